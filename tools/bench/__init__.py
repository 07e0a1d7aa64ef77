"""Benchmarks: each prints figures as ratios against a baseline measured in the same run and
writes JSON to bench-results/<name>.json (run all with `make bench`)."""
