"""The onboard daemon's TOML configuration (``trundle daemon --config robot.toml``), validated.

Device tables use the same layout as ``trundle record --config``: ``[lrf]``, ``[can]`` and
``[camera]`` each hold a ``url`` and the driver's own options, passed to the driver unchanged
(the driver checks them); a list of tables (``[[camera]]``) declares several devices of one
family, each with its own ``name``. Everything else is the daemon's and is checked here: a wrong
key or value is a ``UserError`` of one line naming the key. See ``tools/daemon/example.toml``.
"""

from __future__ import annotations

import json
import math
import os
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from trundle.drivers.devices import FAMILIES
from trundle.logs.errors import UserError

DEVICE_KEYS = {"url", "enabled", "name"}  # read by the daemon; every other key goes to the driver
ACTIONS = ("delete_oldest", "stop")
COMPRESSIONS = ("zstd", "lz4", "none")


def default_socket_path() -> Path:
    """Where the status socket lives: systemd's RuntimeDirectory, else $XDG_RUNTIME_DIR/trundle,
    else /tmp/trundle-<uid>."""
    runtime = os.environ.get("RUNTIME_DIRECTORY")
    if runtime:
        return Path(runtime.split(":")[0]) / "status.sock"
    xdg = os.environ.get("XDG_RUNTIME_DIR")
    if xdg:
        return Path(xdg) / "trundle" / "status.sock"
    return Path(f"/tmp/trundle-{os.getuid()}") / "status.sock"


@dataclass(frozen=True)
class Device:
    """One device: ``family`` (lrf, can, camera), a unique ``name``, its URL and driver options."""

    family: str
    name: str
    url: str
    options: dict[str, Any]


@dataclass(frozen=True)
class StaticTransform:
    """``child`` in ``parent``: translation (m) and roll, pitch, yaw (rad)."""

    parent: str
    child: str
    xyz: tuple[float, float, float]
    rpy: tuple[float, float, float]


@dataclass(frozen=True)
class LoggerConfig:
    folder: Path
    prefix: str = "trundle"
    record: bool = True
    compression: str = "zstd"
    chunk_size_kb: int = 1024
    flush_period_s: float = 0.5
    fsync: bool = False
    split_size_mb: float = 0.0
    split_duration_s: float = 0.0
    queue_size: int = 10000


@dataclass(frozen=True)
class DiskConfig:
    min_free_mb: float = 1024.0
    action: str = "delete_oldest"
    check_period_s: float = 2.0
    resume_margin: float = 0.1


@dataclass(frozen=True)
class ProcessingConfig:
    odometry: bool = True
    slam: bool = False
    markers: bool = False
    map_period_s: float = 5.0
    markers_hz: float = 2.0
    marker_size_m: float = 0.25
    aruco_dictionary: str = "DICT_6X6_250"
    queue_size: int = 2000


@dataclass(frozen=True)
class StatusConfig:
    socket: Path = field(default_factory=default_socket_path)
    diagnostics_period_s: float = 1.0


@dataclass(frozen=True)
class SupervisionConfig:
    restart_delay_s: float = 1.0
    max_restart_delay_s: float = 30.0
    stop_timeout_s: float = 5.0


@dataclass(frozen=True)
class LiveConfig:
    enabled: bool = False
    host: str = "127.0.0.1"
    port: int = 8765


@dataclass(frozen=True)
class FramesConfig:
    map: str = "map"
    odom: str = "odom"
    base: str = "base_link"


@dataclass(frozen=True)
class DaemonConfig:
    """Everything ``trundle daemon`` needs, checked."""

    robot: str
    devices: tuple[Device, ...]
    frames: FramesConfig
    transforms: tuple[StaticTransform, ...]
    logger: LoggerConfig
    disk: DiskConfig
    processing: ProcessingConfig
    status: StatusConfig
    supervision: SupervisionConfig
    slam: dict[str, Any]
    live: LiveConfig = LiveConfig()
    source: str = ""


def _where(source: str, key: str) -> str:
    return f"{source}: {key}" if source else key


def _key(key: str) -> str:
    """A TOML key as the message shows it: bare when plain, quoted otherwise (one line always)."""
    return key if key.replace("_", "").replace("-", "").isalnum() else repr(key)


