"""The topic names trundle publishes and reads (ROS conventions where there is one): the one place
they are spelt, so a driver, a job and the daemon cannot disagree on a name.

A camera's topics hang under its namespace (``/`` + its ``name``, ``/camera`` by default):
``NS/image_raw/compressed``, ``NS/image_raw`` and ``NS/camera_info``.
"""

from __future__ import annotations

TF_TOPIC = "/tf"                                    # tf2_msgs/TFMessage: moving frames (odom -> base_link, map -> odom)
TF_STATIC_TOPIC = "/tf_static"                      # tf2_msgs/TFMessage, latched: where the sensors sit (REP 105)
SCAN_TOPIC = "/scan"                                # sensor_msgs/LaserScan of the laser
SCAN_TIMING_TOPIC = "/scan/timing"                  # the SCIP laser's raw timestamps, one per scan
REAR_SCAN_TOPIC = "/scan_rear"                      # a second, rear-facing laser (CARMEN logs)
ODOM_TOPIC = "/odom"                                # nav_msgs/Odometry: wheel odometry
WHEELS_TOPIC = "/wheels"                            # sensor_msgs/JointState: the wheel encoders of the CAN driver
JOINT_STATES_TOPIC = "/joint_states"                # sensor_msgs/JointState: ROS's default wheel topic
CAN_RX_TOPIC = "/can/rx"                            # every CAN frame received
IMAGE_TOPIC = "/camera/image_raw/compressed"        # the default camera's JPEG frames
CAMERA_INFO_TOPIC = "/camera/camera_info"           # the default camera's calibration, latched
DIAGNOSTICS_TOPIC = "/diagnostics"                  # diagnostic_msgs/DiagnosticArray of drivers and daemon
SLAM_POSE_TOPIC = "/slam/pose"                      # the online SLAM's pose of each scan (map frame)
MAP_TOPIC = "/map"                                  # nav_msgs/OccupancyGrid
PATH_TOPIC = "/path"                                # nav_msgs/Path: the SLAM trajectory
LANDMARK_TOPIC = "/landmarks"                       # trundle_msgs/LandmarkList: landmark sightings (robot frame)
LANDMARK_MAP_TOPIC = "/landmarks/map"               # visualization_msgs/MarkerArray: the mapped landmarks
SESSION_SCAN_TOPIC = "/session/keyframes/scan"      # sensor_msgs/LaserScan: a session bundle's keyframe scans
SESSION_POSE_TOPIC = "/session/keyframes/pose"      # geometry_msgs/PoseWithCovarianceStamped: their map poses
