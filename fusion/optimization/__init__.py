"""Optimisation: the sparse Levenberg-Marquardt core, robust kernels, pose and factor graphs."""
