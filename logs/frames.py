"""The tf tree: where every frame is, from ``/tf_static`` and ``/tf``, chained between any two frames.

Frames follow REP 103/105 (metres, radians, x forward, y left, z up; ``map -> odom -> base_link ->
sensor``). Each frame has one parent (tf's rule); an edge is static (``/tf_static``: valid at any
time) or dynamic (``/tf``: a reading at each stamp). A lookup at a time chains the edges from
both frames up to their nearest common ancestor: static edges as they are, dynamic edges
**interpolated** between the two readings around the time asked (translation linearly, rotation by
slerp); a time outside a dynamic edge's readings is an error unless it is within ``extrapolate_s``
of the first or last one, and then that **nearest** reading stands. Without a time, a dynamic edge
gives its latest reading. Dynamic readings older than ``cache_s`` before the newest are forgotten
(tf2 keeps 10 s too).

Configured transforms (a robot config's ``[[transforms]]``) win: a child frame added with
``configured=True`` keeps that transform whatever a driver later publishes for it, so a laser
driver's default (zero) mount never replaces the mount the robot's config gives.

Anything that cannot be looked up (a frame the tree does not hold, two frames not connected, a
time outside the readings) is a :class:`~trundle.logs.errors.DataError` naming the frame and what
the tree holds. This is the only module that reads ``/tf_static``; everything needing a mount or a
frame asks it.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Protocol

import numpy as np

from trundle.logs import messages as m
from trundle.logs.errors import DataError
from trundle.logs.topics import TF_STATIC_TOPIC, TF_TOPIC

if TYPE_CHECKING:
    from trundle.logs.reader import LogReader

BASE_FRAME = "base_link"  # REP 105: the robot's body frame, in which sensors are mounted


class TransformSpec(Protocol):
    """A configured static transform: ``child`` in ``parent`` at ``xyz`` (m), roll-pitch-yaw ``rpy`` (rad)."""

    @property
    def parent(self) -> str: ...
    @property
    def child(self) -> str: ...
    @property
    def xyz(self) -> tuple[float, float, float]: ...
    @property
    def rpy(self) -> tuple[float, float, float]: ...


def quaternion_from_rpy(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """The quaternion (x, y, z, w) of fixed-axis roll, pitch, yaw (rad) about x, y, z (ROS's RPY:
    ``R = Rz(yaw) Ry(pitch) Rx(roll)``)."""
    cr, sr = math.cos(roll / 2.0), math.sin(roll / 2.0)
    cp, sp = math.cos(pitch / 2.0), math.sin(pitch / 2.0)
    cy, sy = math.cos(yaw / 2.0), math.sin(yaw / 2.0)
    return np.array([sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy,
                     cr * cp * sy - sr * sp * cy, cr * cp * cy + sr * sp * sy])


def rpy_transform(stamp_ns: int, parent: str, child: str, xyz: Iterable[float],
                  rpy: Iterable[float]) -> m.TransformStamped:
    """``child`` in ``parent`` at ``xyz`` (m), rotated by roll, pitch, yaw ``rpy`` (rad), stamped ``stamp_ns``."""
    return m.TransformStamped(stamp_ns, parent, child, np.array(tuple(xyz), np.float64), quaternion_from_rpy(*rpy))


def rotation_matrix(quaternion: Iterable[float]) -> np.ndarray:
    """The 3x3 rotation of a quaternion (x, y, z, w), normalised first."""
    x, y, z, w = np.asarray(quaternion, np.float64) / np.linalg.norm(np.asarray(quaternion, np.float64))
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def transform_matrix(transform: m.TransformStamped) -> np.ndarray:
    """The 4x4 homogeneous pose of ``child_frame_id`` in ``frame_id``."""
    matrix = np.eye(4)
    matrix[:3, :3] = rotation_matrix(transform.rotation)
    matrix[:3, 3] = transform.translation
    return matrix


def planar(matrix: np.ndarray) -> np.ndarray:
    """A 4x4 pose seen from above: (x m, y m, yaw rad), yaw the heading of the frame's x axis."""
    return np.array([matrix[0, 3], matrix[1, 3], math.atan2(matrix[1, 0], matrix[0, 0])])


def links(msg: m.TFMessage) -> set[tuple[str, str]]:
    """The (parent, child) frame pairs a TF message carries, e.g. ``{("map", "odom")}``."""
    return {(t.frame_id, t.child_frame_id) for t in msg.transforms}


