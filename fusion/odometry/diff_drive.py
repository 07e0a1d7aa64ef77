"""Differential-drive wheel odometry with exact arc integration and distance-driven covariance.

Each step between two wheel readings is taken as a circular arc (constant wheel speeds), which
is exact for that motion model: splitting an arc into any number of pieces gives the same pose.
Covariance follows the usual wheel-slip model: each wheel's travelled distance ``d`` carries a
variance ``wheel_variance_per_m * |d|`` (m^2), propagated through the exact Jacobians, so the
uncertainty grows with distance travelled, not with time. Poses follow REP 103 (x forward,
y left, yaw counter-clockwise, metres and radians). The same class runs live on the wheels
driver (:class:`OdometrySink` around the driver's sink) and on a replayed log (it only reads
``JointState`` messages).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from typing import Annotated, Any

import numpy as np
from pydantic import Field, model_validator

from trundle.fusion.geometry import wrap_angle
from trundle.logs import messages as m
from trundle.logs.errors import UserError
from trundle.logs.schema import Schema, parse
from trundle.logs.topics import DIAGNOSTICS_TOPIC, ODOM_TOPIC, TF_TOPIC, WHEELS_TOPIC


def _sinc(u: np.ndarray) -> np.ndarray:
    """sin(u) / u, 1 at 0."""
    return np.sinc(u / np.pi)


def _dsinc(u: np.ndarray) -> np.ndarray:
    """d/du of sin(u) / u, by its series near 0 where the closed form cancels."""
    u = np.asarray(u, dtype=np.float64)
    small = np.abs(u) < 1e-3
    safe = np.where(small, 1.0, u)
    closed = (safe * np.cos(safe) - np.sin(safe)) / (safe * safe)
    return np.where(small, -u / 3.0 + u**3 / 30.0, closed)


def integrate_path(pose: tuple[float, float, float] | np.ndarray, d_left_m: float | np.ndarray,
                   d_right_m: float | np.ndarray, track_m: float) -> np.ndarray:
    """Poses (N, 3) after each of N wheel steps, starting from ``pose`` (x, y, theta).

    Parameters
    ----------
    pose : start (x m, y m, theta rad); theta is not wrapped, so headings stay continuous.
    d_left_m, d_right_m : (N,) distance each wheel rolled in each step (m, forward positive; a scalar: one step).
    track_m : distance between the wheel contact points (m).
    """
    d_left = np.atleast_1d(np.asarray(d_left_m, dtype=np.float64))
    d_right = np.atleast_1d(np.asarray(d_right_m, dtype=np.float64))
    x0, y0, theta0 = (float(v) for v in pose)
    ds = 0.5 * (d_left + d_right)
    dtheta = (d_right - d_left) / track_m
    theta = theta0 + np.cumsum(dtheta)
    mid = theta - 0.5 * dtheta
    chord = ds * _sinc(0.5 * dtheta)
    out = np.empty((d_left.size, 3))
    out[:, 0] = x0 + np.cumsum(chord * np.cos(mid))
    out[:, 1] = y0 + np.cumsum(chord * np.sin(mid))
    out[:, 2] = theta
    return out


def integrate(pose: tuple[float, float, float] | np.ndarray, d_left_m: float | np.ndarray,
              d_right_m: float | np.ndarray, track_m: float) -> np.ndarray:
    """Pose (x, y, theta) after the wheels rolled ``d_left_m`` and ``d_right_m`` (scalars for one
    arc, or (N,) arrays for N successive arcs) from ``pose``; theta is not wrapped."""
    return integrate_path(pose, d_left_m, d_right_m, track_m)[-1]


def propagate_covariance(start: np.ndarray, covariance: np.ndarray, path: np.ndarray, d_left_m: np.ndarray,
                         d_right_m: np.ndarray, track_m: float, wheel_variance_per_m: float) -> np.ndarray:
    """Covariance (3x3 over x, y, theta) at the end of ``path`` (poses after each step).

    Uses that the pose Jacobians of planar motion compose by adding translations, so the whole
    recursion P <- F P F^T + L S L^T collapses into one vectorised sum; the result does not
    depend on how the steps were grouped into calls.
    """
    d_left = np.atleast_1d(np.asarray(d_left_m, dtype=np.float64))
    d_right = np.atleast_1d(np.asarray(d_right_m, dtype=np.float64))
    theta_before = np.concatenate(([start[2]], path[:-1, 2]))
    ds = 0.5 * (d_left + d_right)
    dtheta = (d_right - d_left) / track_m
    half = 0.5 * dtheta
    mid = theta_before + half
    sinc, dsinc = _sinc(half), _dsinc(half)
    chord = ds * sinc
    dchord_ddtheta = 0.5 * ds * dsinc
    cos, sin = np.cos(mid), np.sin(mid)
    # d(step)/d(ds, dtheta): (N, 3, 2)
    j_motion = np.zeros((d_left.size, 3, 2))
    j_motion[:, 0, 0], j_motion[:, 1, 0] = sinc * cos, sinc * sin
    j_motion[:, 0, 1] = dchord_ddtheta * cos - 0.5 * chord * sin
    j_motion[:, 1, 1] = dchord_ddtheta * sin + 0.5 * chord * cos
    j_motion[:, 2, 1] = 1.0
    j_wheels = np.array([[0.5, 0.5], [-1.0 / track_m, 1.0 / track_m]])
    jac = j_motion @ j_wheels  # (N, 3, 2) d(step)/d(d_left, d_right)
    wheel_var = wheel_variance_per_m * np.stack((np.abs(d_left), np.abs(d_right)), axis=1)
    q = np.einsum("nij,nj,nkj->nik", jac, wheel_var, jac)
    # Transport each step's noise to the end pose: A_k = [[1, 0, -(y_N - y_k)], [0, 1, x_N - x_k], [0, 0, 1]].
    end = path[-1]
    a = np.broadcast_to(np.eye(3), (d_left.size, 3, 3)).copy()
    a[:, 0, 2] = -(end[1] - path[:, 1])
    a[:, 1, 2] = end[0] - path[:, 0]
    a0 = np.eye(3)
    a0[0, 2], a0[1, 2] = -(end[1] - start[1]), end[0] - start[0]
    return a0 @ covariance @ a0.T + np.einsum("nij,njk,nlk->il", a, q, a)


def _sinc_scalar(u: float) -> float:
    """sin(u) / u, 1 at 0 (:func:`_sinc` for one value)."""
    return math.sin(u) / u if u != 0.0 else 1.0


def _dsinc_scalar(u: float) -> float:
    """:func:`_dsinc` for one value."""
    if abs(u) < 1e-3:
        return -u / 3.0 + u**3 / 30.0
    return (u * math.cos(u) - math.sin(u)) / (u * u)


def step(pose: tuple[float, float, float], covariance: np.ndarray, d_left_m: float, d_right_m: float,
         track_m: float, wheel_variance_per_m: float) -> tuple[tuple[float, float, float], np.ndarray]:
    """Pose and covariance after one wheel step: :func:`integrate_path` and
    :func:`propagate_covariance` for a single step, in scalar arithmetic (a live driver advances one
    reading at a time, 100 times a second, where numpy on one-element arrays cost 0.15 ms a step)."""
    x0, y0, theta0 = pose
    ds = 0.5 * (d_left_m + d_right_m)
    dtheta = (d_right_m - d_left_m) / track_m
    half = 0.5 * dtheta
    mid = theta0 + half
    sinc, dsinc = _sinc_scalar(half), _dsinc_scalar(half)
    chord = ds * sinc
    cos, sin = math.cos(mid), math.sin(mid)
    x1, y1 = x0 + chord * cos, y0 + chord * sin
    # d(step)/d(ds, dtheta) times d(ds, dtheta)/d(d_left, d_right) = [[0.5, 0.5], [-1/track, 1/track]]
    dchord = 0.5 * ds * dsinc
    m00, m10 = sinc * cos, sinc * sin
    m01, m11 = dchord * cos - 0.5 * chord * sin, dchord * sin + 0.5 * chord * cos
    inv = 1.0 / track_m
    jl = (0.5 * m00 - inv * m01, 0.5 * m10 - inv * m11, -inv)
    jr = (0.5 * m00 + inv * m01, 0.5 * m10 + inv * m11, inv)
    var_l, var_r = wheel_variance_per_m * abs(d_left_m), wheel_variance_per_m * abs(d_right_m)
    # A0 P A0^T with A0 = [[1, 0, -dy], [0, 1, dx], [0, 0, 1]] (the start's noise carried to the end), plus the step's
    dx, dy = x1 - x0, y1 - y0
    p = covariance
    r0 = (p[0, 0] - dy * p[2, 0], p[0, 1] - dy * p[2, 1], p[0, 2] - dy * p[2, 2])
    r1 = (p[1, 0] + dx * p[2, 0], p[1, 1] + dx * p[2, 1], p[1, 2] + dx * p[2, 2])
    r2 = (p[2, 0], p[2, 1], p[2, 2])
    out = np.empty((3, 3))
    for i, row in enumerate((r0, r1, r2)):
        out[i, 0] = row[0] - dy * row[2] + jl[i] * var_l * jl[0] + jr[i] * var_r * jr[0]
        out[i, 1] = row[1] + dx * row[2] + jl[i] * var_l * jl[1] + jr[i] * var_r * jr[1]
        out[i, 2] = row[2] + jl[i] * var_l * jl[2] + jr[i] * var_r * jr[2]
    return (x1, y1, theta0 + dtheta), out


class DiffDriveOdometry:
    """Odometry of a differential-drive base from wheel angles (``JointState`` positions, rad).

    Parameters
    ----------
    wheel_radius_m : rolling radius of both wheels (m); ``left_radius_m`` / ``right_radius_m``
        override it per wheel.
    track_m : distance between the wheel contact points (m).
    left, right : joint names of the wheels in the ``JointState`` messages.
    wheel_variance_per_m : variance (m^2) added per metre a wheel rolls (slip model).
    max_speed_m_s, max_yaw_rate_rad_s : bound on the motion while a wheel is stale.

    A reading with a non-finite wheel position (a stale wheel) marks the odometry stale and
    produces no output. Wheel angles are cumulative (an ODrive's position estimate, an unwrapped
    counter), so when the wheels report again the motion across the gap is still in them: it is
    integrated as one arc, with the heading exact (it follows from the wheels alone) and the
    position uncertain by half the distance times the turn (the path's shape is unknown), if it
    is a motion the robot could make in that time (at most ``max_speed_m_s``). Otherwise (a
    counter that restarted, a device that rebooted) the next good reading becomes the new
    reference, so the pose never jumps, and the covariance grows by ``max_speed_m_s`` and
    ``max_yaw_rate_rad_s`` over the gap. ``gaps`` counts the interruptions, ``bridged`` those
    whose motion was kept.
    """

    def __init__(self, wheel_radius_m: float, track_m: float, *, left: str = "left", right: str = "right",
                 left_radius_m: float | None = None, right_radius_m: float | None = None,
                 wheel_variance_per_m: float = 1e-4, max_speed_m_s: float = 1.0, max_yaw_rate_rad_s: float = 2.0,
                 frame_id: str = "odom", child_frame_id: str = "base_link") -> None:
        if not (wheel_radius_m > 0 and track_m > 0):
            raise UserError(f"wheel radius and track must be positive, got {wheel_radius_m} m and {track_m} m")
        self.left_radius_m = float(left_radius_m or wheel_radius_m)
        self.right_radius_m = float(right_radius_m or wheel_radius_m)
        self.track_m = float(track_m)
        self.left, self.right = left, right
        self.wheel_variance_per_m = float(wheel_variance_per_m)
        self.max_speed_m_s, self.max_yaw_rate_rad_s = float(max_speed_m_s), float(max_yaw_rate_rad_s)
        self.frame_id, self.child_frame_id = frame_id, child_frame_id
        self.pose = np.zeros(3)
        self.covariance = np.zeros((3, 3))
        self.distance_m = 0.0
        self.gaps = 0
        self.bridged = 0
        self.stale = False
        self._ref: tuple[int, float, float] | None = None  # stamp, left rad, right rad
        self._stale_since_ns: int | None = None
        self._names: tuple[str, ...] = ()
        self._indices = (0, 1)

    def reset(self, pose: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> None:
        self.pose = np.asarray(pose, dtype=np.float64).copy()
        self.covariance = np.zeros((3, 3))
        self.distance_m = 0.0
        self._ref = None

    def _wheel_indices(self, names: tuple[str, ...]) -> tuple[int, int]:
        if names != self._names:
            try:
                self._indices = (names.index(self.left), names.index(self.right))
            except ValueError:
                raise UserError(
                    f"wheel joints {self.left!r} and {self.right!r} not in joint state names {list(names)}"
                ) from None
            self._names = names
        return self._indices

    def update(self, joint_state: m.JointState) -> m.Odometry | None:
        """Advance with one wheel reading; returns the odometry at its stamp, or None while a
        wheel is stale. The first reading (and the first after a gap) only sets the reference."""
        i, j = self._wheel_indices(joint_state.name)
        left, right = float(joint_state.position[i]), float(joint_state.position[j])
        if self._ref is not None and not self.stale and math.isfinite(left) and math.isfinite(right):
            return self._advance_one(int(joint_state.stamp_ns), left, right)
        return self.update_many(np.array([joint_state.stamp_ns]), joint_state.position[i:i + 1],
                                joint_state.position[j:j + 1])

    def update_many(self, stamps_ns: np.ndarray, left_rad: np.ndarray, right_rad: np.ndarray) -> m.Odometry | None:
        """Advance with N readings at once (e.g. a log's wheel angles); same result as N calls
        of :meth:`update`. Returns the odometry at the last reading, or None if it is stale."""
        stamps = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
        left = np.asarray(left_rad, dtype=np.float64).reshape(-1)
        right = np.asarray(right_rad, dtype=np.float64).reshape(-1)
        good = np.isfinite(left) & np.isfinite(right)
        if not good.all():
            bad = np.flatnonzero(~good)
            result = None
            start = 0
            for b in bad:  # one pass per interruption, not per reading
                if b > start:
                    result = self._advance(stamps[start:b], left[start:b], right[start:b])
                self._mark_stale(int(stamps[b]))
                result = None
                start = int(b) + 1
            if start < stamps.size:
                result = self._advance(stamps[start:], left[start:], right[start:])
            return result
        return self._advance(stamps, left, right)

    def _mark_stale(self, stamp_ns: int) -> None:
        if self._ref is None and not self.stale:
            return  # no reference yet (start-up): nothing is lost
        if not self.stale:
            self.stale = True
            self._stale_since_ns = self._ref[0] if self._ref is not None else stamp_ns

    def _bridge(self, stamp_ns: int, left: float, right: float) -> bool:
        """After a gap: can the wheels' travel since the last good reading be kept? If so, add the
        uncertainty of the unknown path to the covariance."""
        if self._ref is None:
            return False
        ref_stamp, ref_left, ref_right = self._ref
        gap_s = max(0.0, (stamp_ns - ref_stamp) * 1e-9)
        d_left, d_right = (left - ref_left) * self.left_radius_m, (right - ref_right) * self.right_radius_m
        if max(abs(d_left), abs(d_right)) > self.max_speed_m_s * gap_s:
            return False
        sigma = 0.5 * abs(0.5 * (d_left + d_right)) * min(1.0, abs(d_right - d_left) / self.track_m)
        self.covariance = self.covariance + np.diag((sigma ** 2, sigma ** 2, 0.0))
        return True

    def _advance(self, stamps: np.ndarray, left: np.ndarray, right: np.ndarray) -> m.Odometry | None:
        if self.stale:
            if self._bridge(int(stamps[0]), float(left[0]), float(right[0])):
                self.gaps += 1
                self.bridged += 1
                self.stale = False
                self._stale_since_ns = None
            else:
                self._ref = None
        if self._ref is None:
            if self.stale and self._stale_since_ns is not None:
                gap_s = max(0.0, (int(stamps[0]) - self._stale_since_ns) * 1e-9)
                var_xy, var_th = (self.max_speed_m_s * gap_s) ** 2, (self.max_yaw_rate_rad_s * gap_s) ** 2
                self.covariance = self.covariance + np.diag((var_xy, var_xy, var_th))
                self.gaps += 1
            self.stale = False
            self._stale_since_ns = None
            self._ref = (int(stamps[0]), float(left[0]), float(right[0]))
            stamps, left, right = stamps[1:], left[1:], right[1:]
            if stamps.size == 0:
                return self._message(int(self._ref[0]), 0.0, 0.0, 0.0, 0.0, 0.0)
        ref_stamp, ref_left, ref_right = self._ref
        if stamps.size == 1:
            return self._advance_one(int(stamps[0]), float(left[0]), float(right[0]))
        d_left = np.diff(left, prepend=ref_left) * self.left_radius_m
        d_right = np.diff(right, prepend=ref_right) * self.right_radius_m
        path = integrate_path(self.pose, d_left, d_right, self.track_m)
        self.covariance = propagate_covariance(self.pose, self.covariance, path, d_left, d_right, self.track_m,
                                               self.wheel_variance_per_m)
        self.pose = path[-1].copy()
        self.distance_m += float(np.sum(np.abs(0.5 * (d_left + d_right))))
        last_stamp = int(stamps[-1])
        prev_stamp = int(stamps[-2]) if stamps.size > 1 else ref_stamp
        self._ref = (last_stamp, float(left[-1]), float(right[-1]))
        return self._message(last_stamp, float(d_left[-1]), float(d_right[-1]), (last_stamp - prev_stamp) * 1e-9,
                             *self._wheel_var(float(d_left[-1]), float(d_right[-1])))

    def _advance_one(self, stamp_ns: int, left: float, right: float) -> m.Odometry:
        """:meth:`_advance` for one reading after the reference (the live case), in scalars."""
        assert self._ref is not None
        ref_stamp, ref_left, ref_right = self._ref
        d_left, d_right = (left - ref_left) * self.left_radius_m, (right - ref_right) * self.right_radius_m
        pose, self.covariance = step((float(self.pose[0]), float(self.pose[1]), float(self.pose[2])), self.covariance,
                                     d_left, d_right, self.track_m, self.wheel_variance_per_m)
        self.pose = np.array(pose)
        self.distance_m += abs(0.5 * (d_left + d_right))
        self._ref = (stamp_ns, left, right)
        return self._message(stamp_ns, d_left, d_right, (stamp_ns - ref_stamp) * 1e-9,
                             *self._wheel_var(d_left, d_right))

    def _wheel_var(self, d_left: float, d_right: float) -> tuple[float, float]:
        return self.wheel_variance_per_m * abs(d_left), self.wheel_variance_per_m * abs(d_right)

    def _message(self, stamp_ns: int, d_left: float, d_right: float, dt_s: float, var_left: float,
                 var_right: float) -> m.Odometry:
        twist_cov = np.zeros((3, 3))
        vx = wz = 0.0
        if dt_s > 0:
            vx = 0.5 * (d_left + d_right) / dt_s
            wz = (d_right - d_left) / self.track_m / dt_s
            # J diag(var_left, var_right) J^T with J = [[0.5, 0.5], [0, 0], [-1/track, 1/track]] / dt
            inv, scale = 1.0 / self.track_m, 1.0 / (dt_s * dt_s)
            vx_wz = 0.5 * inv * (var_right - var_left) * scale
            twist_cov[0, 0] = 0.25 * (var_left + var_right) * scale
            twist_cov[0, 2] = twist_cov[2, 0] = vx_wz
            twist_cov[2, 2] = inv * inv * (var_left + var_right) * scale
        x, y, theta = self.pose
        return m.Odometry(stamp_ns, self.frame_id, self.child_frame_id, float(x), float(y), float(wrap_angle(theta)),
                          vx, 0.0, wz, self.covariance.copy(), twist_cov)


def odometry_transform(odom: m.Odometry) -> m.TFMessage:
    """The ``odom -> base_link`` transform of an odometry message, for ``/tf``."""
    return m.TFMessage((m.TransformStamped.planar(odom.stamp_ns, odom.frame_id, odom.child_frame_id,
                                                  odom.x, odom.y, odom.theta),))


class WheelModel(Schema):
    """The wheel model in a robot config (``[odometry]``, or the ``[can]`` table beside the driver's
    options) or a log's metadata: ``wheel_radius_m`` and ``track_m`` (m, both or neither),
    ``wheels`` / ``odometry_wheels`` (joint names; the first two are left and right) and
    ``wheel_variance_per_m`` (m^2 per metre rolled)."""

    wheel_radius_m: Annotated[float, Field(gt=0)] | None = None
    track_m: Annotated[float, Field(gt=0)] | None = None
    wheels: Annotated[list[Annotated[str, Field(min_length=1)]], Field(min_length=2)] | None = None
    odometry_wheels: Annotated[list[Annotated[str, Field(min_length=1)]], Field(min_length=2)] | None = None
    wheel_variance_per_m: Annotated[float, Field(ge=0)] = 1e-4

    @model_validator(mode="after")
    def _both(self) -> WheelModel:
        if (self.wheel_radius_m is None) != (self.track_m is None):
            raise ValueError("odometry needs both wheel_radius_m and track_m (missing "
                             f"{'track_m' if self.track_m is None else 'wheel_radius_m'})")
        return self


def odometry_from_config(config: Mapping[str, Any], where: str = "odometry") -> DiffDriveOdometry | None:
    """Odometry from a table holding a :class:`WheelModel` (its keys are picked from ``config``,
    e.g. the ``[can]`` table); None without ``wheel_radius_m`` and ``track_m``. A bad value is a
    ConfigError naming ``where`` and the key."""
    model = parse(WheelModel, {k: v for k, v in config.items() if k in WheelModel.model_fields}, where)
    if model.wheel_radius_m is None or model.track_m is None:
        return None
    names = model.odometry_wheels or model.wheels or ["left", "right"]
    return DiffDriveOdometry(model.wheel_radius_m, model.track_m, left=names[0], right=names[1],
                             wheel_variance_per_m=model.wheel_variance_per_m)


class OdometrySink:
    """A sink that passes every message on to ``sink`` and runs ``odometry`` on the wheel states
    (``wheels_topic``): ``Odometry`` on ``/odom``, the ``odom -> base_link`` transform on ``/tf``,
    and a ``/diagnostics`` status whenever the odometry goes stale (a wheel lost) or recovers."""

    def __init__(self, sink: Callable[[str, m.Message, int], object], odometry: DiffDriveOdometry, *,
                 wheels_topic: str = WHEELS_TOPIC, name: str = "odometry") -> None:
        self.sink, self.odometry = sink, odometry
        self.wheels_topic, self.name = wheels_topic, name

    def __call__(self, topic: str, msg: m.Message, log_time_ns: int) -> object:
        result = self.sink(topic, msg, log_time_ns)
        if topic == self.wheels_topic and isinstance(msg, m.JointState):
            was_stale = self.odometry.stale
            odom = self.odometry.update(msg)
            if odom is not None:
                self.sink(ODOM_TOPIC, odom, log_time_ns)
                self.sink(TF_TOPIC, odometry_transform(odom), log_time_ns)
            if self.odometry.stale != was_stale:
                self.sink(DIAGNOSTICS_TOPIC, m.DiagnosticArray(msg.stamp_ns, (self.status(),)), log_time_ns)
        return result

    def status(self) -> m.DiagnosticStatus:
        odo = self.odometry
        values = (("gaps", str(odo.gaps)), ("distance_m", f"{odo.distance_m:.3f}"))
        if odo.stale:
            return m.DiagnosticStatus(m.WARN, self.name, "stale: a wheel is not reporting; pose held", "", values)
        return m.DiagnosticStatus(m.OK, self.name, "ok" if not odo.gaps else f"ok after {odo.gaps} gap(s)", "", values)
