"""Evaluation: trajectory errors against references, sensor characteristics."""