def _slerp(q0: np.ndarray, q1: np.ndarray, f: float) -> np.ndarray:
    """The rotation a fraction ``f`` of the way from ``q0`` to ``q1`` (shortest arc)."""
    q0, q1 = q0 / np.linalg.norm(q0), q1 / np.linalg.norm(q1)
    dot = float(q0 @ q1)
    if dot < 0.0:
        q1, dot = -q1, -dot
    if dot > 0.9995:  # nearly equal: linear is exact to rounding
        q = q0 + f * (q1 - q0)
        return q / np.linalg.norm(q)
    angle = math.acos(dot)
    return (math.sin((1.0 - f) * angle) * q0 + math.sin(f * angle) * q1) / math.sin(angle)


@dataclass
class _Track:
    """The readings of one dynamic edge from ``parent``, oldest first: their stamps (ns) and transforms."""

    parent: str
    stamps: list[int] = field(default_factory=list)
    transforms: list[m.TransformStamped] = field(default_factory=list)

    def add(self, transform: m.TransformStamped, cache_ns: int) -> None:
        k = bisect.bisect_right(self.stamps, transform.stamp_ns)
        self.stamps.insert(k, transform.stamp_ns)
        self.transforms.insert(k, transform)
        old = bisect.bisect_left(self.stamps, self.stamps[-1] - cache_ns)
        del self.stamps[:old], self.transforms[:old]

    def matrix_at(self, child: str, stamp_ns: int | None, extrapolate_ns: int) -> np.ndarray:
        if stamp_ns is None:
            return transform_matrix(self.transforms[-1])
        first, last = self.stamps[0], self.stamps[-1]
        if stamp_ns <= first or stamp_ns >= last:
            if (stamp_ns < first and first - stamp_ns > extrapolate_ns) or (
                    stamp_ns > last and stamp_ns - last > extrapolate_ns):
                raise DataError(f"no transform {self.parent} -> {child} at {stamp_ns * 1e-9:.3f} s: "
                                f"/tf has it from {first * 1e-9:.3f} s to {last * 1e-9:.3f} s")
            return transform_matrix(self.transforms[0] if stamp_ns <= first else self.transforms[-1])
        k = bisect.bisect_left(self.stamps, stamp_ns)
        a, b = self.transforms[k - 1], self.transforms[k]
        f = (stamp_ns - a.stamp_ns) / (b.stamp_ns - a.stamp_ns)
        matrix = np.eye(4)
        matrix[:3, :3] = rotation_matrix(_slerp(a.rotation, b.rotation, f))
        matrix[:3, 3] = a.translation + f * (b.translation - a.translation)
        return matrix


