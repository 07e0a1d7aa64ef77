"""The one mapping between trundle's message types and standard ROS 2 messages, encoded as CDR.

Encoding uses the ``rosbags`` typestore (Humble definitions plus ``can_msgs/msg/Frame`` and
``trundle_msgs/msg/LandmarkList``, registered from their ``.msg`` text), so the
bytes are exactly what a ROS 2 node would publish, and the schema text handed to MCAP is the full
``ros2msg`` definition with every dependency.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import cache
from typing import Any

import numpy as np
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from trundle.logs import cdr
from trundle.logs import messages as m

CAN_FRAME_MSG = """\
std_msgs/Header header
uint32 id
bool is_rtr
bool is_extended
bool is_error
uint8 dlc
uint8[8] data
"""

# One landmark observation, modelled on cartographer_ros_msgs/LandmarkEntry (its four fields come
# first, with Cartographer's meaning) plus what a filter needs: range, bearing and their covariance.
LANDMARK_ENTRY_MSG = """\
# Identity of the landmark when the sensor knows it (marker or barcode number); empty when not.
string id
# Pose of the landmark in the tracking frame (header.frame_id).
geometry_msgs/Pose tracking_from_landmark_transform
# As cartographer_ros_msgs/LandmarkEntry: 1 / standard deviation of the translation (1/m) and of
# the rotation (1/rad); rotation_weight 0 when the landmark's orientation is not observed.
float64 translation_weight
float64 rotation_weight
# Range (m) and bearing (rad, counter-clockwise from x) in the tracking frame's x-y plane.
float64 range
float64 bearing
# Row-major 2x2 covariance of (range, bearing): m^2, m rad, rad^2.
float64[4] range_bearing_covariance
# Variance (rad^2) of the landmark's yaw about z; 0 when its orientation is not observed.
float64 yaw_variance
"""

LANDMARK_LIST_MSG = """\
std_msgs/Header header
trundle_msgs/LandmarkEntry[] landmarks
"""

TYPESTORE = get_typestore(Stores.ROS2_HUMBLE)
TYPESTORE.register(get_types_from_msg(CAN_FRAME_MSG, "can_msgs/msg/Frame"))
TYPESTORE.register(get_types_from_msg(LANDMARK_ENTRY_MSG, "trundle_msgs/msg/LandmarkEntry"))
TYPESTORE.register(get_types_from_msg(LANDMARK_LIST_MSG, "trundle_msgs/msg/LandmarkList"))
_T = TYPESTORE.types

_Header = _T["std_msgs/msg/Header"]
_Time = _T["builtin_interfaces/msg/Time"]
_Duration = _T["builtin_interfaces/msg/Duration"]
_Vector3 = _T["geometry_msgs/msg/Vector3"]
_Point = _T["geometry_msgs/msg/Point"]
_Quaternion = _T["geometry_msgs/msg/Quaternion"]
_Pose = _T["geometry_msgs/msg/Pose"]
_ColorRGBA = _T["std_msgs/msg/ColorRGBA"]

_EMPTY_U8 = np.zeros(0, np.uint8)
_POSE_AXES = np.array([0, 1, 5])  # x, y, yaw inside ROS's 6x6 (x, y, z, roll, pitch, yaw)
_COV_CELLS = (_POSE_AXES[:, None] * 6 + _POSE_AXES[None, :]).reshape(-1)  # flat 6x6 cells of the 3x3


class UnsupportedType(KeyError):
    """A ROS type (or Python type) that trundle does not map."""


def header(stamp_ns: int, frame_id: str) -> Any:
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    return _Header(stamp=_Time(sec=sec, nanosec=nanosec), frame_id=frame_id)


def stamp_of(ros_header: Any) -> int:
    return ros_header.stamp.sec * 1_000_000_000 + ros_header.stamp.nanosec


def _quaternion(yaw: float) -> Any:
    return _Quaternion(x=0.0, y=0.0, z=float(np.sin(yaw / 2.0)), w=float(np.cos(yaw / 2.0)))


def _yaw(q: Any) -> float:
    return float(np.arctan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z)))


def _cov6(cov3: np.ndarray) -> np.ndarray:
    cov = np.zeros(36)
    cov[_COV_CELLS] = cov3.reshape(-1)
    return cov


def _cov3(cov6: np.ndarray) -> np.ndarray:
    return np.asarray(cov6, np.float64).reshape(-1)[_COV_CELLS].reshape(3, 3)


def _pose(x: float, y: float, theta: float) -> Any:
    return _Pose(position=_Point(x=float(x), y=float(y), z=0.0), orientation=_quaternion(theta))


def _color(rgba: tuple[float, ...]) -> Any:
    return _ColorRGBA(r=rgba[0], g=rgba[1], b=rgba[2], a=rgba[3])


# --- per type: to ROS, from ROS ---------------------------------------------------------------

def _laserscan_to(msg: m.LaserScan) -> Any:
    return _T["sensor_msgs/msg/LaserScan"](
        header=header(msg.stamp_ns, msg.frame_id), angle_min=msg.angle_min, angle_max=msg.angle_max,
        angle_increment=msg.angle_increment, time_increment=msg.time_increment,
        scan_time=msg.scan_time, range_min=msg.range_min, range_max=msg.range_max,
        ranges=msg.ranges, intensities=msg.intensities)


def _laserscan_from(r: Any) -> m.LaserScan:
    return m.LaserScan(stamp_ns(r), r.header.frame_id, float(r.angle_min), float(r.angle_max),
                       float(r.angle_increment), float(r.time_increment), float(r.scan_time),
                       float(r.range_min), float(r.range_max), r.ranges, r.intensities)


def stamp_ns(ros_msg: Any) -> int:
    return stamp_of(ros_msg.header)


def _compressed_to(msg: m.CompressedImage) -> Any:
    return _T["sensor_msgs/msg/CompressedImage"](
        header=header(msg.stamp_ns, msg.frame_id), format=msg.format,
        data=np.frombuffer(msg.data, np.uint8))


def _compressed_from(r: Any) -> m.CompressedImage:
    return m.CompressedImage(stamp_ns(r), r.header.frame_id, r.format, r.data.tobytes())


def _image_to(msg: m.Image) -> Any:
    return _T["sensor_msgs/msg/Image"](
        header=header(msg.stamp_ns, msg.frame_id), height=msg.height, width=msg.width,
        encoding=msg.encoding, is_bigendian=int(msg.is_bigendian), step=msg.step, data=msg.data)


def _image_from(r: Any) -> m.Image:
    return m.Image(stamp_ns(r), r.header.frame_id, int(r.height), int(r.width), r.encoding,
                   int(r.step), r.data, bool(r.is_bigendian))


def _camerainfo_to(msg: m.CameraInfo) -> Any:
    roi = _T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    return _T["sensor_msgs/msg/CameraInfo"](
        header=header(msg.stamp_ns, msg.frame_id), height=msg.height, width=msg.width,
        distortion_model=msg.distortion_model, d=msg.d, k=msg.k.reshape(-1), r=msg.r.reshape(-1),
        p=msg.p.reshape(-1), binning_x=msg.binning_x, binning_y=msg.binning_y, roi=roi)


def _camerainfo_from(r: Any) -> m.CameraInfo:
    return m.CameraInfo(stamp_ns(r), r.header.frame_id, int(r.height), int(r.width),
                        r.distortion_model, r.d, r.k, r.r, r.p, int(r.binning_x), int(r.binning_y))


def _jointstate_to(msg: m.JointState) -> Any:
    return _T["sensor_msgs/msg/JointState"](
        header=header(msg.stamp_ns, msg.frame_id), name=list(msg.name), position=msg.position,
        velocity=msg.velocity, effort=msg.effort)


def _jointstate_from(r: Any) -> m.JointState:
    return m.JointState(stamp_ns(r), r.header.frame_id, tuple(r.name), r.position, r.velocity, r.effort)


def _canframe_to(msg: m.CanFrame) -> Any:
    data = np.zeros(8, np.uint8)
    data[: len(msg.data)] = np.frombuffer(msg.data[:8], np.uint8)
    return _T["can_msgs/msg/Frame"](
        header=header(msg.stamp_ns, msg.frame_id), id=msg.id, is_rtr=msg.is_rtr,
        is_extended=msg.is_extended, is_error=msg.is_error, dlc=min(len(msg.data), 8), data=data)


def _canframe_from(r: Any) -> m.CanFrame:
    return m.CanFrame(stamp_ns(r), r.header.frame_id, int(r.id), r.data[: r.dlc].tobytes(),
                      bool(r.is_extended), bool(r.is_rtr), bool(r.is_error))


def _odometry_to(msg: m.Odometry) -> Any:
    pose = _T["geometry_msgs/msg/PoseWithCovariance"](
        pose=_pose(msg.x, msg.y, msg.theta), covariance=_cov6(msg.pose_covariance))
    twist = _T["geometry_msgs/msg/TwistWithCovariance"](
        twist=_T["geometry_msgs/msg/Twist"](linear=_Vector3(x=msg.vx, y=msg.vy, z=0.0),
                                           angular=_Vector3(x=0.0, y=0.0, z=msg.wz)),
        covariance=_cov6(msg.twist_covariance))
    return _T["nav_msgs/msg/Odometry"](header=header(msg.stamp_ns, msg.frame_id),
                                       child_frame_id=msg.child_frame_id, pose=pose, twist=twist)


def _odometry_from(r: Any) -> m.Odometry:
    p, t = r.pose.pose, r.twist.twist
    return m.Odometry(stamp_ns(r), r.header.frame_id, r.child_frame_id, float(p.position.x),
                      float(p.position.y), _yaw(p.orientation), float(t.linear.x), float(t.linear.y),
                      float(t.angular.z), _cov3(r.pose.covariance), _cov3(r.twist.covariance))


def _pose2d_to(msg: m.Pose2D) -> Any:
    pose = _T["geometry_msgs/msg/PoseWithCovariance"](
        pose=_pose(msg.x, msg.y, msg.theta), covariance=_cov6(msg.covariance))
    return _T["geometry_msgs/msg/PoseWithCovarianceStamped"](header=header(msg.stamp_ns, msg.frame_id), pose=pose)


def _pose2d_from(r: Any) -> m.Pose2D:
    p = r.pose.pose
    return m.Pose2D(stamp_ns(r), r.header.frame_id, float(p.position.x), float(p.position.y),
                    _yaw(p.orientation), _cov3(r.pose.covariance))


def _transform_to(msg: m.TransformStamped) -> Any:
    tx, ty, tz = (float(v) for v in msg.translation)
    qx, qy, qz, qw = (float(v) for v in msg.rotation)
    return _T["geometry_msgs/msg/TransformStamped"](
        header=header(msg.stamp_ns, msg.frame_id), child_frame_id=msg.child_frame_id,
        transform=_T["geometry_msgs/msg/Transform"](translation=_Vector3(x=tx, y=ty, z=tz),
                                                   rotation=_Quaternion(x=qx, y=qy, z=qz, w=qw)))


def _transform_from(r: Any) -> m.TransformStamped:
    t, q = r.transform.translation, r.transform.rotation
    return m.TransformStamped(stamp_ns(r), r.header.frame_id, r.child_frame_id,
                              np.array((t.x, t.y, t.z)), np.array((q.x, q.y, q.z, q.w)))


def _tf_to(msg: m.TFMessage) -> Any:
    return _T["tf2_msgs/msg/TFMessage"](transforms=[_transform_to(t) for t in msg.transforms])


def _tf_from(r: Any) -> m.TFMessage:
    return m.TFMessage(tuple(_transform_from(t) for t in r.transforms))


def _grid_to(msg: m.OccupancyGrid) -> Any:
    info = _T["nav_msgs/msg/MapMetaData"](
        map_load_time=_Time(sec=0, nanosec=0), resolution=msg.resolution, width=msg.width,
        height=msg.height, origin=_pose(msg.origin_x, msg.origin_y, msg.origin_theta))
    return _T["nav_msgs/msg/OccupancyGrid"](header=header(msg.stamp_ns, msg.frame_id), info=info,
                                            data=msg.data.reshape(-1))


def _grid_from(r: Any) -> m.OccupancyGrid:
    info = r.info
    return m.OccupancyGrid(stamp_ns(r), r.header.frame_id, float(info.resolution),
                           float(info.origin.position.x), float(info.origin.position.y),
                           _yaw(info.origin.orientation),
                           np.asarray(r.data, np.int8).reshape(int(info.height), int(info.width)))


def _path_to(msg: m.Path) -> Any:
    poses = [_T["geometry_msgs/msg/PoseStamped"](header=header(int(t), msg.frame_id), pose=_pose(*p))
             for t, p in zip(msg.stamps_ns, msg.poses, strict=True)]
    return _T["nav_msgs/msg/Path"](header=header(msg.stamp_ns, msg.frame_id), poses=poses)


def _path_from(r: Any) -> m.Path:
    stamps = [stamp_ns(p) for p in r.poses]
    poses = [(p.pose.position.x, p.pose.position.y, _yaw(p.pose.orientation)) for p in r.poses]
    return m.Path(stamp_ns(r), r.header.frame_id, np.array(stamps, np.int64),
                  np.array(poses, np.float64).reshape(-1, 3))


def _status_to(s: m.DiagnosticStatus) -> Any:
    kv = _T["diagnostic_msgs/msg/KeyValue"]
    return _T["diagnostic_msgs/msg/DiagnosticStatus"](
        level=s.level, name=s.name, message=s.message, hardware_id=s.hardware_id,
        values=[kv(key=k, value=v) for k, v in s.values])


def _diag_to(msg: m.DiagnosticArray) -> Any:
    return _T["diagnostic_msgs/msg/DiagnosticArray"](header=header(msg.stamp_ns, ""),
                                                     status=[_status_to(s) for s in msg.status])


def _diag_from(r: Any) -> m.DiagnosticArray:
    return m.DiagnosticArray(stamp_ns(r), tuple(
        m.DiagnosticStatus(int(s.level), s.name, s.message, s.hardware_id,
                           tuple((v.key, v.value) for v in s.values)) for s in r.status))


def _marker_to(msg: m.ImageMarker) -> Any:
    return _T["visualization_msgs/msg/ImageMarker"](
        header=header(msg.stamp_ns, msg.frame_id), ns=msg.ns, id=msg.id, type=msg.type, action=0,
        position=_Point(x=msg.position[0], y=msg.position[1], z=0.0), scale=msg.scale,
        outline_color=_color(msg.outline_color), filled=int(msg.filled), fill_color=_color(msg.fill_color),
        lifetime=_Duration(sec=0, nanosec=0),
        points=[_Point(x=float(x), y=float(y), z=0.0) for x, y in msg.points], outline_colors=[])


def _marker_from(r: Any) -> m.ImageMarker:
    def rgba(c: Any) -> tuple[float, float, float, float]:
        return (float(c.r), float(c.g), float(c.b), float(c.a))
    return m.ImageMarker(stamp_ns(r), r.header.frame_id, r.ns, int(r.id), int(r.type),
                         (float(r.position.x), float(r.position.y)), float(r.scale), rgba(r.outline_color),
                         bool(r.filled), rgba(r.fill_color), np.array([(p.x, p.y) for p in r.points]).reshape(-1, 2))


def _landmark_entry_to(o: m.LandmarkObservation) -> Any:
    planar = np.linalg.eigvalsh(o.position_covariance())
    sigma = float(np.sqrt(max(planar.max(), 0.0)))
    qx, qy, qz, qw = (float(v) for v in o.rotation)
    tx, ty, tz = (float(v) for v in o.translation)
    pose = _Pose(position=_Point(x=tx, y=ty, z=tz), orientation=_Quaternion(x=qx, y=qy, z=qz, w=qw))
    return _T["trundle_msgs/msg/LandmarkEntry"](
        id=o.id, tracking_from_landmark_transform=pose, translation_weight=1.0 / sigma if sigma > 0 else 0.0,
        rotation_weight=1.0 / float(np.sqrt(o.yaw_variance)) if o.yaw_variance > 0 else 0.0,
        range=o.range, bearing=o.bearing, range_bearing_covariance=o.covariance.reshape(-1),
        yaw_variance=o.yaw_variance)


def _landmarks_to(msg: m.LandmarkList) -> Any:
    return _T["trundle_msgs/msg/LandmarkList"](header=header(msg.stamp_ns, msg.frame_id),
                                               landmarks=[_landmark_entry_to(o) for o in msg.landmarks])


def _landmarks_from(r: Any) -> m.LandmarkList:
    def entry(e: Any) -> m.LandmarkObservation:
        p, q = e.tracking_from_landmark_transform.position, e.tracking_from_landmark_transform.orientation
        return m.LandmarkObservation(e.id, float(e.range), float(e.bearing), e.range_bearing_covariance,
                                     np.array((p.x, p.y, p.z)), np.array((q.x, q.y, q.z, q.w)), float(e.yaw_variance))
    return m.LandmarkList(stamp_ns(r), r.header.frame_id, tuple(entry(e) for e in r.landmarks))


def _scene_marker_to(k: m.SceneMarker) -> Any:
    return _T["visualization_msgs/msg/Marker"](
        header=header(k.stamp_ns, k.frame_id), ns=k.ns, id=k.id, type=k.type, action=0,
        pose=_Pose(position=_Point(x=float(k.x), y=float(k.y), z=float(k.z)), orientation=_quaternion(k.yaw)),
        scale=_Vector3(x=float(k.scale[0]), y=float(k.scale[1]), z=float(k.scale[2])), color=_color(k.color),
        lifetime=_Duration(sec=0, nanosec=0), frame_locked=False, points=[], colors=[], texture_resource="",
        texture=_T["sensor_msgs/msg/CompressedImage"](header=header(0, ""), format="", data=_EMPTY_U8),
        uv_coordinates=[], text=k.text, mesh_resource="",
        mesh_file=_T["visualization_msgs/msg/MeshFile"](filename="", data=_EMPTY_U8), mesh_use_embedded_materials=False)


def _scene_markers_to(msg: m.SceneMarkers) -> Any:
    return _T["visualization_msgs/msg/MarkerArray"](markers=[_scene_marker_to(k) for k in msg.markers])


def _scene_markers_from(r: Any) -> m.SceneMarkers:
    def marker(k: Any) -> m.SceneMarker:
        c = k.color
        return m.SceneMarker(
            stamp_ns(k),
            k.header.frame_id,
            k.ns,
            int(k.id),
            int(k.type),
            float(k.pose.position.x),
            float(k.pose.position.y),
            float(k.pose.position.z),
            _yaw(k.pose.orientation),
            np.array((k.scale.x, k.scale.y, k.scale.z)),
            (float(c.r), float(c.g), float(c.b), float(c.a)),
            k.text,
        )

    return m.SceneMarkers(tuple(marker(k) for k in r.markers))


@dataclass(frozen=True)
class Mapping:
    """How one trundle type travels as one ROS 2 type."""

    python_type: type
    ros_type: str
    to_ros: Callable[[Any], Any]
    from_ros: Callable[[Any], Any]


MAPPINGS: tuple[Mapping, ...] = (
    Mapping(m.LaserScan, "sensor_msgs/msg/LaserScan", _laserscan_to, _laserscan_from),
    Mapping(m.CompressedImage, "sensor_msgs/msg/CompressedImage", _compressed_to, _compressed_from),
    Mapping(m.Image, "sensor_msgs/msg/Image", _image_to, _image_from),
    Mapping(m.CameraInfo, "sensor_msgs/msg/CameraInfo", _camerainfo_to, _camerainfo_from),
    Mapping(m.JointState, "sensor_msgs/msg/JointState", _jointstate_to, _jointstate_from),
    Mapping(m.CanFrame, "can_msgs/msg/Frame", _canframe_to, _canframe_from),
    Mapping(m.Odometry, "nav_msgs/msg/Odometry", _odometry_to, _odometry_from),
    Mapping(m.Pose2D, "geometry_msgs/msg/PoseWithCovarianceStamped", _pose2d_to, _pose2d_from),
    Mapping(m.TransformStamped, "geometry_msgs/msg/TransformStamped", _transform_to, _transform_from),
    Mapping(m.TFMessage, "tf2_msgs/msg/TFMessage", _tf_to, _tf_from),
    Mapping(m.OccupancyGrid, "nav_msgs/msg/OccupancyGrid", _grid_to, _grid_from),
    Mapping(m.Path, "nav_msgs/msg/Path", _path_to, _path_from),
    Mapping(m.DiagnosticArray, "diagnostic_msgs/msg/DiagnosticArray", _diag_to, _diag_from),
    Mapping(m.ImageMarker, "visualization_msgs/msg/ImageMarker", _marker_to, _marker_from),
    Mapping(m.LandmarkList, "trundle_msgs/msg/LandmarkList", _landmarks_to, _landmarks_from),
    Mapping(m.SceneMarkers, "visualization_msgs/msg/MarkerArray", _scene_markers_to, _scene_markers_from),
)
_BY_PYTHON = {mp.python_type: mp for mp in MAPPINGS}
_BY_ROS = {mp.ros_type: mp for mp in MAPPINGS}
# the types logged with every scan or at the wheels' and CAN bus's rate: the same bytes as the
# typestore, without its objects
_DIRECT: dict[type, Callable[[Any], bytes]] = {
    m.LaserScan: cdr.laser_scan, m.DiagnosticArray: cdr.diagnostic_array, m.CanFrame: cdr.can_frame,
    m.Odometry: cdr.odometry, m.TFMessage: cdr.tf_message, m.JointState: cdr.joint_state, m.Pose2D: cdr.pose2d}


def ros_type(python_type: type) -> str:
    """The ROS 2 type name (``pkg/msg/Name``) a trundle type is written as."""
    try:
        return _BY_PYTHON[python_type].ros_type
    except KeyError:
        raise UnsupportedType(f"no ROS 2 mapping for {python_type.__name__}") from None


def is_supported(ros_type_name: str) -> bool:
    return ros_type_name in _BY_ROS


def encode(msg: m.Message) -> tuple[str, bytes]:
    """``(ros_type, cdr_bytes)`` for a trundle message (little-endian CDR with encapsulation header)."""
    mp = _BY_PYTHON.get(type(msg))
    if mp is None:
        raise UnsupportedType(f"no ROS 2 mapping for {type(msg).__name__}")
    direct = _DIRECT.get(type(msg))
    if direct is not None:
        return mp.ros_type, direct(msg)
    return mp.ros_type, bytes(TYPESTORE.serialize_cdr(mp.to_ros(msg), mp.ros_type))


def decode(ros_type_name: str, data: bytes | memoryview) -> m.Message:
    """The trundle message for CDR bytes of a mapped ROS 2 type."""
    mp = _BY_ROS.get(ros_type_name)
    if mp is None:
        raise UnsupportedType(f"trundle does not decode {ros_type_name}")
    return mp.from_ros(TYPESTORE.deserialize_cdr(data, ros_type_name))


@cache
def schema_text(ros_type_name: str) -> str:
    """Full ``ros2msg`` definition: the type's text, then every dependency after a ``MSG:`` separator."""
    return TYPESTORE.generate_msgdef(ros_type_name, ros_version=2)[0]
