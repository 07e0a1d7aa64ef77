"""The robot model a job uses: the wheel model and laser mount from the job's config (a robot
config, :mod:`trundle.tools.config.robot`) or from the log's own description.

``[odometry]`` holds the wheel model (``wheel_radius_m``, ``track_m``, ``wheels = [left, right]``,
``wheel_variance_per_m``), ``[laser]`` the laser mount on the robot (``x_m``, ``y_m`` in metres,
``yaw_rad``); ``trundle slam`` and ``trundle localize`` read the same file the daemon does.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from trundle.fusion.odometry.diff_drive import DiffDriveOdometry, odometry_from_config
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


def wheel_model(info: LogInfo, config: JobConfig) -> tuple[Mapping[str, Any] | None, str]:
    """The wheel model for ``info``'s log and where it comes from: the config's ``[odometry]``
    table, its ``[can]`` table, else the log's own description
    (:meth:`trundle.logs.metadata.LogMetadata.wheel_model`: what the importers, the recorder and
    the daemon store); ``(None, "")`` without one."""
    config = robot_config(config)
    can = config.options("can") if any(d.family == "can" for d in config.devices) else {}
    for model, where in ((config.odometry, "the config's [odometry]"), (can, "the config's [can]"),
                         (read_metadata(info.metadata).wheel_model(), "the log's metadata")):
        if model and ("wheel_radius_m" in model or "track_m" in model):
            return model, where
    return None, ""


def _topics(info: LogInfo, ros_type: str) -> list[str]:
    return sorted(name for name, t in info.topics.items() if t.ros_type == ros_type)


def make_odometry(info: LogInfo, config: JobConfig) -> DiffDriveOdometry | None:
    """Wheel odometry for a log with wheel joint states (wheel model: :func:`wheel_model`); None if
    it has none, or only ``Odometry``; a UserError for wheel states without a wheel model."""
    if not _topics(info, "sensor_msgs/msg/JointState"):
        return None
    model, _ = wheel_model(info, config)
    if model is not None:
        return odometry_from_config(model)
    if _topics(info, "nav_msgs/msg/Odometry"):
        return None
    raise UserError("the log has wheel joint states but no wheel model: give wheel_radius_m and track_m "
                    "in the [odometry] table of --config")


def odometry_source(info: LogInfo, config: JobConfig, wheels: DiffDriveOdometry | None) -> str:
    """What a job's odometry is, in words: the wheel encoders (and where their model came from),
    the log's odometry messages (and, for an imported log, what the importer made them of), or ""
    when the log has none (the job then runs on the laser alone)."""
    if wheels is not None:
        return (f"wheel encoders ({', '.join(_topics(info, 'sensor_msgs/msg/JointState'))}; "
                f"wheel model from {wheel_model(info, config)[1]})")
    topics = _topics(info, "nav_msgs/msg/Odometry")
    if not topics:
        return ""
    made = read_metadata(info.metadata).fields.get("odometry_description", "")
    return f"odometry messages ({', '.join(topics)})" + (f": {made}" if made else "")


def laser_pose(info: LogInfo, config: JobConfig) -> tuple[float, float, float] | None:
    """The laser mount (x m, y m, yaw rad): the ``[laser]`` table, else the log's ``robot`` metadata
    (``laser_x_m``, ``laser_y_m``, ``laser_yaw_rad``), else None (then the log's /tf_static, or the identity)."""
    config = robot_config(config)
    return config.laser if config.laser is not None else read_metadata(info.metadata).laser_mount()
