"""A differential-drive robot driving a waypoint route through a ``trundle.tools.sim.world.World``.

The whole run is simulated once, at construction, with a fixed control period: a pure-pursuit
controller (look-ahead point on the route, curvature-limited and acceleration-limited speed)
commands wheel speeds; each wheel slips by a random, slowly varying fraction (an
Ornstein-Uhlenbeck process), so the ground moves less (or more) than the wheel turns. The
ground motion of every step is an exact arc (``trundle.fusion.odometry.diff_drive.integrate_path``), so the ground
truth pose is exact at any time ``t``, not just at control ticks.

Sensors are sampled at any ``t`` (seconds from the start) by the device emulators:
``wheel_angles_at`` / ``wheel_speeds_at`` (true wheel rotation, what a perfect encoder reads),
``encoder_angles_at`` (quantised to counts, with noise), ``ranges_at`` (the laser, via
``trundle.tools.sim.world.simulate_scan``) and ``frame_at`` (the camera, via ``trundle.tools.sim.camera_render``). Noise
is drawn from a generator seeded by ``(seed, t)``, so the same ``t`` gives the same reading.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from trundle.fusion.geometry import compose, wrap_angle
from trundle.fusion.odometry.diff_drive import integrate, integrate_path
from trundle.logs import messages as m
from trundle.logs.errors import UserError
from trundle.tools.sim.camera_render import CameraPose, CameraRenderer, PinholeCamera
from trundle.tools.sim.world import LaserModel, World, simulate_scan


@dataclass(frozen=True)
class Mount:
    """Pose of a sensor on the robot (base_link frame): x forward, y left, z up (m), yaw (rad)."""

    x: float = 0.0
    y: float = 0.0
    z: float = 0.0
    yaw: float = 0.0


@dataclass(frozen=True)
class RobotModel:
    """Geometry, limits, controller and error model of the simulated robot.

    ``slip_sigma`` is the standard deviation of each wheel's slip fraction (ground distance =
    wheel distance x (1 - slip)), ``slip_tau_s`` its correlation time. ``encoder_cpr`` counts per
    wheel revolution and ``encoder_noise_rad`` the standard deviation of a reading's angle error.
    """

    wheel_radius_m: float = 0.1
    track_m: float = 0.5
    max_speed_m_s: float = 1.0
    max_accel_m_s2: float = 0.8
    max_yaw_rate_rad_s: float = 1.2
    max_lateral_accel_m_s2: float = 0.6
    lookahead_m: float = 0.8
    control_period_s: float = 0.02
    slip_sigma: float = 0.003
    slip_tau_s: float = 2.0
    encoder_cpr: int = 8192
    encoder_noise_rad: float = 2e-4
    laser: Mount = Mount(0.2, 0.0, 0.3, 0.0)
    camera: Mount = Mount(0.25, 0.0, 0.45, 0.0)
    laser_model: LaserModel = field(default_factory=LaserModel)


def _route_lengths(route: np.ndarray) -> np.ndarray:
    """Cumulative arc length (K,) at each route point."""
    return np.concatenate(([0.0], np.cumsum(np.hypot(*np.diff(route, axis=0).T))))


def _project(route: np.ndarray, cumulative: np.ndarray, point: np.ndarray, s_min: float, s_max: float) -> float:
    """Arc length of the route point nearest ``point`` among arc lengths in [s_min, s_max]."""
    a, b = route[:-1], route[1:]
    e = b - a
    length2 = np.maximum((e * e).sum(1), 1e-18)
    u = np.clip(((point - a) * e).sum(1) / length2, 0.0, 1.0)
    s = np.clip(cumulative[:-1] + u * np.sqrt(length2), s_min, s_max)
    along = np.clip((s - cumulative[:-1]) / np.sqrt(length2), 0.0, 1.0)
    closest = a + along[:, None] * e
    i = int(np.argmin(np.hypot(*(closest - point).T)))
    return float(s[i])


def _point_at(route: np.ndarray, cumulative: np.ndarray, s: float) -> np.ndarray:
    return np.array([np.interp(s, cumulative, route[:, 0]), np.interp(s, cumulative, route[:, 1])])


class RobotSim:
    """One simulated run: the robot starts at ``world.start`` and drives ``laps`` times along
    ``world.route`` (or ``route``), then stands still for ``tail_s``.

    Parameters
    ----------
    world : the world (walls for the laser and camera, route and start pose).
    model : robot geometry, limits and error model.
    route : (K, 2) waypoints overriding ``world.route``.
    laps : how many times to drive the route (the route should then end where it starts).
    seed : seeds slip and every sensor's noise.
    noise : False for a perfect robot: no slip, exact encoders, exact laser and camera.
    max_time_s : give up (UserError) if the route is not finished by then.
    """

    def __init__(self, world: World, model: RobotModel = RobotModel(), *, route: np.ndarray | None = None,
                 laps: int = 1, seed: int = 0, noise: bool = True, tail_s: float = 1.0,
                 max_time_s: float = 3600.0, camera: PinholeCamera = PinholeCamera()) -> None:
        self.world, self.model, self.seed, self.noise = world, model, seed, noise
        self.camera = camera
        base = np.asarray(world.route if route is None else route, dtype=np.float64)
        self.route = np.vstack([base] + [base[1:]] * (laps - 1))
        self._simulate(tail_s, max_time_s)

    # ------------------------------------------------------------------ simulation
    def _simulate(self, tail_s: float, max_time_s: float) -> None:
        mdl = self.model
        dt, r, b = mdl.control_period_s, mdl.wheel_radius_m, mdl.track_m
        route, cumulative = self.route, _route_lengths(self.route)
        end_s = float(cumulative[-1])
        rng = np.random.default_rng([self.seed, 1])
        decay = math.exp(-dt / mdl.slip_tau_s)
        kick = mdl.slip_sigma * math.sqrt(1.0 - decay * decay) if self.noise else 0.0
        slip = rng.normal(0.0, mdl.slip_sigma, 2) if self.noise else np.zeros(2)
        pose = np.array(self.world.start, dtype=np.float64)
        progress, v = 0.0, 0.0
        wheel_speeds, ground = [], []
        steps, finished_at = 0, None
        while True:
            t = steps * dt
            if finished_at is None:
                progress = _project(route, cumulative, pose[:2], progress - 0.5, progress + 2.0)
                goal = route[-1]
                if end_s - progress < 0.05 and np.hypot(*(goal - pose[:2])) < 0.1:
                    finished_at = t
            if finished_at is not None:
                command_v, command_w = 0.0, 0.0
                if t >= finished_at + tail_s:
                    break
            else:
                target = _point_at(route, cumulative, min(progress + mdl.lookahead_m, end_s))
                c, s = math.cos(pose[2]), math.sin(pose[2])
                dx, dy = target - pose[:2]
                tx, ty = c * dx + s * dy, -s * dx + c * dy
                curvature = 2.0 * ty / max(tx * tx + ty * ty, 1e-9)
                remaining = max(np.hypot(dx, dy) if end_s - progress < mdl.lookahead_m else end_s - progress, 0.0)
                v_goal = min(mdl.max_speed_m_s, math.sqrt(mdl.max_lateral_accel_m_s2 / max(abs(curvature), 1e-9)),
                             mdl.max_yaw_rate_rad_s / max(abs(curvature), 1e-9),
                             math.sqrt(2.0 * mdl.max_accel_m_s2 * remaining) + 0.02)
                command_v = float(np.clip(v_goal, v - mdl.max_accel_m_s2 * dt, v + mdl.max_accel_m_s2 * dt))
                command_w = curvature * command_v
            if t > max_time_s:
                raise UserError(f"simulated robot did not finish its route within {max_time_s:.0f} s")
            v = command_v
            speeds = np.array([command_v - 0.5 * b * command_w, command_v + 0.5 * b * command_w]) / r
            if kick:
                slip = decay * slip + kick * rng.standard_normal(2)
            step = speeds * dt * r * (1.0 - slip)
            pose = integrate(pose, step[0], step[1], b)
            wheel_speeds.append(speeds)
            ground.append(step)
            steps += 1
        self._speeds = np.array(wheel_speeds)                                  # (N, 2) rad/s per step
        self._ground = np.array(ground)                                        # (N, 2) m rolled on the ground
        self._times = np.arange(steps + 1) * dt                                # (N + 1,) step boundaries
        self._angles = np.vstack([np.zeros(2), np.cumsum(self._speeds * dt, axis=0)])
        self._poses = np.vstack([np.asarray(self.world.start, dtype=np.float64),
                                 integrate_path(self.world.start, self._ground[:, 0], self._ground[:, 1], b)])
        self.duration_s = float(self._times[-1])
        self.route_done_s = float(finished_at if finished_at is not None else self.duration_s)

    def _step(self, t: float) -> tuple[int, float]:
        """Index of the control step containing ``t`` and the fraction of it elapsed."""
        dt = self.model.control_period_s
        if t >= self.duration_s:
            return len(self._speeds) - 1, 1.0
        k = min(max(int(t // dt), 0), len(self._speeds) - 1)
        return k, min(max((t - self._times[k]) / dt, 0.0), 1.0)

    # ------------------------------------------------------------------ ground truth
    def pose_at(self, t: float) -> np.ndarray:
        """Exact ground-truth pose (x, y, theta) of base_link in the map at ``t`` s (theta unwrapped)."""
        k, frac = self._step(t)
        if frac == 0.0:
            return self._poses[k].copy()
        return integrate(self._poses[k], frac * self._ground[k, 0], frac * self._ground[k, 1], self.model.track_m)

    def poses_at(self, times: np.ndarray) -> np.ndarray:
        """Ground-truth poses (N, 3) at each of ``times`` (theta wrapped to [-pi, pi))."""
        poses = np.array([self.pose_at(float(t)) for t in np.atleast_1d(times)]).reshape(-1, 3)
        poses[:, 2] = wrap_angle(poses[:, 2])
        return poses

    def path_length_m(self) -> float:
        """Distance the robot travelled over the ground (m)."""
        return float(np.hypot(*np.diff(self._poses[:, :2], axis=0).T).sum())

    # ------------------------------------------------------------------ wheels
    def wheel_angles_at(self, t: float) -> np.ndarray:
        """True rotation (rad) of the left and right wheel since the start: what a perfect encoder reads."""
        k, frac = self._step(t)
        return self._angles[k] + frac * self._speeds[k] * self.model.control_period_s

    def wheel_speeds_at(self, t: float) -> np.ndarray:
        """Angular speed (rad/s) of the left and right wheel at ``t`` (still before 0 and after the end)."""
        if t < 0.0 or t >= self.duration_s:
            return np.zeros(2)
        return self._speeds[self._step(t)[0]].copy()

    def encoder_angles_at(self, t: float) -> np.ndarray:
        """Wheel angles (rad) as an encoder reports them: with noise, quantised to its counts."""
        angles = self.wheel_angles_at(t)
        if not self.noise:
            return angles
        count = 2.0 * math.pi / self.model.encoder_cpr
        noisy = angles + self._rng(t, 2).normal(0.0, self.model.encoder_noise_rad, 2)
        return np.round(noisy / count) * count

    # ------------------------------------------------------------------ laser and camera
    def sensor_pose_at(self, t: float, mount: Mount) -> np.ndarray:
        """Pose (x, y, yaw) in the map of a sensor mounted at ``mount``."""
        return compose(self.pose_at(t), np.array([mount.x, mount.y, mount.yaw]))

    def ranges_at(self, t: float, model: LaserModel | None = None) -> np.ndarray:
        """One laser scan whose first beam is at ``t`` (m; +inf no return, -inf too close), beams as
        ``model`` lays them out; a sweeping model (``time_increment``) casts beam ``i`` from the
        laser's pose at ``t + i * time_increment`` (linear between the sweep's ends: constant
        velocity over a few milliseconds)."""
        model = model or self.model.laser_model
        pose = self.sensor_pose_at(t, self.model.laser)
        if model.time_increment > 0:
            sweep = model.time_increment * (model.beams - 1)
            end = self.sensor_pose_at(t + sweep, self.model.laser)
            share = np.linspace(0.0, 1.0, model.beams)[:, None]
            pose = pose + share * np.array([end[0] - pose[0], end[1] - pose[1], wrap_angle(end[2] - pose[2])])
        return simulate_scan(self.world, pose, model, self._rng(t, 3) if self.noise else None)

    def laser_scan(self, t: float, stamp_ns: int, frame_id: str = "laser") -> m.LaserScan:
        """:meth:`ranges_at` ``t`` as the sensor_msgs/LaserScan of the robot's laser, stamped ``stamp_ns``."""
        model = self.model.laser_model
        return m.LaserScan(stamp_ns, frame_id, model.angle_min, model.angle_max, model.angle_increment,
                           model.time_increment, model.scan_time, model.range_min, model.range_max,
                           self.ranges_at(t).astype(np.float32))

    def camera_pose_at(self, t: float) -> CameraPose:
        x, y, yaw = self.sensor_pose_at(t, self.model.camera)
        return CameraPose(float(x), float(y), self.model.camera.z, float(yaw))

    @cached_property
    def renderer(self) -> CameraRenderer:
        return CameraRenderer(self.world, self.camera)

    def frame_at(self, t: float, renderer: CameraRenderer | None = None) -> np.ndarray:
        """The camera image (H, W, 3) BGR uint8 at ``t`` (``renderer``: another camera on the same mount)."""
        renderer = renderer or self.renderer
        return renderer.render(self.camera_pose_at(t), self._rng(t, 4) if self.noise else None)

    def _rng(self, t: float, stream: int) -> np.random.Generator:
        return np.random.default_rng([self.seed, stream, max(0, int(round(t * 1e6)))])
