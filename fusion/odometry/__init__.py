"""Odometry: wheel odometry, increments and their noise, motion models, checks and faults."""
