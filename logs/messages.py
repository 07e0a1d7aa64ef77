"""trundle's message types: small frozen dataclasses with numpy arrays for bulk data.

Units and frames follow REP 103/105 (metres, radians, counter-clockwise, x forward).
Every ``stamp_ns`` is the host time of the measurement in integer nanoseconds since the
Unix epoch. ``trundle.logs.ros2`` maps each type to its standard ROS 2 message.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np


def _f32(values) -> np.ndarray:
    return np.ascontiguousarray(values, dtype=np.float32)


def _f64(values, shape: tuple[int, ...] | None = None) -> np.ndarray:
    array = np.ascontiguousarray(values, dtype=np.float64)
    return array.reshape(shape) if shape is not None else array


def _float32(value: float) -> float:
    """A Python float holding exactly the float32 that ROS will carry."""
    return float(np.float32(value))


def _frozen_array(array: np.ndarray) -> np.ndarray:
    array.flags.writeable = False
    return array


def _eq(a: object, b: object) -> bool:
    """Field equality that treats numpy arrays by value (NaN equal to NaN)."""
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        a, b = np.asarray(a), np.asarray(b)
        if a.shape != b.shape:
            return False
        if a.dtype.kind == "f" or b.dtype.kind == "f":
            return bool(np.array_equal(a, b, equal_nan=True))
        return bool(np.array_equal(a, b))
    if isinstance(a, tuple) and isinstance(b, tuple):
        return len(a) == len(b) and all(_eq(x, y) for x, y in zip(a, b, strict=True))
    return a == b


class Message:
    """Base of every message: value equality over fields, arrays compared by value."""

    __slots__ = ()
    __dataclass_fields__: ClassVar[dict[str, Any]]  # every message is a dataclass

    def __eq__(self, other: object) -> bool:
        if type(self) is not type(other):
            return NotImplemented
        return all(_eq(getattr(self, f), getattr(other, f)) for f in self.__dataclass_fields__)

    __hash__ = None  # type: ignore[assignment]


_SCAN_SCALARS = ("angle_min", "angle_max", "angle_increment", "time_increment", "scan_time", "range_min", "range_max")


@dataclass(frozen=True, eq=False)
class LaserScan(Message):
    """One sweep of a planar range finder (sensor_msgs/LaserScan).

    ``ranges`` in metres; REP 117 invalid readings: +inf no return, -inf too close, NaN error.
    Angles in radians, counter-clockwise, 0 straight ahead. ``time_increment`` is the time
    between beams and ``scan_time`` between scans, in seconds.
    """

    stamp_ns: int
    frame_id: str
    angle_min: float
    angle_max: float
    angle_increment: float
    time_increment: float
    scan_time: float
    range_min: float
    range_max: float
    ranges: np.ndarray
    intensities: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))

    def __post_init__(self) -> None:
        scalars = np.array([self.angle_min, self.angle_max, self.angle_increment, self.time_increment,
                            self.scan_time, self.range_min, self.range_max], np.float32).tolist()
        for name, value in zip(_SCAN_SCALARS, scalars, strict=True):
            object.__setattr__(self, name, value)
        object.__setattr__(self, "ranges", _frozen_array(_f32(self.ranges)))
        object.__setattr__(self, "intensities", _frozen_array(_f32(self.intensities)))

    def angles(self) -> np.ndarray:
        """Beam angles in radians, one per range."""
        return self.angle_min + self.angle_increment * np.arange(self.ranges.size)


@dataclass(frozen=True, eq=False)
class CompressedImage(Message):
    """An encoded image (sensor_msgs/CompressedImage); ``format`` is e.g. ``jpeg`` or ``png``."""

    stamp_ns: int
    frame_id: str
    format: str
    data: bytes


@dataclass(frozen=True, eq=False)
class Image(Message):
    """A raw image (sensor_msgs/Image); ``data`` is the row-major byte buffer, ``step`` bytes a row."""

    stamp_ns: int
    frame_id: str
    height: int
    width: int
    encoding: str
    step: int
    data: np.ndarray
    is_bigendian: bool = False

    def __post_init__(self) -> None:
        array = np.ascontiguousarray(self.data, dtype=np.uint8).reshape(-1)
        object.__setattr__(self, "data", _frozen_array(array))

    @classmethod
    def from_array(cls, stamp_ns: int, frame_id: str, pixels: np.ndarray, encoding: str | None = None) -> Image:
        """Wrap an OpenCV-style array (H x W mono8 or H x W x 3 bgr8)."""
        pixels = np.ascontiguousarray(pixels, dtype=np.uint8)
        if encoding is None:
            encoding = "mono8" if pixels.ndim == 2 else "bgr8"
        height, width = pixels.shape[:2]
        return cls(stamp_ns, frame_id, height, width, encoding, pixels.strides[0], pixels.reshape(-1))

    def to_array(self) -> np.ndarray:
        """The pixels as H x W (x channels) uint8 for 8-bit encodings."""
        channels = self.step // max(self.width, 1)
        shape = (self.height, self.width) if channels == 1 else (self.height, self.width, channels)
        return (
            self.data[: self.height * self.step]
            .reshape(self.height, self.step)[:, : self.width * channels]
            .reshape(shape)
        )


@dataclass(frozen=True, eq=False)
class CameraInfo(Message):
    """Pinhole calibration (sensor_msgs/CameraInfo): K 3x3, D, R 3x3, P 3x4."""

    stamp_ns: int
    frame_id: str
    height: int
    width: int
    distortion_model: str
    d: np.ndarray
    k: np.ndarray
    r: np.ndarray = field(default_factory=lambda: np.eye(3))
    p: np.ndarray = field(default_factory=lambda: np.zeros((3, 4)))
    binning_x: int = 0
    binning_y: int = 0

    def __post_init__(self) -> None:
        object.__setattr__(self, "d", _frozen_array(_f64(self.d).reshape(-1)))
        object.__setattr__(self, "k", _frozen_array(_f64(self.k, (3, 3))))
        object.__setattr__(self, "r", _frozen_array(_f64(self.r, (3, 3))))
        object.__setattr__(self, "p", _frozen_array(_f64(self.p, (3, 4))))


@dataclass(frozen=True, eq=False)
class JointState(Message):
    """Wheel (joint) states (sensor_msgs/JointState): position rad, velocity rad/s, effort N m."""

    stamp_ns: int
    frame_id: str
    name: tuple[str, ...]
    position: np.ndarray
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(0))
    effort: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def __post_init__(self) -> None:
        object.__setattr__(self, "name", tuple(self.name))
        for name in ("position", "velocity", "effort"):
            object.__setattr__(self, name, _frozen_array(_f64(getattr(self, name)).reshape(-1)))


@dataclass(frozen=True, eq=False)
class CanFrame(Message):
    """One raw CAN frame (can_msgs/Frame), kept so a log can be decoded again later."""

    stamp_ns: int
    frame_id: str
    id: int
    data: bytes
    is_extended: bool = False
    is_rtr: bool = False
    is_error: bool = False

    @property
    def dlc(self) -> int:
        return len(self.data)


@dataclass(frozen=True, eq=False)
class Odometry(Message):
    """Planar odometry (nav_msgs/Odometry): pose of ``child_frame_id`` in ``frame_id``.

    ``pose_covariance`` and ``twist_covariance`` are 3x3 over (x, y, yaw) and (vx, vy, wz);
    the ROS 6x6 matrices are filled from them.
    """

    stamp_ns: int
    frame_id: str
    child_frame_id: str
    x: float
    y: float
    theta: float
    vx: float = 0.0
    vy: float = 0.0
    wz: float = 0.0
    pose_covariance: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))
    twist_covariance: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))

    def __post_init__(self) -> None:
        object.__setattr__(self, "pose_covariance", _frozen_array(_f64(self.pose_covariance, (3, 3))))
        object.__setattr__(self, "twist_covariance", _frozen_array(_f64(self.twist_covariance, (3, 3))))


@dataclass(frozen=True, eq=False)
class Pose2D(Message):
    """A planar pose with 3x3 covariance over (x, y, yaw) (geometry_msgs/PoseWithCovarianceStamped)."""

    stamp_ns: int
    frame_id: str
    x: float
    y: float
    theta: float
    covariance: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))

    def __post_init__(self) -> None:
        object.__setattr__(self, "covariance", _frozen_array(_f64(self.covariance, (3, 3))))


@dataclass(frozen=True, eq=False)
class TransformStamped(Message):
    """Pose of ``child_frame_id`` in ``frame_id``: translation (m) and quaternion (x, y, z, w)."""

    stamp_ns: int
    frame_id: str
    child_frame_id: str
    translation: np.ndarray
    rotation: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "translation", _frozen_array(_f64(self.translation, (3,))))
        object.__setattr__(self, "rotation", _frozen_array(_f64(self.rotation, (4,))))

    @classmethod
    def planar(cls, stamp_ns: int, frame_id: str, child_frame_id: str, x: float, y: float, yaw: float,
               z: float = 0.0) -> TransformStamped:
        """A transform in the plane: translation (x, y, z) and a rotation of ``yaw`` about z."""
        return cls(stamp_ns, frame_id, child_frame_id, np.array((x, y, z)),
                   np.array((0.0, 0.0, math.sin(yaw / 2.0), math.cos(yaw / 2.0))))

    @property
    def yaw(self) -> float:
        qx, qy, qz, qw = self.rotation
        return math.atan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))


@dataclass(frozen=True, eq=False)
class TFMessage(Message):
    """A batch of transforms (tf2_msgs/TFMessage) as published on ``/tf`` and ``/tf_static``."""

    transforms: tuple[TransformStamped, ...]

    def __post_init__(self) -> None:
        object.__setattr__(self, "transforms", tuple(self.transforms))


@dataclass(frozen=True, eq=False)
class OccupancyGrid(Message):
    """A 2-D occupancy map (nav_msgs/OccupancyGrid).

    ``data`` is int8 of shape (height, width), row 0 at the origin (bottom of the map); values
    0..100 are occupancy probability in percent, -1 unknown. ``resolution`` in m/cell; the origin
    is the pose of cell (0, 0)'s corner in ``frame_id``.
    """

    stamp_ns: int
    frame_id: str
    resolution: float
    origin_x: float
    origin_y: float
    origin_theta: float
    data: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "resolution", _float32(self.resolution))
        array = np.ascontiguousarray(self.data, dtype=np.int8)
        if array.ndim != 2:
            raise ValueError("OccupancyGrid.data must be 2-D (height, width)")
        object.__setattr__(self, "data", _frozen_array(array))

    @property
    def height(self) -> int:
        return int(self.data.shape[0])

    @property
    def width(self) -> int:
        return int(self.data.shape[1])


@dataclass(frozen=True, eq=False)
class Path(Message):
    """A trajectory (nav_msgs/Path): ``stamps_ns`` (N,) and ``poses`` (N, 3) as x, y, theta."""

    stamp_ns: int
    frame_id: str
    stamps_ns: np.ndarray
    poses: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "stamps_ns", _frozen_array(np.ascontiguousarray(self.stamps_ns, np.int64).reshape(-1)))
        object.__setattr__(self, "poses", _frozen_array(_f64(self.poses).reshape(-1, 3)))


OK, WARN, ERROR, STALE = 0, 1, 2, 3


@dataclass(frozen=True, eq=False)
class DiagnosticStatus(Message):
    """Health of one component (diagnostic_msgs/DiagnosticStatus); ``level`` OK/WARN/ERROR/STALE."""

    level: int
    name: str
    message: str
    hardware_id: str = ""
    values: tuple[tuple[str, str], ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "values", tuple((str(k), str(v)) for k, v in self.values))


@dataclass(frozen=True, eq=False)
class DiagnosticArray(Message):
    """A batch of statuses (diagnostic_msgs/DiagnosticArray) as published on ``/diagnostics``."""

    stamp_ns: int
    status: tuple[DiagnosticStatus, ...]

    def __post_init__(self) -> None:
        object.__setattr__(self, "status", tuple(self.status))


CIRCLE, LINE_STRIP, LINE_LIST, POLYGON, POINTS = 0, 1, 2, 3, 4


@dataclass(frozen=True, eq=False)
class ImageMarker(Message):
    """A 2-D annotation drawn over an image (visualization_msgs/ImageMarker).

    ``points`` (N, 2) pixel coordinates; ``position`` is the circle centre; colours RGBA in [0, 1].
    """

    stamp_ns: int
    frame_id: str
    ns: str
    id: int
    type: int
    position: tuple[float, float] = (0.0, 0.0)
    scale: float = 1.0
    outline_color: tuple[float, float, float, float] = (0.0, 1.0, 0.0, 1.0)
    filled: bool = False
    fill_color: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    points: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))

    def __post_init__(self) -> None:
        object.__setattr__(self, "scale", _float32(self.scale))
        object.__setattr__(self, "points", _frozen_array(_f64(self.points).reshape(-1, 2)))
        object.__setattr__(self, "position", tuple(float(v) for v in self.position))
        object.__setattr__(self, "outline_color", tuple(_float32(v) for v in self.outline_color))
        object.__setattr__(self, "fill_color", tuple(_float32(v) for v in self.fill_color))


@dataclass(frozen=True, eq=False)
class LandmarkObservation(Message):
    """One landmark seen from the tracking frame (one entry of trundle_msgs/LandmarkList).

    ``id`` is the landmark's identity when the sensor knows it (a marker or barcode number), ""
    when it does not (a laser corner). ``range`` (m) and ``bearing`` (rad, counter-clockwise from
    x) are in the tracking frame's x-y plane, ``covariance`` (2x2) is over (range, bearing).
    ``translation`` (m) and ``rotation`` (quaternion x, y, z, w) are the landmark's full pose in
    the tracking frame (default: the range-bearing point at z = 0, identity rotation); ``yaw_variance``
    (rad^2) is that of the landmark's yaw about z, 0 when its orientation is not observed.
    """

    id: str
    range: float
    bearing: float
    covariance: np.ndarray
    translation: np.ndarray = None  # type: ignore[assignment]  # None: the range-bearing point (__post_init__)
    rotation: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 0.0, 1.0]))
    yaw_variance: float = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "id", str(self.id))
        object.__setattr__(self, "range", float(self.range))
        object.__setattr__(self, "bearing", float(self.bearing))
        object.__setattr__(self, "yaw_variance", float(self.yaw_variance))
        object.__setattr__(self, "covariance", _frozen_array(_f64(self.covariance, (2, 2))))
        translation = self.translation
        if translation is None:
            translation = np.array((self.range * math.cos(self.bearing), self.range * math.sin(self.bearing), 0.0))
        object.__setattr__(self, "translation", _frozen_array(_f64(translation, (3,))))
        object.__setattr__(self, "rotation", _frozen_array(_f64(self.rotation, (4,))))

    @property
    def oriented(self) -> bool:
        """Whether the landmark's orientation was observed (a marker's full pose)."""
        return self.yaw_variance > 0.0

    @classmethod
    def from_position(cls, landmark_id: str, xy, covariance_xy, translation=None, rotation=(0.0, 0.0, 0.0, 1.0),
                      yaw_variance: float = 0.0) -> LandmarkObservation:
        """An observation from a position ``xy`` (m, tracking frame) and its 2x2 covariance, which
        becomes the (range, bearing) covariance to first order; ``translation`` defaults to ``(x, y, 0)``."""
        x, y = (float(v) for v in np.asarray(xy, np.float64).reshape(2))
        q = max(x * x + y * y, 1e-18)
        r = math.sqrt(q)
        jac = np.array([[x / r, y / r], [-y / q, x / q]])
        covariance = jac @ np.asarray(covariance_xy, np.float64).reshape(2, 2) @ jac.T
        return cls(landmark_id, r, math.atan2(y, x), 0.5 * (covariance + covariance.T),
                   np.array((x, y, 0.0)) if translation is None else translation, rotation, yaw_variance)

    def position_covariance(self) -> np.ndarray:
        """The 2x2 covariance (m^2) of the range-bearing point in the tracking frame (first order)."""
        c, s = math.cos(self.bearing), math.sin(self.bearing)
        jac = np.array([[c, -self.range * s], [s, self.range * c]])
        return jac @ self.covariance @ jac.T

    @property
    def yaw(self) -> float:
        """The landmark's yaw in the tracking frame (rad)."""
        qx, qy, qz, qw = self.rotation
        return math.atan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))


