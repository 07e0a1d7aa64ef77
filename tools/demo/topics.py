"""The topics of the demo's log that the demo reads back: what the daemon's drivers publish them as."""

from __future__ import annotations

SCAN_TOPIC = "/scan"                                # the laser's LaserScan
WHEELS_TOPIC = "/wheels"                            # the wheel encoders' joint states
IMAGE_TOPIC = "/camera/image_raw/compressed"        # the camera's JPEG frames
CAMERA_INFO_TOPIC = "/camera/camera_info"           # the camera's calibration
LANDMARK_TOPIC = "/landmarks"                       # the markers the daemon saw, as landmark observations
