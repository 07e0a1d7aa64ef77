"""A log's own description (where it came from, the robot that made it), written and read as
structured data: the one module that knows the layout of the ``trundle`` metadata record.

MCAP metadata is a map of strings, so structured values are stored as JSON. Keys:

- ``trundle_version``, ``host``: set by the logger;
- ``command``: what wrote the log (``record``, ``daemon``, ``import carmen``, ``slam``, ...);
- ``robot``: JSON object, the robot's ``name`` and its model: ``wheel_radius_m``, ``track_m``,
  ``wheels`` (left and right joint names), ``wheel_variance_per_m``, and the laser mount
  ``laser_x_m``, ``laser_y_m``, ``laser_yaw_rad`` (metres, radians);
- ``devices``: JSON object, device name -> ``{"family": ..., "url": ..., <driver options>}``;
- ``odometry``: the odometry source a log was made with (importers: ``odom``, ``laser``, ``none``);
- ``recovered_from``: JSON object, the crash file a recovered log was made from: its ``name``,
  ``size_bytes`` and ``mtime_ns`` (:mod:`trundle.logs.recover`: a crash file is recovered once);
- ``log_damage``: JSON object, what the damage of the log a replay read skipped
  (:func:`trundle.logs.reader.damage_dict`, as a report's ``log_damage``; null when it was intact);
- anything else a writer adds (``source``, ``config_file``, ``malformed_lines``, ...): JSON
  when it is not a string (and read back as such when it is a JSON object or array).

Reading never fails on a log written earlier or by someone else: a ``robot`` that is a plain
name and ``devices`` written as ``family=url`` words (what trundle 0.1 wrote) are understood,
and a value that is not valid JSON is kept as text.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from trundle.logs.outputs import json_text

RECORD = "trundle"  # the MCAP metadata record's name
WHEEL_KEYS = ("wheel_radius_m", "track_m", "wheels", "odometry_wheels", "wheel_variance_per_m")
LASER_KEYS = ("laser_x_m", "laser_y_m", "laser_yaw_rad")
STRUCTURED = ("robot", "devices")


def _text(value: object) -> str:
    """A metadata value as stored: strings as they are, anything else as JSON."""
    return value if isinstance(value, str) else json_text(value, sort_keys=True)


def encode(fields: Mapping[str, object]) -> dict[str, str]:
    """The string map stored in the ``trundle`` record for ``fields``; ``robot`` and ``devices``
    are always stored as JSON objects (a ``robot`` given as a plain name becomes ``{"name": ...}``)."""
    fields = dict(fields)
    if isinstance(fields.get("robot"), str):
        fields["robot"] = {"name": fields["robot"]}
    for key in STRUCTURED:
        if key in fields and not isinstance(fields[key], Mapping):
            raise TypeError(f"log metadata {key!r} must be a mapping, got {type(fields[key]).__name__}")
    return {key: _text(value) for key, value in fields.items()}


def _json(text: str) -> Any:
    try:
        return json.loads(text)
    except (json.JSONDecodeError, RecursionError):
        return text


def _robot(text: str) -> dict[str, Any]:
    value = _json(text)
    if isinstance(value, dict):
        return value
    return {"name": text} if text else {}


def _devices(text: str) -> dict[str, dict[str, Any]]:
    value = _json(text)
    if isinstance(value, dict):
        return {str(name): dict(d) for name, d in value.items() if isinstance(d, dict)}
    devices: dict[str, dict[str, Any]] = {}
    for word in text.split():  # trundle 0.1's record: "lrf=scip2:///dev/ttyACM0 can=slcan://..."
        family, sep, url = word.partition("=")
        if sep and family:
            name = family if family not in devices else f"{family}{len(devices)}"
            devices[name] = {"family": family, "url": url}
    return devices


@dataclass(frozen=True)
class LogMetadata:
    """The ``trundle`` record of a log, decoded: ``command``, ``robot`` (name and model),
    ``devices`` (name -> family, url, options) and every other key (``fields``, JSON decoded)."""

    command: str = ""
    robot: Mapping[str, Any] = field(default_factory=dict)
    devices: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    fields: Mapping[str, Any] = field(default_factory=dict)

    @property
    def robot_name(self) -> str:
        name = self.robot.get("name", "")
        return name if isinstance(name, str) else ""

    def wheel_model(self) -> dict[str, Any] | None:
        """The wheel model (``wheel_radius_m``, ``track_m``, ...): the robot's, else the first CAN
        device's options; None when the log has none."""
        sources = [self.robot] + [d for d in self.devices.values() if d.get("family") == "can"]
        for source in sources:
            if "wheel_radius_m" in source or "track_m" in source:
                return {k: source[k] for k in WHEEL_KEYS if k in source}
        return None

    def laser_mount(self) -> tuple[float, float, float] | None:
        """The laser mount on the robot (x m, y m, yaw rad) if the robot model gives it, else None."""
        if not any(k in self.robot for k in LASER_KEYS):
            return None
        try:
            return tuple(float(self.robot.get(k, 0.0)) for k in LASER_KEYS)  # type: ignore[return-value]
        except (TypeError, ValueError):
            return None


def decode(record: Mapping[str, str]) -> LogMetadata:
    """The ``trundle`` metadata record (a string map) as :class:`LogMetadata`."""
    others = {k: _json(v) if isinstance(v, str) and v[:1] in ("{", "[") else v for k, v in record.items()
              if k not in ("command", *STRUCTURED)}
    return LogMetadata(str(record.get("command", "")), _robot(str(record.get("robot", ""))),
                       _devices(str(record.get("devices", ""))), others)


def read_metadata(metadata: Mapping[str, Mapping[str, str]]) -> LogMetadata:
    """The log's own description from all its metadata records (``LogInfo.metadata``)."""
    return decode(metadata.get(RECORD, {}))
