"""The robot model a job uses: the wheel model and laser mount from the job's config (a robot
config, :mod:`trundle.tools.config.robot`) or from the log's own description.

``[odometry]`` holds the wheel model (``wheel_radius_m``, ``track_m``, ``wheels = [left, right]``,
``wheel_variance_per_m``), ``[laser]`` the laser mount on the robot (``x_m``, ``y_m`` in metres,
``yaw_rad``); ``trundle slam`` and ``trundle localize`` read the same file the daemon does.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from trundle.fusion.odometry import DiffDriveOdometry, odometry_from_config
from trundle.logs.errors import UserError
from trundle.logs.metadata import read_metadata
from trundle.logs.reader import LogInfo
from trundle.tools.config.robot import RobotConfig, parse_config

JobConfig = RobotConfig | Mapping[str, Any] | None
"""What a job takes as its config: a checked robot config, a decoded TOML document (checked here), or none."""


def robot_config(config: JobConfig) -> RobotConfig:
    """``config`` as a checked :class:`RobotConfig` (a document goes through the one validator)."""
    if config is None:
        return RobotConfig()
    if isinstance(config, RobotConfig):
        return config
    return parse_config(dict(config))


def make_odometry(info: LogInfo, config: JobConfig) -> DiffDriveOdometry | None:
    """Wheel odometry for a log with wheel joint states; None if it has none (or only ``Odometry``).

    The wheel model comes from the first of: the config's ``[odometry]`` table, its ``[can]``
    table, the log's own description (:meth:`trundle.logs.metadata.LogMetadata.wheel_model`:
    the robot model the importers, the recorder and the daemon store).
    """
    if not any(t.ros_type == "sensor_msgs/msg/JointState" for t in info.topics.values()):
        return None
    config = robot_config(config)
    can = config.options("can") if any(d.family == "can" for d in config.devices) else {}
    for source in (config.odometry, can, read_metadata(info.metadata).wheel_model()):
        odometry = odometry_from_config(source) if source else None
        if odometry is not None:
            return odometry
    if any(t.ros_type == "nav_msgs/msg/Odometry" for t in info.topics.values()):
        return None
    raise UserError("the log has wheel joint states but no wheel model: give wheel_radius_m and track_m "
                    "in the [odometry] table of --config")


def laser_pose(info: LogInfo, config: JobConfig) -> tuple[float, float, float] | None:
    """The laser mount (x m, y m, yaw rad): the ``[laser]`` table, else the log's ``robot`` metadata
    (``laser_x_m``, ``laser_y_m``, ``laser_yaw_rad``), else None (then the log's /tf_static, or the identity)."""
    config = robot_config(config)
    return config.laser if config.laser is not None else read_metadata(info.metadata).laser_mount()
