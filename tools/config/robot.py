"""The robot configuration (``robot.toml``), checked: one model and one validator for every
command that reads it: ``trundle daemon`` (and ``--check``), ``trundle record --config``,
``trundle slam --config`` and ``trundle localize --config``.

Tables (``example.toml`` has them all; ``trundle daemon --print-example-config`` prints it):

- ``[lrf]``, ``[can]``, ``[camera]`` (or lists ``[[camera]]``, each with its own ``name``): a
  device's ``url`` and its driver's options, checked by building the driver (no device is
  opened), so a bad URL or option is found before anything runs;
- ``[robot]``, ``[frames]``, ``[[transforms]]``, ``[logger]``, ``[disk]``, ``[processing]``,
  ``[status]``, ``[supervision]``, ``[live]``: the daemon's own;
- ``[slam]``: :class:`trundle.fusion.slam.config.SlamConfig` options; ``[odometry]``: the wheel model
  ``slam`` and ``localize`` use instead of the log's (``wheel_radius_m``, ``track_m``, ``wheels``,
  ``wheel_variance_per_m``); ``[laser]``: the laser mount (``x_m``, ``y_m``, ``yaw_rad``).

Every table and key is known: a misspelt one, a wrong type or an impossible value is a
``UserError`` of one line naming the key, whichever command reads the file. :func:`parse_config`
checks the document; :func:`check_daemon_config` checks what the daemon needs besides (every
device has a URL, the log folder can be written on a real disk, the live view's extra is
installed). The daemon runs both, and ``trundle daemon --check`` runs exactly the same.
"""

from __future__ import annotations

import importlib.util
import math
import os
import tomllib
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

from trundle.drivers.devices import FAMILIES, make_driver
from trundle.fusion.odometry.diff_drive import odometry_from_config
from trundle.logs.errors import UserError
from trundle.logs.paths import read_text

ACTIONS = ("delete_oldest", "stop")
COMPRESSIONS = ("zstd", "lz4", "none")
ODOMETRY_KEYS = ("wheel_radius_m", "track_m", "wheels", "wheel_variance_per_m")
LASER_KEYS = ("x_m", "y_m", "yaw_rad")


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
    """One device: ``family`` (lrf, can, camera), a unique ``name``, its URL ("" when the table
    gives only options, e.g. for ``trundle record --lrf URL --config``) and driver options."""

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
    """``[logger]``: where and how the daemon logs (``folder`` None: not given)."""

    folder: Path | None = None
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


# options that must be above zero (a period, a rate, a size); every other number must be >= 0
POSITIVE = {"chunk_size_kb", "flush_period_s", "queue_size", "check_period_s", "map_period_s", "markers_hz",
            "marker_size_m", "diagnostics_period_s", "restart_delay_s", "max_restart_delay_s", "stop_timeout_s"}


@dataclass(frozen=True)
class RobotConfig:
    """A checked robot configuration (``source``: the file it came from)."""

    robot: str = "trundle"
    devices: tuple[Device, ...] = ()
    frames: FramesConfig = FramesConfig()
    transforms: tuple[StaticTransform, ...] = ()
    logger: LoggerConfig = LoggerConfig()
    disk: DiskConfig = DiskConfig()
    processing: ProcessingConfig = ProcessingConfig()
    status: StatusConfig = field(default_factory=StatusConfig)
    supervision: SupervisionConfig = SupervisionConfig()
    slam: dict[str, Any] = field(default_factory=dict)
    odometry: dict[str, Any] = field(default_factory=dict)
    laser: tuple[float, float, float] | None = None
    live: LiveConfig = LiveConfig()
    source: str = ""
    landmarks: dict[str, Any] = field(default_factory=dict)

    def options(self, family: str) -> dict[str, Any]:
        """The driver options of the one device of ``family`` (without its name), {} if there is
        none; several are a UserError (which of them a command-line URL means is unclear)."""
        tables = [d for d in self.devices if d.family == family]
        if len(tables) > 1:
            raise UserError(f"{_where(self.source, family)}: {len(tables)} [[{family}]] tables; "
                            f"which one goes with the --{family} URL?")
        return {k: v for k, v in tables[0].options.items() if k != "name"} if tables else {}


def _where(source: str, key: str) -> str:
    return f"{source}: {key}" if source else key


def _key(key: str) -> str:
    """A TOML key as the message shows it: bare when plain, quoted otherwise (one line always)."""
    return key if key.replace("_", "").replace("-", "").isalnum() else repr(key)


def _typed(value: Any, expected: Any, key: str, source: str, positive: bool = False) -> Any:
    """``value`` converted to the type of ``expected`` (the default), or a UserError naming ``key``;
    a number must be finite and >= 0 (> 0 when ``positive``)."""
    bad = UserError(f"{_where(source, key)} = {value!r}: expected {_type_name(expected, positive)}")
    if isinstance(expected, bool):
        if not isinstance(value, bool):
            raise bad
        return value
    if isinstance(expected, (int, float)):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
            raise bad
        if positive and value <= 0:
            raise bad
        if isinstance(expected, int):
            if value != int(value):
                raise bad
            return int(value)
        return float(value)
    if isinstance(expected, (str, Path)) or expected is None:
        if not isinstance(value, str) or not value:
            raise bad
        return Path(value).expanduser() if isinstance(expected, Path) or expected is None else value
    raise AssertionError(expected)


