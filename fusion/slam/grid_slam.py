"""Online 2-D SLAM: odometry-predicted scan-to-submap matching, keyframe pose graph, loop closure.

Per scan (``process`` takes messages, so the same object runs on a live driver or a log):

1. **Predict**: the wheel odometry increment since the previous scan moves an EKF
   (``trundle.fusion.odometry.ekf.PoseEKF``) in the local tracking frame; without odometry a constant-velocity
   guess with a wide covariance stands in.
2. **Match**: the scan is matched against the older active submap: Levenberg-Marquardt from the
   prediction when the prediction is tight, otherwise (or when that fails) a correlative search
   over a window of three standard deviations first. The match corrects the EKF, gated by
   Mahalanobis distance; with no laser match the odometry alone carries on, covariance growing.
3. **Keyframes**: a scan that moved far enough (or waited long enough) becomes a pose-graph node
   with an edge to the previous keyframe, and is inserted into the active submaps.
4. **Loop closure**: each new keyframe is searched for, by branch-and-bound correlative search
   with a window that grows with the distance travelled since, in finished submaps near its
   current estimate; matches that score well and that point-to-line ICP against the submap's
   occupied cells confirms become edges to the submap's anchor node. The graph
   is optimised with a robust kernel, edges that still disagree afterwards are removed, and the
   map frame follows the optimised poses.

Every scan's map pose is kept relative to its keyframe, so after the final optimisation
``trajectory()`` gives one optimised pose per scan and ``build_map()`` rebuilds the occupancy
grid from the optimised keyframes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import Any, Callable, Mapping

import numpy as np

from trundle.fusion.odometry.ekf import GATE_CHI2_99, PoseEKF, odometry_noise
from trundle.fusion.geometry import (compose, inverse, no_return_directions, relative, rotate_covariance,
                                     scan_to_points, transform_points, voxel_filter, wrap_angle)
from trundle.fusion.matching.icp import LineReference, icp
from trundle.fusion.mapping.map_check import MapCheck, check_map
from trundle.fusion.odometry.motion_model import MotionModel, MotionPrediction
from trundle.fusion.mapping.occupancy_grid import LogOddsGrid
from trundle.fusion.odometry.diff_drive import DiffDriveOdometry
from trundle.fusion.odometry.check import OdometryCheck
from trundle.fusion.optimization.pose_graph import PoseGraph
from trundle.fusion.optimization.robust_window import RobustWindow
from trundle.fusion.matching.scan_matching import MatchResult, match_scan, refine_pose, samples_walls_densely
from trundle.fusion.mapping.submaps import Submap, SubmapStack
from trundle.logs import messages as m
from trundle.logs.errors import UserError
from trundle.logs.frames import FrameTree
from trundle.logs.topics import SCAN_TOPIC

# chi-square 3 dof: 99.9 % quantile, for pruning loop edges that disagree after optimisation
CHI2_3DOF_999 = 16.266236196238129


def _mahalanobis2(prediction: np.ndarray, covariance: np.ndarray, result: MatchResult) -> float:
    """Squared Mahalanobis distance of a match from a predicted pose with ``covariance`` (both uncertain)."""
    innovation = result.pose - prediction
    innovation[2] = wrap_angle(innovation[2])
    return float(innovation @ np.linalg.solve(covariance + result.covariance, innovation))


@dataclass
class SlamConfig:
    """Parameters of :class:`Slam` (the ``[slam]`` table of a config file). Metres, radians, seconds."""

    resolution: float = 0.05
    scan_topic: str = SCAN_TOPIC
    min_range_m: float = 0.0
    max_range_m: float = 30.0
    voxel_m: float = 0.05
    deskew: bool = True
    deskew_max_gap_s: float = 0.5
    no_return_clear_m: float = 0.0
    # motion filter: a keyframe every so far / so much turn / so long
    keyframe_distance_m: float = 0.2
    keyframe_angle_rad: float = math.radians(10.0)
    keyframe_time_s: float = 5.0
    scans_per_submap: int = 25
    # tracking: search windows are 3 standard deviations of the prediction, between these bounds
    search_window_xy_m: tuple[float, float] = (0.1, 2.0)
    search_window_theta_rad: tuple[float, float] = (math.radians(3.0), math.radians(45.0))
    search_angular_step_rad: float = math.radians(0.5)
    search_prior_scale: float = 2.0
    min_match_score: float = 0.3
    gate_chi2: float = GATE_CHI2_99  # a match poorer than usual is believed only this close to the prediction
    # odometry noise model per scan step: a floor (wheel/laser timing) plus per metre travelled / radian turned
    odom_sigma_xy_m: float = 0.01
    odom_sigma_theta_rad: float = math.radians(0.5)
    odom_sigma_xy_per_m: float = 0.2
    odom_sigma_theta_per_m: float = math.radians(5.0)
    odom_sigma_theta_per_rad: float = 0.2
    odom_timeout_s: float = 0.25
    # test each odometry increment against the scan match and bridge those the laser contradicts
    odometry_check: bool = True
    # motion model (without odometry, or to test it): learned from the log; this prior per scan interval until then
    motion_prior_sigma_xy_m: float = 0.3
    motion_prior_sigma_theta_rad: float = math.radians(10.0)
    # loop closure
    loop_closure: bool = True
    loop_every_keyframes: int = 3
    loop_min_node_gap: int = 30
    loop_search_radius_m: float = 6.0
    loop_max_candidates: int = 3
    loop_cooldown_keyframes: int = 5
    loop_window_xy_m: tuple[float, float] = (0.5, 3.0)
    loop_window_theta_rad: tuple[float, float] = (math.radians(10.0), math.radians(30.0))
    loop_window_per_m: float = 0.05
    loop_angular_step_rad: float = math.radians(1.0)
    loop_min_score: float = 0.55
    loop_min_inliers: float = 0.6
    loop_verify_xy_m: float = 0.1
    loop_verify_theta_rad: float = math.radians(2.0)
    loop_min_std_xy_m: float = 0.05
    loop_min_std_theta_rad: float = math.radians(1.0)
    optimize_every_keyframes: int = 10
    robust_kernel: str = "cauchy"

    POSITIVE = frozenset({"resolution", "scans_per_submap", "optimize_every_keyframes", "loop_every_keyframes"})

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any]) -> SlamConfig:
        """A config from a TOML table; unknown keys, wrong types and impossible values (negative,
        non-finite, a zero resolution) are a UserError."""
        known = {f.name: f for f in fields(cls)}
        config = cls()
        for key, value in values.items():
            if key not in known:
                raise UserError(f"unknown [slam] option {key!r} (known: {', '.join(sorted(known))})")
            default = getattr(config, key)
            try:
                if isinstance(default, tuple):
                    converted: Any = tuple(float(v) for v in value)
                    if len(converted) != len(default):
                        raise ValueError
                elif isinstance(default, bool):
                    if not isinstance(value, bool):
                        raise ValueError
                    converted = value
                else:
                    converted = type(default)(value)
            except (TypeError, ValueError):
                raise UserError(f"[slam] {key} = {value!r}: expected {type(default).__name__}") from None
            numbers = converted if isinstance(converted, tuple) else (converted,)
            if not isinstance(converted, (bool, str)) and not all(math.isfinite(v) and v >= 0 for v in numbers):
                raise UserError(f"[slam] {key} = {value!r}: expected finite numbers >= 0")
            if key in cls.POSITIVE and not converted > 0:
                raise UserError(f"[slam] {key} = {value!r}: expected a number > 0")
            setattr(config, key, converted)
        if config.max_range_m <= config.min_range_m:
            raise UserError(f"[slam] max_range_m {config.max_range_m} must be above min_range_m {config.min_range_m}")
        return config


@dataclass
class ScanResult:
    """What happened to one scan: its map pose, the match (None if none), keyframe node (or -1)."""

    stamp_ns: int
    pose_map: np.ndarray
    match: MatchResult | None
    matched: bool
    searched: bool
    node: int


@dataclass(frozen=True)
class _Closure:
    """A verified loop-closure candidate: submap ``anchor`` node -> ``node`` with its measurement and
    covariance (anchor frame), and the map pose it implies for ``node`` with that covariance (map frame)."""

    anchor: int
    node: int
    submap: int
    measurement: np.ndarray
    covariance: np.ndarray
    implied: np.ndarray
    implied_covariance: np.ndarray


@dataclass
class SlamStats:
    scans: int = 0
    keyframes: int = 0
    matched: int = 0
    searched: int = 0
    gated_out: int = 0
    odometry_only: int = 0
    motion_model_only: int = 0
    odometry_rejected: int = 0
    loop_attempts: int = 0
    loop_closures: int = 0
    loop_rejected: int = 0
    loop_unverified: int = 0
    loop_paired: int = 0
    loop_inconsistent: int = 0
    optimizations: int = 0
    scores: list[float] = field(default_factory=list)
    residuals: list[float] = field(default_factory=list)


class Slam:
    """The online SLAM front end and back end; feed it messages with :meth:`process`.

    ``odometry`` turns ``JointState`` wheel angles into odometry (None: use ``Odometry``
    messages if any arrive); ``laser_pose`` is the laser's pose in base_link (also taken from
    ``/tf_static`` when it arrives, chained to base_link by :class:`trundle.logs.frames.FrameTree`; a
    scan frame the log never places is taken as base_link itself).
    """

    def __init__(self, config: SlamConfig | None = None, odometry: DiffDriveOdometry | None = None,
                 laser_pose: tuple[float, float, float] | None = None) -> None:
        self.config = config or SlamConfig()
        self.wheels = odometry
        self.laser_pose = None if laser_pose is None else np.asarray(laser_pose, np.float64)
        self.submaps = SubmapStack(self.config.resolution, self.config.scans_per_submap, subcell=True)
        self.graph = PoseGraph()
        self.stats = SlamStats()
        self.ekf: PoseEKF | None = None
        self.map_from_local = np.zeros(3)
        self._odom: list[tuple[int, np.ndarray]] = []
        self._last_scan_odom: np.ndarray | None = None
        self._last_stamp: int | None = None
        self._last_local: np.ndarray | None = None
        floor = (self.config.resolution, self.config.resolution, self.config.search_angular_step_rad)
        self.motion = MotionModel((self.config.motion_prior_sigma_xy_m, self.config.motion_prior_sigma_xy_m,
                                   self.config.motion_prior_sigma_theta_rad), floor)
        self.odometry_check = OdometryCheck()
        self._scores = RobustWindow()
        self._dense = True  # does the current scan sample walls densely (point-to-line refinement)?
        self.frames = FrameTree()
        self._mount = np.zeros(3)
        self._kf_cov = np.zeros((3, 3))
        self.map_to_odom = np.zeros(3)
        self._kf_local: list[np.ndarray] = []
        self._kf_points: list[np.ndarray] = []
        self._kf_free: list[np.ndarray | None] = []
        self._kf_stamp: list[int] = []
        self._kf_spacing: list[float] = []  # angle between beams of each keyframe's scan (rad)
        self._kf_path_m: list[float] = []
        self._path_m = 0.0
        self._scan_node: list[int] = []
        self._scan_rel: list[np.ndarray] = []
        self._scan_stamp: list[int] = []
        self._loop_edges: list[int] = []
        self._kf_chain: list[np.ndarray] = []  # summed covariance of the sequential edges up to each keyframe
        self._pending: list[_Closure] = []
        self._last_loop_node: dict[int, int] = {}
        self._nodes_at_last_optimization = 0
        self._loops_at_last_optimization = 0

    # --- input -------------------------------------------------------------------------------

    def process(self, topic: str, msg: m.Message) -> ScanResult | None:
        """Route one message: scans on ``config.scan_topic`` return a :class:`ScanResult`."""
        if isinstance(msg, m.LaserScan):
            return self.add_scan(msg) if topic == self.config.scan_topic else None
        if isinstance(msg, m.JointState) and self.wheels is not None:
            odom = self.wheels.update(msg)
            if odom is not None:
                self.add_odometry(odom)
        elif isinstance(msg, m.Odometry) and self.wheels is None:
            self.add_odometry(msg)
        else:
            self.frames.add(topic, msg)
        return None

    def add_odometry(self, odom: m.Odometry) -> None:
        """Remember an odometry pose (odom frame) for interpolation at scan times.

        A reading older than the last one (a clock that stepped back) starts the buffer afresh.
        """
        if self._odom and odom.stamp_ns < self._odom[-1][0]:
            self._odom.clear()
        self._odom.append((odom.stamp_ns, np.array([odom.x, odom.y, odom.theta])))
        if len(self._odom) > 256:
            del self._odom[:128]

    def odometry_at(self, stamp_ns: int) -> np.ndarray | None:
        """Odometry pose at ``stamp_ns``, interpolated between the readings around it.

        Outside the readings the nearest one stands in, unless it is more than
        ``config.odom_timeout_s`` away: then odometry counts as missing (None).
        """
        if not self._odom:
            return None
        stamps = np.array([s for s, _ in self._odom])
        k = int(np.searchsorted(stamps, stamp_ns))
        if k == 0 or k >= len(stamps):
            nearest = self._odom[0] if k == 0 else self._odom[-1]
            if abs(stamp_ns - nearest[0]) * 1e-9 > self.config.odom_timeout_s:
                return None
            return nearest[1].copy()
        (s0, p0), (s1, p1) = self._odom[k - 1], self._odom[k]
        f = (stamp_ns - s0) / (s1 - s0) if s1 > s0 else 1.0
        step = relative(p0, p1)
        return compose(p0, step * f)

    # --- per scan ----------------------------------------------------------------------------

    def add_scan(self, scan: m.LaserScan) -> ScanResult:
        """Track one scan, add a keyframe if due, close loops; returns its map pose."""
        cfg = self.config
        mount = (self.laser_pose if self.laser_pose is not None
                 else self.frames.mount(scan.frame_id, unknown_is_base=True))
        self._mount = mount
        odom = self.odometry_at(scan.stamp_ns)
        dt = 0.0 if self._last_stamp is None else max(0.0, (scan.stamp_ns - self._last_stamp) * 1e-9)
        swept = cfg.deskew and 0.0 < dt <= cfg.deskew_max_gap_s
        with_odometry = swept and odom is not None and self._last_scan_odom is not None
        limits = (max(cfg.min_range_m, scan.range_min), min(cfg.max_range_m, scan.range_max))
        # de-skewed by the odometry's velocity, or the tracked one; the latter also when the odometry is
        # rejected (a glitch's velocity would bend the scan it is tested against)
        tracked_points = scan_to_points(scan, mount, *limits, self.motion.velocity if swept else None)
        points = (scan_to_points(scan, mount, *limits, relative(self._last_scan_odom, odom) / dt) if with_odometry
                  else tracked_points)
        free_ends = None
        if cfg.no_return_clear_m > 0:
            free_ends = mount[:2] + cfg.no_return_clear_m * no_return_directions(scan, mount)
        match_points = voxel_filter(points, cfg.voxel_m)
        self._dense = samples_walls_densely(points, cfg.resolution)
        self.stats.scans += 1
        self._last_stamp = scan.stamp_ns

        result: MatchResult | None = None
        matched = searched = False
        if self.ekf is None:  # the map frame starts where odometry starts (map -> odom identity)
            self.ekf = PoseEKF(np.zeros(3) if odom is None else odom, np.diag([1e-6, 1e-6, 1e-8]))
        else:
            odom_step = None if odom is None or self._last_scan_odom is None else relative(self._last_scan_odom, odom)
            motion = self.motion.predict(dt)
            submap = self.submaps.matching_submap()
            if submap is not None and len(match_points) >= 10:
                rejected = self.stats.odometry_rejected
                result, searched = self._track(submap, match_points, odom_step, motion,
                                               lambda: voxel_filter(tracked_points, cfg.voxel_m))
                matched = result is not None
                if self.stats.odometry_rejected > rejected:
                    points = tracked_points
            else:
                self._predict(odom_step, motion)
            if matched:
                self.stats.matched += 1
                self.stats.scores.append(result.score)
                self.stats.residuals.append(result.residual_m)
                self._scores.add(result.overlap_score)
            elif submap is not None:
                if odom_step is not None:
                    self.stats.odometry_only += 1
                else:
                    self.stats.motion_model_only += 1
        self._last_scan_odom = odom  # after a gap the first reading only sets the reference again
        self.stats.searched += int(searched)
        pose_local = self.ekf.pose.copy()
        if self._last_local is not None:
            self._path_m += float(np.hypot(*(pose_local[:2] - self._last_local[:2])))
        self.motion.update(scan.stamp_ns, pose_local, tracked=matched or self._last_local is None)
        self._last_local = pose_local

        node = -1
        if self._is_keyframe(pose_local, scan.stamp_ns):
            self._kf_spacing.append(abs(float(scan.angle_increment)))
            node = self._add_keyframe(pose_local, points, mount, free_ends, scan.stamp_ns)
        kf = len(self._kf_local) - 1
        self._scan_node.append(kf)
        self._scan_rel.append(relative(self._kf_local[kf], pose_local))
        self._scan_stamp.append(scan.stamp_ns)
        pose_map = compose(self.map_from_local, pose_local)
        if odom is not None:
            self.map_to_odom = compose(pose_map, inverse(odom))
        return ScanResult(scan.stamp_ns, pose_map, result, matched, searched, node)

    def _odometry_noise(self, step: np.ndarray) -> np.ndarray:
        cfg = self.config
        return odometry_noise(step, cfg.odom_sigma_xy_m, cfg.odom_sigma_theta_rad, cfg.odom_sigma_xy_per_m,
                              cfg.odom_sigma_theta_per_m, cfg.odom_sigma_theta_per_rad)

    def _predict(self, odom_step: np.ndarray | None, motion: MotionPrediction) -> None:
        """Move the EKF by the odometry increment (with the noise learned on this log), or by the motion
        model's step without odometry."""
        assert self.ekf is not None
        if odom_step is not None:
            self.ekf.predict(odom_step, self.odometry_check.noise(self._odometry_noise(odom_step)))
        else:
            self.ekf.predict(motion.delta, motion.covariance)

    def _track(self, submap: Submap, points: np.ndarray, odom_step: np.ndarray | None,
               motion: MotionPrediction, tracked_points: Callable[[], np.ndarray]) -> tuple[MatchResult | None, bool]:
        """Match the scan and correct the EKF; returns the match used (None: prediction only) and whether it searched.

        A match scoring as well as the recent ones on this log is believed; a poorer one only where
        the prediction expects it. With odometry the match starts from its increment; when the
        laser contradicts the increment (:class:`OdometryCheck`) that match bridges it, and when
        the match is poor the scan is matched again from the motion model alone (a glitch may have
        thrown the prediction beyond its window) and a good match from there bridges it; either
        way the increment is rejected. Without odometry a failed match is retried once over the widest window.
        """
        assert self.ekf is not None
        before = PoseEKF(self.ekf.pose, self.ekf.covariance)
        self._predict(odom_step, motion)
        result, searched = self._match(submap, points, self.ekf.pose, self.ekf.covariance)
        usual = result is not None and self._usual(result)
        if odom_step is not None and self.config.odometry_check:
            disagreement = relative(self.ekf.pose, result.pose) if result is not None else np.zeros(3)
            match_covariance = rotate_covariance(result.covariance, -float(self.ekf.pose[2])) if result else np.eye(3)
            model = self._odometry_noise(odom_step)
            outlier = usual and self.odometry_check.is_outlier(disagreement, match_covariance, model)
            if usual and not outlier:
                self.odometry_check.accept(disagreement, match_covariance, model)
                return self._fuse(result), searched
            self.odometry_check.interrupt()
            before.predict(motion.delta, motion.covariance)
            points = tracked_points()  # de-skewed without the odometry in question
            if not usual:  # the truth may lie outside the odometry's window: match from the motion model
                alternative, also_searched = self._match(submap, points, before.pose, before.covariance)
                searched |= also_searched
                if alternative is not None and self._usual(alternative) and self._clearly_better(alternative, result):
                    result, usual = alternative, True
            elif result is not None:
                result = refine_pose(submap.grid, points, result.pose, shaped_covariance=True, wall_lines=self._dense)
                usual = self._usual(result)
            if usual:  # the laser contradicts the odometry increment: the match bridges it
                self.stats.odometry_rejected += 1
                self.ekf = before
                return self._fuse(result), searched
        elif odom_step is None and usual:
            return self._fuse(result), searched
        elif odom_step is None:  # motion unlike any seen lately (a robot that turned on the spot sets off): the widest window,
            # around the prediction and around the last pose (a velocity extrapolated too far)
            widest = np.diag([(self.config.search_window_xy_m[1] / 3.0) ** 2] * 2
                             + [(self.config.search_window_theta_rad[1] / 3.0) ** 2])
            centres = [self.ekf.pose] if motion.predictor == "standstill" else [self.ekf.pose, before.pose]
            retries = [self._match(submap, points, centre, widest) for centre in centres]
            searched |= any(also for _, also in retries)
            usual_retries = [r for r, _ in retries if r is not None and self._usual(r)]
            if not usual_retries:  # a slow log's robot may turn further than the widest window between two scans
                turned = self._match_any_heading(submap, points, before.pose)
                searched = True
                if turned is not None and self._usual(turned):
                    self.ekf = PoseEKF(turned.pose, np.diag([(self.config.search_window_xy_m[1] / 3.0) ** 2] * 2
                                                            + [(math.pi / 3.0) ** 2]))
                    return self._fuse(turned), searched
            if usual_retries:
                self.ekf.covariance = self.ekf.covariance + widest
                return self._fuse(max(usual_retries, key=lambda r: r.score)), searched
        if result is not None and self.ekf.mahalanobis2(result.pose, result.covariance) <= self.config.gate_chi2:
            return self._fuse(result), searched
        if result is not None:
            self.stats.gated_out += 1
        return None, searched

    def _usual(self, result: MatchResult) -> bool:
        """Does a match fit as well as the recent ones on this log? Its score at least ``min_match_score``,
        and its score where the submap has seen anything (``overlap_score``: new space seen is no
        fault) within 4 robust sigma or 20 % of their median, whichever is wider (scores barely vary
        while the robot stands)."""
        if result.score < self.config.min_match_score:
            return False
        if len(self._scores) < 10:
            return True
        median = float(self._scores.median())
        return result.overlap_score >= min(median - 4.0 * float(self._scores.scale()), 0.8 * median)

    def _clearly_better(self, result: MatchResult, other: MatchResult | None) -> bool:
        """Does ``result`` fit clearly better than ``other`` (by a tenth of its score)? A match from a
        wider window has more chances to fit a look-alike place nearly as well. The same scan's
        matches compare by their whole score: one that puts the scan out into unknown space would
        look fine where it still overlaps."""
        return other is None or result.score >= 1.1 * other.score

    def _fuse(self, result: MatchResult) -> MatchResult:
        """Correct the EKF with a believed match. A prediction that the match puts beyond its 99 % gate
        claimed too little uncertainty: its covariance is widened by the excess first, so the match
        is not averaged with a prediction it has shown wrong."""
        assert self.ekf is not None
        d2 = self.ekf.mahalanobis2(result.pose, result.covariance)
        if d2 > GATE_CHI2_99:
            self.ekf.covariance = self.ekf.covariance * (d2 / GATE_CHI2_99)
        self.ekf.correct(result.pose, result.covariance, None)
        return result

    def _match(self, submap: Submap, points: np.ndarray, prediction: np.ndarray,
               covariance: np.ndarray) -> tuple[MatchResult | None, bool]:
        """Best match near ``prediction``: for a scan that samples walls densely, the refinement from it
        when that fits as usual where the prediction expects it (most scans, and cheap); else a
        correlative search over three standard deviations (prior-weighted), refined. A sparse scan
        (few returns per wall) gives the refinement a narrow, rough basin that holds it near the
        prediction, so the prediction's error (a wrong wheel radius) would pass into the match: it is
        always searched, which costs little with few points."""
        cfg = self.config
        sigma_xy = math.sqrt(max(float(np.linalg.eigvalsh(covariance[:2, :2]).max()), 0.0))
        sigma_theta = math.sqrt(max(float(covariance[2, 2]), 0.0))
        refined = refine_pose(submap.grid, points, prediction, shaped_covariance=True, wall_lines=self._dense)
        if self._dense and self._usual(refined) and _mahalanobis2(prediction, covariance, refined) <= cfg.gate_chi2:
            return refined, False
        window_xy = float(np.clip(3.0 * sigma_xy, *cfg.search_window_xy_m))
        window_theta = float(np.clip(3.0 * sigma_theta, *cfg.search_window_theta_rad))
        result = match_scan(submap.grid, points, prediction, window_xy_m=window_xy, window_theta_rad=window_theta,
                            angular_step_rad=cfg.search_angular_step_rad, min_score=cfg.min_match_score,
                            prior_std_xy_m=cfg.search_prior_scale * max(sigma_xy, cfg.resolution),
                            prior_std_theta_rad=cfg.search_prior_scale * max(sigma_theta, cfg.search_angular_step_rad),
                            shaped_covariance=True, wall_lines=self._dense)
        if result is None or refined.score > result.score:
            result = refined
        return (result if result.score >= cfg.min_match_score else None), True

    def _match_any_heading(self, submap: Submap, points: np.ndarray, centre: np.ndarray) -> MatchResult | None:
        """Best match within the widest translation window of ``centre`` at any heading (no prior on it)."""
        cfg = self.config
        reach = cfg.search_window_xy_m[1]
        return match_scan(submap.grid, points, centre, window_xy_m=reach, window_theta_rad=math.pi,
                          angular_step_rad=cfg.search_angular_step_rad, min_score=cfg.min_match_score,
                          prior_std_xy_m=cfg.search_prior_scale * reach / 3.0, shaped_covariance=True,
                          wall_lines=self._dense)

    def _is_keyframe(self, pose_local: np.ndarray, stamp_ns: int) -> bool:
        cfg = self.config
        if not self._kf_local:
            return True
        step = relative(self._kf_local[-1], pose_local)
        return (float(np.hypot(step[0], step[1])) >= cfg.keyframe_distance_m
                or abs(float(step[2])) >= cfg.keyframe_angle_rad
                or (stamp_ns - self._kf_stamp[-1]) * 1e-9 >= cfg.keyframe_time_s)

    def _add_keyframe(self, pose_local: np.ndarray, points: np.ndarray, mount: np.ndarray,
                      free_ends: np.ndarray | None, stamp_ns: int) -> int:
        assert self.ekf is not None
        node = self.graph.add_node(compose(self.map_from_local, pose_local))
        covariance = self.ekf.covariance.copy()
        if self._kf_local:
            previous = self._kf_local[-1]
            relative_cov = rotate_covariance(covariance + self._kf_cov, -float(previous[2]))
            relative_cov += np.diag([1e-4, 1e-4, 1e-6])
            self.graph.add_edge(node - 1, node, relative(previous, pose_local), np.linalg.inv(relative_cov))
            self._kf_chain.append(self._kf_chain[-1] + rotate_covariance(relative_cov, float(previous[2])))
        else:
            self._kf_chain.append(np.zeros((3, 3)))
        self._kf_cov = covariance
        self._kf_local.append(pose_local.copy())
        self._kf_points.append(points)
        self._kf_free.append(free_ends)
        self._kf_stamp.append(stamp_ns)
        self._kf_path_m.append(self._path_m)
        self.stats.keyframes += 1
        self.submaps.insert(node, pose_local, points, mount[:2], free_ends)
        if self.config.loop_closure and node % max(self.config.loop_every_keyframes, 1) == 0:
            self._close_loops(node, voxel_filter(points, self.config.voxel_m))
        due = len(self.graph) - self._nodes_at_last_optimization >= self.config.optimize_every_keyframes
        if len(self._loop_edges) > self._loops_at_last_optimization and due:
            self.optimize()
        return node

    # --- loop closure and optimisation -----------------------------------------------------

    def _close_loops(self, node: int, points: np.ndarray) -> None:
        cfg = self.config
        poses = self.graph.poses
        here = poses[node]
        candidates = []
        for submap in self.submaps.finished:
            if node - submap.nodes[-1] < cfg.loop_min_node_gap:
                continue
            if node - self._last_loop_node.get(submap.index, -(1 << 30)) < cfg.loop_cooldown_keyframes:
                continue
            frame = submap.local_to_map(poses[submap.anchor_node])
            guess = relative(frame, here)
            distance = float(np.hypot(*(guess[:2] - submap.centre())))
            if distance <= cfg.loop_search_radius_m:
                candidates.append((distance, submap, guess))
        candidates.sort(key=lambda c: c[0])
        for _, submap, guess in candidates[: cfg.loop_max_candidates]:
            travelled = self._path_m - self._kf_path_m[submap.nodes[-1]]
            window_xy = float(np.clip(cfg.loop_window_per_m * travelled, *cfg.loop_window_xy_m))
            window_theta = float(np.clip(cfg.loop_window_per_m * travelled, *cfg.loop_window_theta_rad))
            self.stats.loop_attempts += 1
            result = match_scan(submap.grid, points, guess, window_xy_m=window_xy, window_theta_rad=window_theta,
                                angular_step_rad=cfg.loop_angular_step_rad, min_score=cfg.loop_min_score,
                                min_std_xy_m=cfg.loop_min_std_xy_m, min_std_theta_rad=cfg.loop_min_std_theta_rad,
                                shaped_covariance=True, wall_lines=self._dense)
            if result is None or result.score < cfg.loop_min_score or result.inlier_fraction < cfg.loop_min_inliers:
                continue
            if not self._verified(submap, points, result.pose):
                self.stats.loop_unverified += 1
                continue
            frame = submap.local_to_map(poses[submap.anchor_node])
            closure = _Closure(submap.anchor_node, node, submap.index, relative(submap.anchor_local, result.pose),
                               rotate_covariance(result.covariance, -float(submap.anchor_local[2])),
                               compose(frame, result.pose), rotate_covariance(result.covariance, float(frame[2])))
            self._consider(closure, poses)
            return

    def _chain_covariance(self, first: int, last: int) -> np.ndarray:
        """Covariance (map frame) of the relative pose of keyframes ``first`` -> ``last`` along the
        sequential edges: their summed covariances, and the translation a heading error causes over
        the distance between them."""
        chain = self._kf_chain[last] - self._kf_chain[first]
        distance = self._kf_path_m[last] - self._kf_path_m[first]
        chain[:2, :2] += np.eye(2) * chain[2, 2] * distance ** 2
        return chain

    def _consider(self, closure: _Closure, poses: np.ndarray) -> None:
        """A verified loop closure goes into the graph if it agrees with the chain of keyframes (the
        correction it asks for is within the chain's own uncertainty) or with another closure made
        shortly before (both ask for one correction); otherwise it waits for such a partner for
        ``2 * scans_per_submap`` keyframes and is then dropped (``loop_inconsistent``)."""
        correction = closure.implied - poses[closure.node]
        correction[2] = wrap_angle(correction[2])
        covariance = self._chain_covariance(closure.anchor, closure.node) + closure.implied_covariance
        if float(correction @ np.linalg.solve(covariance, correction)) <= CHI2_3DOF_999:
            self._add_closure(closure)
            return
        horizon = 2 * self.config.scans_per_submap
        expired = [p for p in self._pending if closure.node - p.node > horizon]
        self.stats.loop_inconsistent += len(expired)
        self._pending = [p for p in self._pending if closure.node - p.node <= horizon]
        for partner in self._pending:
            predicted = compose(partner.implied, relative(poses[partner.node], poses[closure.node]))
            difference = closure.implied - predicted
            difference[2] = wrap_angle(difference[2])
            spread = (partner.implied_covariance + closure.implied_covariance
                      + self._chain_covariance(partner.node, closure.node))
            if float(difference @ np.linalg.solve(spread, difference)) <= CHI2_3DOF_999:
                self._pending.remove(partner)
                self._add_closure(partner)
                self._add_closure(closure)
                self.stats.loop_paired += 2
                return
        self._pending.append(closure)

    def _add_closure(self, closure: _Closure) -> None:
        edge = self.graph.add_edge(closure.anchor, closure.node, closure.measurement, np.linalg.inv(closure.covariance))
        self._loop_edges.append(edge)
        self._last_loop_node[closure.submap] = closure.node
        self.stats.loop_closures += 1

    def _verified(self, submap: Submap, points: np.ndarray, pose: np.ndarray) -> bool:
        """Does point-to-line ICP against the submap's occupied cells agree with the grid match?"""
        cfg = self.config
        cells = submap.grid.occupied_points()
        if len(cells) < 10:
            return False
        reference = submap.grid.cached(("icp_reference",), lambda: LineReference(cells))
        check = icp(reference, points, pose, max_correspondence_m=3 * cfg.resolution, huber_m=cfg.resolution,
                    inlier_m=2 * cfg.resolution)
        step = relative(pose, check.pose)
        return (float(np.hypot(step[0], step[1])) <= cfg.loop_verify_xy_m
                and abs(float(step[2])) <= cfg.loop_verify_theta_rad
                and check.inlier_fraction >= cfg.loop_min_inliers)

    def optimize(self, max_iterations: int = 50) -> None:
        """Optimise the pose graph (robust kernel), drop loop edges that still disagree, move the map frame."""
        if len(self.graph) < 2:
            return
        cfg = self.config
        kernel = cfg.robust_kernel if cfg.robust_kernel in ("huber", "cauchy") else None
        self._optimize_graph(max_iterations, kernel)
        chi2 = self.graph.edge_chi2()
        ij = self.graph.edges[0]
        loops = np.flatnonzero(np.abs(ij[:, 1] - ij[:, 0]) > 1)
        bad = loops[chi2[loops] > CHI2_3DOF_999]
        if len(bad):
            self.graph.remove_edges(bad)
            self.stats.loop_closures -= len(bad)
            self.stats.loop_rejected += len(bad)
            self._optimize_graph(max_iterations, kernel)
        self._loop_edges = list(np.flatnonzero(np.abs(self.graph.edges[0][:, 1] - self.graph.edges[0][:, 0]) > 1))
        self._nodes_at_last_optimization = len(self.graph)
        self._loops_at_last_optimization = len(self._loop_edges)
        self.stats.optimizations += 1
        last = len(self._kf_local) - 1
        self.map_from_local = compose(self.graph.poses[last], inverse(self._kf_local[last]))

    def _optimize_graph(self, max_iterations: int, kernel: str | None) -> None:
        """One robust optimisation of the pose graph (a subclass may optimise its own constraints with it)."""
        self.graph.optimize(max_iterations=max_iterations, robust_kernel=kernel, kernel_width=3.0)

    def finish(self) -> None:
        """End of the run: a final optimisation when loops were added since the last one."""
        if len(self._loop_edges) != self._loops_at_last_optimization or self.stats.optimizations == 0:
            self.optimize(max_iterations=100)

    # --- output ------------------------------------------------------------------------------

    def trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """Stamps (ns) and optimised map poses (N, 3) of every scan, in arrival order."""
        if not self._scan_stamp:
            return np.zeros(0, np.int64), np.zeros((0, 3))
        nodes = self.graph.poses[np.array(self._scan_node)]
        return np.array(self._scan_stamp, np.int64), compose(nodes, np.array(self._scan_rel))

    def keyframe_stamps(self) -> np.ndarray:
        """Stamps (ns) of the keyframes."""
        return np.array(self._kf_stamp, np.int64)

    def keyframe_poses(self) -> np.ndarray:
        """Optimised map poses (K, 3) of the keyframes."""
        return self.graph.poses

    def loop_edges(self) -> np.ndarray:
        """Node pairs (L, 2) of the loop-closure edges kept."""
        ij = self.graph.edges[0]
        return ij[np.abs(ij[:, 1] - ij[:, 0]) > 1]

    def build_map(self, resolution: float | None = None) -> LogOddsGrid:
        """A fresh occupancy grid from every keyframe scan at its optimised pose."""
        grid = LogOddsGrid(resolution or self.config.resolution)
        mount = self._mount
        for pose, points, free in zip(self.graph.poses, self._kf_points, self._kf_free):
            origin = compose(pose, mount)[:2]
            c, s = math.cos(pose[2]), math.sin(pose[2])
            rot = np.array([[c, -s], [s, c]])
            hits = points @ rot.T + pose[:2]
            free_ends = None if free is None else free @ rot.T + pose[:2]
            grid.insert_rays(origin, hits, free_ends)
        return grid

    def check_map(self) -> MapCheck:
        """The map self-check (:func:`trundle.fusion.mapping.map_check.check_map`) at the optimised poses: each
        keyframe against the submaps outside the two it was tracked against and inserted into."""
        poses = self.graph.poses
        frames = np.array([s.local_to_map(poses[s.anchor_node]) for s in self.submaps.submaps]).reshape(-1, 3)
        points = [voxel_filter(p, self.config.voxel_m) for p in self._kf_points]
        ranges = [np.hypot(*(p - self._mount[:2]).T) for p in points]
        return check_map(self.submaps.submaps, frames, poses, points, ranges, np.array(self._kf_spacing),
                         2 * self.config.scans_per_submap)

    def keyframe_endpoints(self) -> list[np.ndarray]:
        """Every keyframe's scan points (N, 2) at its optimised pose, map frame."""
        return [transform_points(pose, points) for pose, points in zip(self.graph.poses, self._kf_points)]

    def keyframe_scans(self, first: int, last: int) -> np.ndarray:
        """Optimised map poses of the scans whose keyframes are ``first`` .. ``last`` (inclusive)."""
        stamps, poses = self.trajectory()
        nodes = np.array(self._scan_node)
        return poses[(nodes >= first) & (nodes <= last)]

    def map_residuals(self, grid: LogOddsGrid) -> np.ndarray:
        """Mean distance (m) of each keyframe's points to ``grid``'s occupied cells at its optimised pose."""
        residuals = [refine_pose(grid, voxel_filter(points, self.config.voxel_m), pose, max_iterations=0).residual_m
                     for pose, points in zip(self.graph.poses, self._kf_points)]
        return np.array(residuals)
