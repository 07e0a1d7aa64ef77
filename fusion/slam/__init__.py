"""SLAM: the grid SLAM, landmark SLAM (EKF and graph), data association."""