def _type_name(expected: Any, positive: bool = False) -> str:
    if isinstance(expected, bool):
        return "true or false"
    if isinstance(expected, int):
        return f"a whole number {'> 0' if positive else '>= 0'}"
    if isinstance(expected, float):
        return f"a number {'> 0' if positive else '>= 0'}"
    return "a path" if isinstance(expected, Path) or expected is None else "a string"


def _table(data: dict[str, Any], name: str, source: str) -> dict[str, Any]:
    value = data.get(name, {})
    if not isinstance(value, dict):
        raise UserError(f"{_where(source, name)}: expected a table [{name}]")
    return value


def _build(cls: type, table: dict[str, Any], name: str, source: str) -> Any:
    """A config dataclass from a TOML table: unknown keys, wrong types and values name the key."""
    defaults = cls()
    known = {f.name for f in fields(cls)}
    values = {}
    for key, value in table.items():
        if key not in known:
            raise UserError(f"{_where(source, f'unknown key {name}.{_key(key)}')} "
                            f"(known in [{name}]: {', '.join(sorted(known))})")
        values[key] = _typed(value, getattr(defaults, key), f"{name}.{key}", source, key in POSITIVE)
    return cls(**values)


def _discard(topic: str, msg: object, log_time_ns: int) -> None:
    """The sink of a driver built only to check its options."""


def check_device(family: str, url: str, options: dict[str, Any], where: str) -> None:
    """Build the driver for ``url`` with ``options`` (no device is opened) and check its wheel
    model: the driver's own checks, as a UserError naming ``where`` (``robot.toml: lrf``)."""
    try:
        make_driver(family, url, _discard, dict(options))
        if family == "can":
            odometry_from_config(options)
    except UserError as error:
        raise UserError(f"{where}: {error}") from None
    except (TypeError, ValueError, KeyError) as error:  # an option of a shape the driver did not expect
        raise UserError(f"{where}: bad option ({type(error).__name__}: {error})") from None


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
            url = table.get("url", "")
            if not isinstance(url, str):
                raise UserError(f"{_where(source, key + '.url')} = {url!r}: expected the device URL as a string")
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
                if url:
                    check_device(family, url, options, _where(source, key))
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
            if not (isinstance(triple, list) and len(triple) == 3 and all(_number(v) for v in triple)):
                raise UserError(f"{_where(source, f'{key}.{part}')} = {triple!r}: expected three numbers")
            triples.append(tuple(float(v) for v in triple))
        out.append(StaticTransform(names[0], names[1], triples[0], triples[1]))
    return tuple(out)


