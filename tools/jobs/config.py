"""The job config (a TOML file of tables) and the robot model it or the log gives: wheels, laser mount.

``[odometry]`` holds the wheel model (``wheel_radius_m``, ``track_m``, ``wheels = [left, right]``,
``wheel_variance_per_m``), ``[laser]`` the laser mount on the robot (``x_m``, ``y_m`` in metres,
``yaw_rad``); ``trundle slam`` and ``trundle localize`` read the same tables.
"""

from __future__ import annotations

import json
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from trundle.fusion.odometry import DiffDriveOdometry, odometry_from_config
from trundle.logs.errors import UserError
from trundle.logs.reader import LogInfo

ODOMETRY_KEYS = {"wheel_radius_m", "track_m", "wheels", "wheel_variance_per_m"}
LASER_KEYS = {"x_m", "y_m", "yaw_rad"}


def load_config(path: Path | None) -> dict[str, Any]:
    """The TOML config as a dict ({} without a path); unreadable or invalid files are a UserError."""
    if path is None:
        return {}
    if not path.is_file():
        raise UserError(f"no such config file: {path}")
    try:
        with open(path, "rb") as f:
            return tomllib.load(f)
    except tomllib.TOMLDecodeError as error:
        raise UserError(f"{path}: invalid TOML ({error})") from None


def config_table(config: Mapping[str, Any], name: str, keys: set[str]) -> dict[str, Any]:
    """The ``[name]`` table of ``config`` ({} if absent); a non-table or an option not in ``keys``
    is a UserError, so a misspelt option is said instead of silently ignored."""
    table = config.get(name, {})
    if not isinstance(table, dict):
        raise UserError(f"[{name}] must be a table")
    unknown = set(table) - keys
    if unknown:
        raise UserError(f"unknown [{name}] option(s) {sorted(unknown)} (known: {sorted(keys)})")
    return table


def robot_model(info: LogInfo) -> dict[str, Any]:
    """The robot model an importer stores as ``robot`` metadata (JSON); {} when there is none, or when
    ``robot`` is just the robot's name (as the daemon writes it)."""
    text = info.metadata.get("trundle", {}).get("robot", "") or ""
    try:
        model = json.loads(text) if text.strip().startswith("{") else {}
    except json.JSONDecodeError:
        return {}
    return model if isinstance(model, dict) else {}


def make_odometry(info: LogInfo, config: Mapping[str, Any]) -> DiffDriveOdometry | None:
    """Wheel odometry for a log with wheel joint states; None if it has none (or only ``Odometry``).

    The wheel model comes from the first of: the config's ``[odometry]`` table, the log's
    ``robot`` metadata (written by the importers), the ``[can]`` device table the recorder or
    daemon ran with (``devices`` metadata).
    """
    if not any(t.ros_type == "sensor_msgs/msg/JointState" for t in info.topics.values()):
        return None
    metadata = info.metadata.get("trundle", {})
    devices = json.loads(metadata.get("devices", "{}") or "{}")
    sources = [config_table(config, "odometry", ODOMETRY_KEYS), robot_model(info),
               next((d for d in devices.values() if isinstance(d, dict) and d.get("family") == "can"), {})]
    for source in sources:
        odometry = odometry_from_config(source) if source else None
        if odometry is not None:
            return odometry
    if any(t.ros_type == "nav_msgs/msg/Odometry" for t in info.topics.values()):
        return None
    raise UserError("the log has wheel joint states but no wheel model: give wheel_radius_m and track_m "
                    "in the [odometry] table of --config")


def laser_pose(info: LogInfo, config: Mapping[str, Any]) -> tuple[float, float, float] | None:
    """The laser mount (x m, y m, yaw rad): the ``[laser]`` table, else the log's ``robot`` metadata
    (``laser_x_m``, ``laser_y_m``, ``laser_yaw_rad``), else None (then the log's /tf_static, or the identity)."""
    table = config_table(config, "laser", LASER_KEYS)
    if table:
        return (float(table.get("x_m", 0.0)), float(table.get("y_m", 0.0)), float(table.get("yaw_rad", 0.0)))
    robot = robot_model(info)
    if any(k in robot for k in ("laser_x_m", "laser_y_m", "laser_yaw_rad")):
        return (float(robot.get("laser_x_m", 0.0)), float(robot.get("laser_y_m", 0.0)),
                float(robot.get("laser_yaw_rad", 0.0)))
    return None
