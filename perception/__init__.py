"""Image and 2-D scan features: plain functions over numpy arrays."""