def _typed(value: Any, expected: Any, key: str, source: str) -> Any:
    """``value`` converted to the type of ``expected`` (the default), or a UserError naming ``key``."""
    bad = UserError(f"{_where(source, key)} = {value!r}: expected {_type_name(expected)}")
    if isinstance(expected, bool):
        if not isinstance(value, bool):
            raise bad
        return value
    if isinstance(expected, (int, float)):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
            raise bad
        if isinstance(expected, int) and not isinstance(expected, bool):
            if value != int(value):
                raise bad
            return int(value)
        return float(value)
    if isinstance(expected, (str, Path)):
        if not isinstance(value, str) or not value:
            raise bad
        return Path(value).expanduser() if isinstance(expected, Path) else value
    raise AssertionError(expected)


def _type_name(expected: Any) -> str:
    if isinstance(expected, bool):
        return "true or false"
    if isinstance(expected, int):
        return "a whole number >= 0"
    if isinstance(expected, float):
        return "a number >= 0"
    return "a path" if isinstance(expected, Path) else "a string"


def _table(data: dict[str, Any], name: str, source: str) -> dict[str, Any]:
    value = data.get(name, {})
    if not isinstance(value, dict):
        raise UserError(f"{_where(source, name)}: expected a table [{name}]")
    return value


def _build(cls: type, table: dict[str, Any], name: str, source: str, **required: Any) -> Any:
    """A config dataclass from a TOML table: unknown keys and wrong types name the key."""
    defaults = cls(**required) if required else cls()
    known = {f for f in cls.__dataclass_fields__}
    values = dict(required)
    for key, value in table.items():
        if key not in known:
            raise UserError(f"{_where(source, f'unknown key {name}.{_key(key)}')} "
                            f"(known in [{name}]: {', '.join(sorted(known))})")
        values[key] = _typed(value, getattr(defaults, key), f"{name}.{key}", source)
    return cls(**values)


def _devices(data: dict[str, Any], source: str) -> tuple[Device, ...]:
    devices: list[Device] = []
    for family in FAMILIES:
        value = data.get(family)
        if value is None:
            continue
        tables = value if isinstance(value, list) else [value]
        for i, table in enumerate(tables):
            key = family if not isinstance(value, list) else f"{family}[{i}]"
            if not isinstance(table, dict):
                raise UserError(f"{_where(source, key)}: expected a table [{family}] or [[{family}]]")
            url = table.get("url")
            if not isinstance(url, str) or not url:
                raise UserError(f"{_where(source, key + '.url')}: missing (the device URL, as for trundle record --{family})")
            enabled = table.get("enabled", True)
            if not isinstance(enabled, bool):
                raise UserError(f"{_where(source, key + '.enabled')} = {enabled!r}: expected true or false")
            name = table.get("name", family if not isinstance(value, list) else f"{family}{i}")
            if not isinstance(name, str) or not name:
                raise UserError(f"{_where(source, key + '.name')} = {name!r}: expected a string")
            if any(d.name == name for d in devices):
                raise UserError(f"{_where(source, key + '.name')}: two devices are named {name!r}")
            if enabled:
                options = {k: v for k, v in table.items() if k not in ("url", "enabled")}
                devices.append(Device(family, name, url, options))
    return tuple(devices)


def _transforms(data: dict[str, Any], source: str) -> tuple[StaticTransform, ...]:
    value = data.get("transforms", [])
    if not isinstance(value, list):
        raise UserError(f"{_where(source, 'transforms')}: expected [[transforms]] tables")
    out = []
    for i, table in enumerate(value):
        key = f"transforms[{i}]"
        if not isinstance(table, dict):
            raise UserError(f"{_where(source, key)}: expected a table")
        unknown = sorted(set(table) - {"parent", "child", "xyz", "rpy"})
        if unknown:
            raise UserError(f"{_where(source, f'unknown key {key}.{_key(unknown[0])}')} (known: child, parent, rpy, xyz)")
        names = []
        for part in ("parent", "child"):
            if not isinstance(table.get(part), str) or not table[part]:
                raise UserError(f"{_where(source, f'{key}.{part}')}: missing frame name")
            names.append(table[part])
        triples = []
        for part in ("xyz", "rpy"):
            triple = table.get(part, [0.0, 0.0, 0.0])
            if not (isinstance(triple, list) and len(triple) == 3 and all(
                    isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in triple)):
                raise UserError(f"{_where(source, f'{key}.{part}')} = {triple!r}: expected three numbers")
            triples.append(tuple(float(v) for v in triple))
        out.append(StaticTransform(names[0], names[1], triples[0], triples[1]))
    return tuple(out)


