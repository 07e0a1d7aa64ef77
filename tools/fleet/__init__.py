"""Many logs through one one-log job on a Ray cluster: one Ray task per log, a table of results.

``trundle fleet JOB LOGS... -o OUT`` (:mod:`trundle.tools.cli.fleet`) is the command; the jobs are
the plain functions of :mod:`trundle.tools.jobs`, run unchanged on the workers. See docs/fleet.md.
"""