def _number(value: Any) -> bool:
    """A finite TOML number (not a boolean)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _odometry(data: dict[str, Any], source: str) -> dict[str, Any]:
    table = _table(data, "odometry", source)
    unknown = sorted(set(table) - set(ODOMETRY_KEYS))
    if unknown:
        raise UserError(f"{_where(source, f'unknown key odometry.{_key(unknown[0])}')} "
                        f"(known in [odometry]: {', '.join(ODOMETRY_KEYS)})")
    try:
        if table:
            odometry_from_config(table)
    except (UserError, TypeError) as error:
        raise UserError(f"{_where(source, 'odometry')}: {error}") from None
    return dict(table)


def _laser(data: dict[str, Any], source: str) -> tuple[float, float, float] | None:
    table = _table(data, "laser", source)
    unknown = sorted(set(table) - set(LASER_KEYS))
    if unknown:
        raise UserError(f"{_where(source, f'unknown key laser.{_key(unknown[0])}')} "
                        f"(known in [laser]: {', '.join(LASER_KEYS)})")
    for key, value in table.items():
        if not _number(value):
            raise UserError(f"{_where(source, f'laser.{key}')} = {value!r}: expected a number (m or rad)")
    return tuple(float(table.get(k, 0.0)) for k in LASER_KEYS) if table else None  # type: ignore[return-value]


TOP_LEVEL = {"robot", "frames", "transforms", "logger", "disk", "processing", "status", "supervision", "slam",
             "odometry", "laser", "landmarks", "live", *FAMILIES}


def parse_config(data: dict[str, Any], source: str = "") -> RobotConfig:
    """Check a decoded TOML document and build the configuration (``source`` names it in errors)."""
    unknown = sorted(set(data) - TOP_LEVEL)
    if unknown:
        raise UserError(f"{_where(source, f'unknown key {_key(unknown[0])}')} (known tables: {', '.join(sorted(TOP_LEVEL))})")
    robot_table = _table(data, "robot", source)
    unknown = sorted(set(robot_table) - {"name"})
    if unknown:
        raise UserError(f"{_where(source, f'unknown key robot.{_key(unknown[0])}')} (known in [robot]: name)")
    robot = _typed(robot_table.get("name", "trundle"), "", "robot.name", source)
    logger_table = _table(data, "logger", source)
    logger = _build(LoggerConfig, logger_table, "logger", source)
    if "prefix" not in logger_table:
        logger = LoggerConfig(**{**logger.__dict__, "prefix": robot})
    if logger.compression not in COMPRESSIONS:
        raise UserError(f"{_where(source, 'logger.compression')} = {logger.compression!r}: "
                        f"expected one of {', '.join(COMPRESSIONS)}")
    disk = _build(DiskConfig, _table(data, "disk", source), "disk", source)
    if disk.action not in ACTIONS:
        raise UserError(f"{_where(source, 'disk.action')} = {disk.action!r}: expected one of {', '.join(ACTIONS)}")
    processing = _build(ProcessingConfig, _table(data, "processing", source), "processing", source)
    from trundle.perception.markers import dictionary_by_name  # OpenCV: only once a config is read

    try:
        dictionary_by_name(processing.aruco_dictionary)
    except UserError as error:
        raise UserError(f"{_where(source, 'processing.aruco_dictionary')}: {error}") from None
    status = _build(StatusConfig, _table(data, "status", source), "status", source)
    supervision = _build(SupervisionConfig, _table(data, "supervision", source), "supervision", source)
    frames = _build(FramesConfig, _table(data, "frames", source), "frames", source)
    devices = _devices(data, source)
    slam = _table(data, "slam", source)
    from trundle.fusion.slam.config import SlamConfig  # pydantic: only once a config is read

    try:
        SlamConfig.from_mapping(slam)  # checked even while SLAM is off, so a typo shows at once
    except UserError as error:
        raise UserError(f"{_where(source, str(error))}") from None
    landmarks = _table(data, "landmarks", source)
    from trundle.fusion.slam.landmark_slam import landmark_configs

    try:
        landmark_configs(landmarks)
    except UserError as error:
        raise UserError(f"{_where(source, str(error))}") from None
    live = _build(LiveConfig, _table(data, "live", source), "live", source)
    if not 0 <= live.port <= 65535:
        raise UserError(f"{_where(source, 'live.port')} = {live.port}: expected a TCP port 0-65535")
    return RobotConfig(robot, devices, frames, _transforms(data, source), logger, disk, processing, status,
                       supervision, dict(slam), _odometry(data, source), _laser(data, source), live, source,
                       dict(landmarks))


def _check_folder(folder: Path, where: str) -> None:
    """The log folder exists as a writable folder on a disk, or can be made: else a UserError."""
    existing = folder
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        made = "" if existing == folder else f" (so {folder} cannot be made)"
        raise UserError(f"{where} = {str(folder)!r}: {existing} is not a folder{made}")
    try:
        disk = os.statvfs(existing)
    except OSError as error:
        raise UserError(f"{where} = {str(folder)!r}: cannot look at {existing}: {error.strerror}") from None
    if disk.f_blocks == 0:
        raise UserError(f"{where} = {str(folder)!r}: {existing} is on a virtual file system (like /proc), not a disk")
    if not os.access(existing, os.W_OK | os.X_OK):
        what = "write in" if existing == folder else "make a folder in"
        raise UserError(f"{where} = {str(folder)!r}: no permission to {what} {existing}")


def check_daemon_config(config: RobotConfig) -> None:
    """What the daemon needs beyond a valid document: a log folder it can write on a disk, a URL
    for every device, at least one device, the live view's extra if it is enabled."""
    source = config.source
    if config.logger.folder is None:
        raise UserError(f"{_where(source, 'logger.folder')}: missing (where the logs go)")
    _check_folder(config.logger.folder, _where(source, "logger.folder"))
    if not config.devices:
        raise UserError(f"{_where(source, 'no device')}: add an [lrf], [can] or [camera] table with a url")
    for device in config.devices:
        if not device.url:
            raise UserError(f"{_where(source, device.family + '.url')}: missing (the device URL, as for "
                            f"trundle record --{device.family})")
    if config.live.enabled and importlib.util.find_spec("foxglove") is None:
        raise UserError(f"{_where(source, 'live.enabled')}: the live view needs the optional extra: "
                        "pip install 'trundle[live]' (foxglove-sdk)")


def read_toml(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The TOML document at ``path``; a missing, unreadable or invalid file is one UserError line."""
    path = Path(path)
    if not path.exists():
        raise UserError(f"config file not found: {path}")
    try:
        return tomllib.loads(read_text(path, "TOML config file"))
    except tomllib.TOMLDecodeError as error:
        raise UserError(f"{path}: not valid TOML ({error})") from None


def load_config(path: str | os.PathLike[str] | None) -> RobotConfig:
    """Read and check the config at ``path`` (None: the empty config, every default)."""
    if path is None:
        return RobotConfig()
    return parse_config(read_toml(path), str(path))
