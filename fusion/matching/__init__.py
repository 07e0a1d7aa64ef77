"""Scan matching: correlative search with refinement, and ICP."""
