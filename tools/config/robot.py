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
``ConfigError`` of one line naming the key, the value and what was expected, whichever command
reads the file. Each table is a strict model on :mod:`trundle.logs.schema`, declared by its owner
(the daemon's tables here, the wheel model in fusion/odometry, the landmark options in
fusion/slam, each driver's options in drivers/); :class:`RobotDocument` composes them. :func:`parse_config`
checks the document; :func:`check_daemon_config` checks what the daemon needs besides (every
device has a URL, the log folder can be written on a real disk, the live view's extra is
installed). The daemon runs both, and ``trundle daemon --check`` runs exactly the same.
"""

from __future__ import annotations

import importlib.util
import os
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import ConfigDict, Field

from trundle.drivers.devices import FAMILIES, make_driver
from trundle.fusion.odometry.diff_drive import WheelModel, odometry_from_config
from trundle.logs.errors import ConfigError, UserError
from trundle.logs.paths import read_text
from trundle.logs.schema import Name, PathValue, Schema, Triple, parse


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


Positive = Annotated[float, Field(gt=0)]
NonNegative = Annotated[float, Field(ge=0)]
Count = Annotated[int, Field(gt=0)]


class StaticTransform(Schema):
    """``child`` in ``parent``: translation (m) and roll, pitch, yaw (rad)."""

    parent: Name
    child: Name
    xyz: Triple = (0.0, 0.0, 0.0)
    rpy: Triple = (0.0, 0.0, 0.0)


class LoggerConfig(Schema):
    """``[logger]``: where and how the daemon logs (``folder`` None: not given; ``prefix``: the
    robot's name unless given)."""

    folder: PathValue | None = None
    prefix: Name = "trundle"
    record: bool = True
    compression: Literal["zstd", "lz4", "none"] = "zstd"
    chunk_size_kb: Count = 1024
    flush_period_s: Positive = 0.5
    fsync: bool = False
    split_size_mb: NonNegative = 0.0
    split_duration_s: NonNegative = 0.0
    queue_size: Count = 10000


class DiskConfig(Schema):
    """``[disk]``: the free space kept (MB) and what is done below it."""

    min_free_mb: NonNegative = 1024.0
    action: Literal["delete_oldest", "stop"] = "delete_oldest"
    check_period_s: Positive = 2.0
    resume_margin: NonNegative = 0.1


class ProcessingConfig(Schema):
    """``[processing]``: what the daemon computes on board."""

    odometry: bool = True
    slam: bool = False
    markers: bool = False
    map_period_s: Positive = 5.0
    # SLAM behind real time skips the waiting scans older than the newest by more than this (the lag it allows)
    max_scan_lag_s: Positive = 0.2
    markers_hz: Positive = 2.0
    marker_size_m: Positive = 0.25
    aruco_dictionary: Name = "DICT_6X6_250"
    queue_size: Count = 2000


class StatusConfig(Schema):
    """``[status]``: the status socket and how often diagnostics are published (s)."""

    socket: PathValue = Field(default_factory=default_socket_path)
    diagnostics_period_s: Positive = 1.0


class SupervisionConfig(Schema):
    """``[supervision]``: restart delays of a crashed driver thread and the stop timeout (s)."""

    restart_delay_s: Positive = 1.0
    max_restart_delay_s: Positive = 30.0
    stop_timeout_s: Positive = 5.0


class LiveConfig(Schema):
    """``[live]``: the Foxglove WebSocket view."""

    enabled: bool = False
    host: Name = "127.0.0.1"
    port: Annotated[int, Field(ge=0, le=65535)] = 8765


class FramesConfig(Schema):
    """``[frames]``: the names of the map, odometry and robot frames."""

    map: Name = "map"
    odom: Name = "odom"
    base: Name = "base_link"


class RobotTable(Schema):
    """``[robot]``: the robot's name (log file names, /diagnostics)."""

    name: Name = "trundle"


class LaserMount(Schema):
    """``[laser]``: the laser on the robot (m, rad), for ``slam`` and ``localize``."""

    x_m: float = 0.0
    y_m: float = 0.0
    yaw_rad: float = 0.0


class DeviceKeys(Schema):
    """What every device table has besides its driver's options (checked by building the driver)."""

    model_config = ConfigDict(extra="allow")

    url: str = ""
    enabled: bool = True
    name: Name | None = None


class RobotDocument(Schema):
    """The tables of ``robot.toml``, each checked by its owner's model: the daemon's here, the
    wheel model by the odometry's; ``[slam]``, ``[landmarks]`` and the device tables are checked
    after, by :class:`SlamConfig`, :func:`landmark_configs` and the drivers."""

    robot: RobotTable = RobotTable()
    frames: FramesConfig = FramesConfig()
    transforms: list[StaticTransform] = []
    logger: LoggerConfig = LoggerConfig()
    disk: DiskConfig = DiskConfig()
    processing: ProcessingConfig = ProcessingConfig()
    status: StatusConfig = Field(default_factory=StatusConfig)
    supervision: SupervisionConfig = SupervisionConfig()
    live: LiveConfig = LiveConfig()
    slam: dict[str, Any] = {}
    landmarks: dict[str, Any] = {}
    odometry: WheelModel | None = None
    laser: LaserMount | None = None
    lrf: Any = None
    can: Any = None
    camera: Any = None


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
            raise ConfigError(f"{_where(self.source, family)}: {len(tables)} [[{family}]] tables; "
                              f"which one goes with the --{family} URL?")
        return {k: v for k, v in tables[0].options.items() if k != "name"} if tables else {}


def _where(source: str, key: str) -> str:
    return f"{source}: {key}" if source else key


def _discard(topic: str, msg: object, log_time_ns: int) -> None:
    """The sink of a driver built only to check its options."""


def check_device(family: str, url: str, options: dict[str, Any], where: str, key: str = "") -> None:
    """Build the driver for ``url`` with ``options`` (no device is opened) and check the wheel model
    of a ``[can]`` table: the driver's own checks, as a ConfigError naming ``where`` (the file) and
    ``key`` (the table, e.g. ``camera[1]``; default the family)."""
    key = key or family
    try:
        if url:
            make_driver(family, url, _discard, dict(options))
        if family == "can":
            odometry_from_config(options, family)
    except UserError as error:
        text = str(error)
        for lead in (f"{family}.", f"{family}:", f"unknown key {family}."):
            if text.startswith(lead):  # the driver named the key: name its table as the file does
                text = lead.replace(family, key, 1) + text[len(lead):]
                break
        else:
            text = f"{key}: {text}"
        raise ConfigError(_where(where, text)) from None


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
                raise ConfigError(f"{_where(source, key)}: expected a table [{family}] or [[{family}]]")
            common = parse(DeviceKeys, table, _where(source, key))
            name = common.name or (family if not isinstance(value, list) else f"{family}{i}")
            if any(d.name == name for d in devices):
                raise ConfigError(f"{_where(source, key + '.name')}: two devices are named {name!r}")
            if common.enabled:
                options = {k: v for k, v in table.items() if k not in ("url", "enabled")}
                check_device(family, common.url, options, source, key)
                devices.append(Device(family, name, common.url, options))
    return tuple(devices)


def parse_config(data: dict[str, Any], source: str = "") -> RobotConfig:
    """Check a decoded TOML document and build the configuration (``source`` names it in errors)."""
    document = parse(RobotDocument, data, f"{source}: " if source else "")
    robot = document.robot.name
    logger = document.logger
    if "prefix" not in logger.model_fields_set:
        logger = logger.model_copy(update={"prefix": robot})
    from trundle.perception.markers import dictionary_by_name  # OpenCV: only once a config is read

    try:
        dictionary_by_name(document.processing.aruco_dictionary)
    except UserError as error:
        raise ConfigError(f"{_where(source, 'processing.aruco_dictionary')}: {error}") from None
    devices = _devices(data, source)
    from trundle.fusion.slam.config import SlamConfig  # pydantic and SciPy: only once a config is read
    from trundle.fusion.slam.landmark_slam import landmark_configs

    try:
        SlamConfig.from_mapping(document.slam)  # checked even while SLAM is off, so a typo shows at once
        landmark_configs(document.landmarks)
    except UserError as error:
        raise ConfigError(_where(source, str(error))) from None
    laser = document.laser
    return RobotConfig(robot, devices, document.frames, tuple(document.transforms), logger, document.disk,
                       document.processing, document.status, document.supervision, dict(document.slam),
                       dict(data.get("odometry", {})), (laser.x_m, laser.y_m, laser.yaw_rad) if laser else None,
                       document.live, source, dict(document.landmarks))


def _check_folder(folder: Path, where: str) -> None:
    """The log folder exists as a writable folder on a disk, or can be made: else a UserError."""
    existing = folder
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        made = "" if existing == folder else f" (so {folder} cannot be made)"
        raise ConfigError(f"{where} = {str(folder)!r}: {existing} is not a folder{made}")
    try:
        disk = os.statvfs(existing)
    except OSError as error:
        raise ConfigError(f"{where} = {str(folder)!r}: cannot look at {existing}: {error.strerror}") from None
    if disk.f_blocks == 0:
        raise ConfigError(f"{where} = {str(folder)!r}: {existing} is on a virtual file system (like /proc), not a disk")
    if not os.access(existing, os.W_OK | os.X_OK):
        what = "write in" if existing == folder else "make a folder in"
        raise ConfigError(f"{where} = {str(folder)!r}: no permission to {what} {existing}")


def check_daemon_config(config: RobotConfig) -> None:
    """What the daemon needs beyond a valid document: a log folder it can write on a disk, a URL
    for every device, at least one device, the live view's extra if it is enabled."""
    source = config.source
    if config.logger.folder is None:
        raise ConfigError(f"{_where(source, 'logger.folder')}: missing (where the logs go)")
    _check_folder(config.logger.folder, _where(source, "logger.folder"))
    if not config.devices:
        raise ConfigError(f"{_where(source, 'no device')}: add an [lrf], [can] or [camera] table with a url")
    for device in config.devices:
        if not device.url:
            raise ConfigError(f"{_where(source, device.family + '.url')}: missing (the device URL, as for "
                            f"trundle record --{device.family})")
    if config.live.enabled and importlib.util.find_spec("foxglove") is None:
        raise ConfigError(f"{_where(source, 'live.enabled')}: the live view needs the optional extra: "
                        "pip install 'trundle[live]' (foxglove-sdk)")


def read_toml(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The TOML document at ``path``; a missing, unreadable or invalid file is one UserError line."""
    path = Path(path)
    if not path.exists():
        raise ConfigError(f"config file not found: {path}")
    try:
        return tomllib.loads(read_text(path, "TOML config file"))
    except tomllib.TOMLDecodeError as error:
        raise ConfigError(f"{path}: not valid TOML ({error})") from None


def load_config(path: str | os.PathLike[str] | None) -> RobotConfig:
    """Read and check the config at ``path`` (None: the empty config, every default)."""
    if path is None:
        return RobotConfig()
    return parse_config(read_toml(path), str(path))