class FrameTree:
    """The tf tree of a log or a robot; see the module docstring for the rules.

    ``cache_s`` (s) is how long dynamic readings are kept, ``extrapolate_s`` (s) how far outside a
    dynamic edge's readings the nearest one still stands.
    """

    def __init__(self, cache_s: float = 10.0, extrapolate_s: float = 0.0) -> None:
        self._static: dict[str, m.TransformStamped] = {}
        self._dynamic: dict[str, _Track] = {}
        self._configured: set[str] = set()
        self._static_paths: dict[tuple[str, str], np.ndarray] = {}  # transforms through static edges only
        self._cache_ns = int(cache_s * 1e9)
        self._extrapolate_ns = int(extrapolate_s * 1e9)

    @classmethod
    def configured(cls, transforms: Iterable[TransformSpec], stamp_ns: int) -> FrameTree:
        """A tree holding a robot config's ``[[transforms]]`` (stamped ``stamp_ns``), which win over
        anything published later for the same child frames."""
        tree = cls()
        tree.add_static(m.TFMessage(tuple(rpy_transform(stamp_ns, t.parent, t.child, t.xyz, t.rpy)
                                          for t in transforms)), configured=True)
        return tree

    @classmethod
    def from_log(cls, reader: LogReader) -> FrameTree:
        """The static tree of a log: every ``/tf_static`` message in it."""
        tree = cls()
        for item in reader.messages(topics=[TF_STATIC_TOPIC]):
            tree.add(item.topic, item.msg)
        return tree

    # ------------------------------------------------------------------ input
    def add(self, topic: str, msg: m.Message) -> bool:
        """Take a message if it is a TFMessage on ``/tf_static`` or ``/tf``; True when taken."""
        if not isinstance(msg, m.TFMessage):
            return False
        if topic == TF_STATIC_TOPIC:
            self.add_static(msg)
        elif topic == TF_TOPIC:
            self.add_dynamic(msg)
        else:
            return False
        return True

    def add_static(self, msg: m.TFMessage, configured: bool = False) -> None:
        """Static edges (valid at any time); a configured child frame keeps its configured transform
        unless this one is ``configured`` too."""
        for transform in msg.transforms:
            child = transform.child_frame_id
            if child in self._configured and not configured:
                continue
            if configured:
                self._configured.add(child)
            self._static[child] = transform
            self._dynamic.pop(child, None)
            self._static_paths.clear()

    def add_dynamic(self, msg: m.TFMessage) -> None:
        """Dynamic readings (``/tf``); a child frame that was static or configured stays static."""
        for transform in msg.transforms:
            child = transform.child_frame_id
            if child in self._static:
                continue
            track = self._dynamic.get(child)
            if track is None or track.parent != transform.frame_id:
                track = self._dynamic[child] = _Track(transform.frame_id)
            track.add(transform, self._cache_ns)

    # ------------------------------------------------------------------ output
    @property
    def frames(self) -> list[str]:
        """Every frame the tree names (children and parents), sorted."""
        names = set(self._static) | set(self._dynamic)
        names |= {t.frame_id for t in self._static.values()} | {t.parent for t in self._dynamic.values()}
        return sorted(names)

    def static_message(self) -> m.TFMessage:
        """Every static edge as one ``/tf_static`` message (what a logger latches)."""
        return m.TFMessage(tuple(self._static.values()))

    def transform(self, target: str, source: str, stamp_ns: int | None = None) -> np.ndarray:
        """The 4x4 pose of frame ``source`` in frame ``target`` at ``stamp_ns`` (None: the latest),
        chained through their nearest common ancestor; DataError when it cannot be had. A chain of
        static edges only (a sensor's mount, asked for with every scan) is computed once."""
        known = self._static_paths.get((target, source))
        if known is not None:
            return known.copy()
        source_up, target_up = self._ancestors(source), self._ancestors(target)
        common = next((frame for frame in source_up if frame in target_up), None)
        if common is None:
            raise DataError(f"frames {source!r} and {target!r} are not connected in the tf tree "
                            f"({source!r} hangs from {source_up[-1]!r}, {target!r} from {target_up[-1]!r}; "
                            f"frames: {', '.join(self.frames)})")
        matrix = np.linalg.inv(self._up_to(target, common, stamp_ns)) @ self._up_to(source, common, stamp_ns)
        below = source_up[:source_up.index(common)] + target_up[:target_up.index(common)]
        if all(frame in self._static for frame in below):
            self._static_paths[(target, source)] = matrix.copy()
        return matrix

    def try_transform(self, target: str, source: str, stamp_ns: int | None = None) -> np.ndarray | None:
        """:meth:`transform`, or None when it cannot be had (e.g. a camera not yet placed)."""
        try:
            return self.transform(target, source, stamp_ns)
        except DataError:
            return None

    def mount(self, frame: str, base: str = BASE_FRAME, stamp_ns: int | None = None, *,
              unknown_is_base: bool = False) -> np.ndarray:
        """Where a sensor frame sits on the robot, seen from above: (x m, y m, yaw rad) of ``frame`` in
        ``base``. ``unknown_is_base``: a frame the tree does not name at all (a log without
        ``/tf_static``) is taken to be ``base`` itself (zero mount) instead of an error."""
        if unknown_is_base and frame not in self._static and frame not in self._dynamic and frame not in self.frames:
            return np.zeros(3)
        return planar(self.transform(base, frame, stamp_ns))

    # ------------------------------------------------------------------ chaining
    def _parent(self, frame: str) -> str | None:
        if frame in self._static:
            return self._static[frame].frame_id
        track = self._dynamic.get(frame)
        return None if track is None else track.parent

    def _ancestors(self, frame: str) -> list[str]:
        """``frame``, its parent, ... up to its root; DataError for a frame the tree does not name or a cycle."""
        if frame not in self.frames:
            raise DataError(f"frame {frame!r} is not in the tf tree (frames: {', '.join(self.frames) or 'none'}; "
                            f"is it on /tf_static, or in the config's [[transforms]]?)")
        chain = [frame]
        parent = self._parent(frame)
        while parent is not None:
            if parent in chain:
                raise DataError(f"the tf tree has a cycle through {parent!r}: {' -> '.join(chain + [parent])}")
            chain.append(parent)
            parent = self._parent(parent)
        return chain

    def _up_to(self, frame: str, ancestor: str, stamp_ns: int | None) -> np.ndarray:
        """The 4x4 pose of ``frame`` in its ``ancestor``, each dynamic edge at ``stamp_ns``."""
        matrix = np.eye(4)
        while frame != ancestor:
            if frame in self._static:
                step, frame_up = transform_matrix(self._static[frame]), self._static[frame].frame_id
            else:
                track = self._dynamic[frame]
                step, frame_up = track.matrix_at(frame, stamp_ns, self._extrapolate_ns), track.parent
            matrix = step @ matrix
            frame = frame_up
        return matrix
