"""Odometry, scan matching, maps, filters, pose graph, SLAM and evaluation."""