@dataclass(frozen=True, eq=False)
class LandmarkList(Message):
    """The landmarks seen at one instant from ``frame_id`` (trundle_msgs/LandmarkList, modelled on
    cartographer_ros_msgs/LandmarkList), published on ``/landmarks``."""

    stamp_ns: int
    frame_id: str
    landmarks: tuple[LandmarkObservation, ...]

    def __post_init__(self) -> None:
        object.__setattr__(self, "landmarks", tuple(self.landmarks))


@dataclass(frozen=True, eq=False)
class SceneMarker(Message):
    """A shape in a 3-D scene (visualization_msgs/Marker, action ADD): its pose in ``frame_id``
    (x, y, z m, yaw rad), ``scale`` (3,) m, colour RGBA in [0, 1] and, for text, ``text``.

    ``type`` is the ROS marker type; the ones trundle draws are class constants.
    """

    SPHERE: ClassVar[int] = 2
    CYLINDER: ClassVar[int] = 3
    TEXT_VIEW_FACING: ClassVar[int] = 9

    stamp_ns: int
    frame_id: str
    ns: str
    id: int
    type: int
    x: float
    y: float
    z: float = 0.0
    yaw: float = 0.0
    scale: np.ndarray = field(default_factory=lambda: np.ones(3))
    color: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 1.0)
    text: str = ""

    def __post_init__(self) -> None:
        object.__setattr__(self, "scale", _frozen_array(_f64(self.scale, (3,))))
        object.__setattr__(self, "color", tuple(_float32(v) for v in self.color))


@dataclass(frozen=True, eq=False)
class SceneMarkers(Message):
    """A batch of scene markers (visualization_msgs/MarkerArray), e.g. a landmark map."""

    markers: tuple[SceneMarker, ...]

    def __post_init__(self) -> None:
        object.__setattr__(self, "markers", tuple(self.markers))
