"""Errors a user can cause (bad path, bad config, corrupt file, unknown device).

The command line prints these as one line on stderr and exits non-zero, never a traceback.
"""


class UserError(Exception):
    """A problem with the user's input, reported as one clear line."""