TOP_LEVEL = {"robot", "frames", "transforms", "logger", "disk", "processing", "status", "supervision", "slam",
             "live", *FAMILIES}


def parse_config(data: dict[str, Any], source: str = "") -> DaemonConfig:
    """Check a decoded TOML document and build the daemon's configuration."""
    unknown = sorted(set(data) - TOP_LEVEL)
    if unknown:
        raise UserError(f"{_where(source, f'unknown key {_key(unknown[0])}')} (known tables: {', '.join(sorted(TOP_LEVEL))})")
    robot_table = _table(data, "robot", source)
    unknown = sorted(set(robot_table) - {"name"})
    if unknown:
        raise UserError(f"{_where(source, f'unknown key robot.{_key(unknown[0])}')} (known in [robot]: name)")
    robot = _typed(robot_table.get("name", "trundle"), "", "robot.name", source)
    logger_table = _table(data, "logger", source)
    if "folder" not in logger_table:
        raise UserError(f"{_where(source, 'logger.folder')}: missing (where the logs go)")
    folder = _typed(logger_table["folder"], Path(), "logger.folder", source)
    logger = _build(LoggerConfig, {k: v for k, v in logger_table.items() if k != "folder"}, "logger", source,
                    folder=folder)
    if "prefix" not in logger_table:
        logger = LoggerConfig(**{**logger.__dict__, "prefix": robot})
    if logger.compression not in COMPRESSIONS:
        raise UserError(f"{_where(source, 'logger.compression')} = {logger.compression!r}: "
                        f"expected one of {', '.join(COMPRESSIONS)}")
    disk = _build(DiskConfig, _table(data, "disk", source), "disk", source)
    if disk.action not in ACTIONS:
        raise UserError(f"{_where(source, 'disk.action')} = {disk.action!r}: expected one of {', '.join(ACTIONS)}")
    processing = _build(ProcessingConfig, _table(data, "processing", source), "processing", source)
    status = _build(StatusConfig, _table(data, "status", source), "status", source)
    supervision = _build(SupervisionConfig, _table(data, "supervision", source), "supervision", source)
    frames = _build(FramesConfig, _table(data, "frames", source), "frames", source)
    devices = _devices(data, source)
    if not devices:
        raise UserError(f"{_where(source, 'no device')}: add an [lrf], [can] or [camera] table with a url")
    slam = _table(data, "slam", source)
    from trundle.fusion.slam import SlamConfig  # SciPy: not for every `trundle status`

    try:
        SlamConfig.from_mapping(slam)  # checked even while SLAM is off, so a typo shows at once
    except UserError as error:
        raise UserError(f"{_where(source, str(error))}") from None
    live = _build(LiveConfig, _table(data, "live", source), "live", source)
    if not 0 <= live.port <= 65535:
        raise UserError(f"{_where(source, 'live.port')} = {live.port}: expected a TCP port 0-65535")
    return DaemonConfig(robot, devices, frames, _transforms(data, source), logger, disk, processing, status,
                        supervision, slam, live, source)


def load_config(path: str | os.PathLike[str]) -> DaemonConfig:
    """Read and check ``path``; a missing file, bad TOML or a bad key is one UserError line."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            data = tomllib.load(f)
    except FileNotFoundError:
        raise UserError(f"config file not found: {path}") from None
    except tomllib.TOMLDecodeError as error:
        raise UserError(f"{path}: not valid TOML ({error})") from None
    return parse_config(data, str(path))


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, (str, Path)):
        return json.dumps(str(value), ensure_ascii=False).replace("\x7f", "\\u007f")  # a valid TOML basic string
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    raise TypeError(f"cannot write {type(value).__name__} to TOML")


def format_config(tables: dict[str, Any]) -> str:
    """TOML text for ``{table: {key: value}}`` (lists of tables as ``[[table]]``): how the demo
    and tests write a daemon configuration; ``parse_config(tomllib.loads(text))`` reads it back."""
    lines: list[str] = []
    for name, table in tables.items():
        for item in table if isinstance(table, list) else [table]:
            lines.append(f"[[{name}]]" if isinstance(table, list) else f"[{name}]")
            nested = {k: v for k, v in item.items() if isinstance(v, dict)}
            lines += [f"{key} = {_toml_value(value)}" for key, value in item.items() if key not in nested]
            for key, sub in nested.items():
                lines.append(f"[{name}.{key}]")
                lines += [f"{k} = {_toml_value(v)}" for k, v in sub.items()]
            lines.append("")
    return "\n".join(lines)
