"""The local trajectory builder (Cartographer's ``LocalTrajectoryBuilder2D``): per scan, prediction,
scan-to-submap matching, the motion filter that makes keyframes, and insertion into the submaps.

Poses here are in the local (tracking) frame, which starts where odometry starts; the back end
(:mod:`trundle.fusion.slam.backend`) places the keyframes in the map frame. :meth:`LocalTrajectoryBuilder.add_scan`
returns what it did with a scan and, for a keyframe, what it inserted (:class:`Insertion`).
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass

import numpy as np

from trundle.fusion.geometry import (
    compose,
    deskewed,
    no_return_directions,
    relative,
    rotate_covariance,
    scan_returns,
    voxel_filter,
)
from trundle.fusion.mapping.submaps import SubmapStack
from trundle.fusion.matching.scan_matching import MatchResult, samples_walls_densely
from trundle.fusion.odometry.ekf import PoseEKF
from trundle.fusion.odometry.motion_model import MotionModel
from trundle.fusion.slam.config import SlamConfig
from trundle.fusion.slam.stats import SlamStats
from trundle.fusion.slam.tracking import Tracker
from trundle.logs import messages as m


@dataclass(frozen=True)
class Insertion:
    """A keyframe inserted into the submaps: its index (the pose-graph node), stamp, local pose, scan
    points and no-return ends (robot frame), laser mount, beam spacing (rad), path length so far (m),
    whether its scan samples walls densely, and its edge from the previous keyframe (measurement in
    the previous keyframe's frame, covariance, and that keyframe's local heading; None for the first)."""

    node: int
    stamp_ns: int
    pose_local: np.ndarray
    points: np.ndarray
    free_ends: np.ndarray | None
    mount: np.ndarray
    spacing_rad: float
    path_m: float
    dense: bool
    edge: tuple[np.ndarray, np.ndarray, float] | None


@dataclass(frozen=True)
class LocalResult:
    """One scan tracked: its local pose, the odometry pose at its stamp (None: none), the match (None
    if none), whether it was believed and whether it searched, its keyframe and its pose relative to
    it, and the insertion when it became a keyframe."""

    stamp_ns: int
    pose_local: np.ndarray
    odometry: np.ndarray | None
    match: MatchResult | None
    matched: bool
    searched: bool
    keyframe: int
    offset: np.ndarray
    insertion: Insertion | None


class OdometryBuffer:
    """Recent odometry poses (odom frame), interpolated at scan times."""

    def __init__(self, timeout_s: float) -> None:
        self.timeout_s = timeout_s
        self._stamps: list[int] = []   # the readings' stamps (ns), ascending: searched by bisection
        self._poses: list[np.ndarray] = []   # their poses (x, y, theta)

    def add(self, odom: m.Odometry) -> None:
        """Remember a reading; one older than the last (a clock that stepped back) starts the buffer afresh."""
        if self._stamps and odom.stamp_ns < self._stamps[-1]:
            self._stamps.clear()
            self._poses.clear()
        self._stamps.append(odom.stamp_ns)
        self._poses.append(np.array([odom.x, odom.y, odom.theta]))
        if len(self._stamps) > 256:
            del self._stamps[:128], self._poses[:128]

    def at(self, stamp_ns: int) -> np.ndarray | None:
        """Odometry pose at ``stamp_ns``, interpolated between the readings around it. Outside the
        readings the nearest one stands in, unless it is more than ``timeout_s`` away: then odometry
        counts as missing (None)."""
        stamps, poses = self._stamps, self._poses
        if not stamps:
            return None
        k = bisect.bisect_left(stamps, stamp_ns)
        if k == 0 or k >= len(stamps):
            nearest = 0 if k == 0 else -1
            if abs(stamp_ns - stamps[nearest]) * 1e-9 > self.timeout_s:
                return None
            return poses[nearest].copy()
        s0, s1, p0 = stamps[k - 1], stamps[k], poses[k - 1]
        f = (stamp_ns - s0) / (s1 - s0) if s1 > s0 else 1.0
        step = relative(p0, poses[k])
        return compose(p0, step * f)


class LocalTrajectoryBuilder:
    """Tracks scans in the local frame and inserts keyframes into ``submaps`` (see the module docstring)."""

    def __init__(self, config: SlamConfig, stats: SlamStats) -> None:
        self.config = config
        self.stats = stats
        resolution = config.submaps.resolution
        self.submaps = SubmapStack(resolution, config.submaps.scans_per_submap, subcell=True)
        self.odometry = OdometryBuffer(config.odometry.timeout_s)
        self.tracker = Tracker(config, stats)
        tracking = config.tracking
        self.motion = MotionModel((tracking.motion_prior_sigma_xy_m, tracking.motion_prior_sigma_xy_m,
                                   tracking.motion_prior_sigma_theta_rad),
                                  (resolution, resolution, tracking.search_angular_step_rad))
        self.last_scan_odometry: np.ndarray | None = None
        self._last_stamp: int | None = None
        self._last_local: np.ndarray | None = None
        self._path_m = 0.0
        self._keyframes = 0
        self._keyframe_local = np.zeros(3)
        self._keyframe_stamp = 0
        self._keyframe_covariance = np.zeros((3, 3))

    def add_scan(self, scan: m.LaserScan, mount: np.ndarray) -> LocalResult:
        """Track one scan taken by a laser at ``mount`` (base_link); a keyframe when due, inserted."""
        opts = self.config.scan
        tracker = self.tracker
        odom = self.odometry.at(scan.stamp_ns)
        last_odom = self.last_scan_odometry
        dt = 0.0 if self._last_stamp is None else max(0.0, (scan.stamp_ns - self._last_stamp) * 1e-9)
        swept = opts.deskew and 0.0 < dt <= opts.deskew_max_gap_s
        with_odometry = swept and odom is not None and last_odom is not None
        limits = (max(opts.min_range_m, scan.range_min), min(opts.max_range_m, scan.range_max))
        # de-skewed by the odometry's velocity, or the tracked one; the latter also when the odometry is
        # rejected (a glitch's velocity would bend the scan it is tested against)
        # (the scan turned into points once, de-skewed by either velocity from there)
        returns = scan_returns(scan, mount, *limits)
        tracked_points = deskewed(returns, self.motion.velocity if swept else None)
        points = tracked_points
        if with_odometry:
            assert odom is not None and last_odom is not None   # with_odometry: both are there
            points = deskewed(returns, relative(last_odom, odom) / dt)
        free_ends = None
        if opts.no_return_clear_m > 0:
            free_ends = mount[:2] + opts.no_return_clear_m * no_return_directions(scan, mount)
        match_points = voxel_filter(points, opts.voxel_m)
        tracker.dense = samples_walls_densely(points, self.config.submaps.resolution)
        self.stats.scans += 1
        self._last_stamp = scan.stamp_ns

        result: MatchResult | None = None
        matched = searched = False
        if tracker.ekf is None:  # the map frame starts where odometry starts (map -> odom identity)
            tracker.ekf = PoseEKF(np.zeros(3) if odom is None else odom, np.diag([1e-6, 1e-6, 1e-8]))
        else:
            odom_step = None if odom is None or last_odom is None else relative(last_odom, odom)
            motion = self.motion.predict(dt)
            submap = self.submaps.matching_submap()
            if submap is not None and len(match_points) >= 10:
                rejected = self.stats.odometry_rejected
                result, searched = tracker.track(submap, match_points, odom_step, motion,
                                                 lambda: voxel_filter(tracked_points, opts.voxel_m))
                matched = result is not None
                if self.stats.odometry_rejected > rejected:
                    points = tracked_points
            else:
                tracker.predict(odom_step, motion)
            if result is not None:
                tracker.matched(result)
            elif submap is not None:
                if odom_step is not None:
                    self.stats.odometry_only += 1
                else:
                    self.stats.motion_model_only += 1
        self.last_scan_odometry = odom  # after a gap the first reading only sets the reference again
        self.stats.searched += int(searched)
        pose_local = tracker.ekf.pose.copy()
        if self._last_local is not None:
            self._path_m += float(np.hypot(*(pose_local[:2] - self._last_local[:2])))
        self.motion.update(scan.stamp_ns, pose_local, tracked=matched or self._last_local is None)
        self._last_local = pose_local

        insertion = None
        if self._is_keyframe(pose_local, scan.stamp_ns):
            insertion = self._insert(pose_local, points, mount, free_ends, scan)
        return LocalResult(scan.stamp_ns, pose_local, odom, result, matched, searched, self._keyframes - 1,
                           relative(self._keyframe_local, pose_local), insertion)

    def _is_keyframe(self, pose_local: np.ndarray, stamp_ns: int) -> bool:
        """The motion filter: the first scan, and one far enough, turned enough or long enough after the
        last keyframe."""
        opts = self.config.keyframes
        if not self._keyframes:
            return True
        step = relative(self._keyframe_local, pose_local)
        return (float(np.hypot(step[0], step[1])) >= opts.distance_m
                or abs(float(step[2])) >= opts.angle_rad
                or (stamp_ns - self._keyframe_stamp) * 1e-9 >= opts.time_s)

    def _insert(self, pose_local: np.ndarray, points: np.ndarray, mount: np.ndarray, free_ends: np.ndarray | None,
                scan: m.LaserScan) -> Insertion:
        """Make the scan a keyframe: its edge from the previous one (the EKF's covariances of both, in the
        previous keyframe's frame, with a floor) and its rays in the active submaps."""
        assert self.tracker.ekf is not None
        covariance = self.tracker.ekf.covariance.copy()
        edge = None
        if self._keyframes:
            previous = self._keyframe_local
            relative_cov = rotate_covariance(covariance + self._keyframe_covariance, -float(previous[2]))
            relative_cov += np.diag([1e-4, 1e-4, 1e-6])
            edge = (relative(previous, pose_local), relative_cov, float(previous[2]))
        node = self._keyframes
        self._keyframes += 1
        self._keyframe_covariance = covariance
        self._keyframe_local = pose_local.copy()
        self._keyframe_stamp = scan.stamp_ns
        self.stats.keyframes += 1
        self.submaps.insert(node, pose_local, points, mount[:2], free_ends)
        return Insertion(node, scan.stamp_ns, pose_local.copy(), points, free_ends, mount,
                         abs(float(scan.angle_increment)), self._path_m, self.tracker.dense, edge)
