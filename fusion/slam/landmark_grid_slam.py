"""Landmarks in the grid SLAM's pose graph: marker sightings tighten the map as Cartographer's
landmark constraints do.

:class:`LandmarkConstraints` is a constraint source of the grid SLAM's back end
(:class:`trundle.fusion.slam.backend.ConstraintSource`); the facade
(:class:`trundle.fusion.slam.grid_slam.Slam`) routes LandmarkList messages to it. A sighting (an
id is needed: the grid SLAM does not associate anonymous features) is tied to the keyframe of the
latest scan: the robot's pose at the sighting's stamp in that keyframe's frame is the scan's
offset from its keyframe composed with the odometry since the scan, and the landmark goes through
it into the keyframe's frame. A marker with its full pose is
a landmark *pose* with a between factor (x, y, yaw), like Cartographer's translation and rotation
weights; a point landmark has a relative-position factor. Whenever the pose graph is optimised
(loop closures, the end of the run, or a landmark seen again from a keyframe far from where it
was first seen) the keyframes and the landmarks are optimised together as one
:class:`trundle.fusion.optimization.factor_graph.FactorGraph`, the landmark factors under a Cauchy kernel, so
one bad sighting pulls with a bounded force.

Three things are read from the data rather than assumed:

- the relative weight of the laser edges and the sightings: the pose graph's edge covariances
  are deliberately conservative (a floor per keyframe), which would let a sighting bend the
  laser's locally exact path; variance component estimation (``vce_rounds``, by
  :meth:`trundle.fusion.optimization.factor_graph.FactorGraph.redundancy`) rescales each group to its
  residuals;
- the error correlation of successive sightings (:mod:`trundle.fusion.optimization.error_correlation`);
- the sightings' time offset: a camera stamped on arrival lags the capture, and while the robot
  turns, a few tens of milliseconds move a marker metres away by centimetres. At the end of the
  run the offset that makes each landmark's sightings agree best (their information-weighted
  scatter, over +-``max_time_offset_s``) is found, and the landmarks are placed with it.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from trundle.fusion.geometry import compose, rotation, wrap_angle
from trundle.fusion.optimization.error_correlation import decorrelated_information
from trundle.fusion.optimization.factor_graph import BETWEEN, POSITION, FactorGraph
from trundle.fusion.optimization.pose_graph import PoseGraph
from trundle.fusion.slam.backend import PoseGraphBackend
from trundle.fusion.slam.config import SlamConfig
from trundle.fusion.slam.landmark_slam import LandmarkMap, between_covariance
from trundle.logs import messages as m
from trundle.logs.topics import LANDMARK_TOPIC

LANDMARK_KERNEL_WIDTH = 3.0
POSITION_FLOOR_M2 = 1e-6       # variance added to a sighting's position: the motion since the scan
TIME_OFFSET_STEP_S = 0.002
MIN_SIGHTINGS_FOR_OFFSET = 20  # fewer cannot tell a time offset from noise
TIME_OFFSET_CHI2 = 10.83       # chi2, 1 degree of freedom, 99.9 %: an offset the sightings call for


@dataclass(frozen=True)
class Sighting:
    """One sighting: its keyframe, landmark, stamp (s), the robot at the stamp in the keyframe's frame
    (``here``), the robot's velocity then (vx, vy, wz, robot frame) and what was seen (robot frame)."""

    node: int
    landmark: str
    stamp_s: float
    here: np.ndarray
    velocity: np.ndarray
    position: np.ndarray
    position_covariance: np.ndarray
    yaw: float
    yaw_variance: float

    @property
    def oriented(self) -> bool:
        return self.yaw_variance > 0

    def measurement(self, time_offset_s: float = 0.0, heading_variance: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """The landmark in the keyframe's frame, (x, y) or (x, y, yaw), and its covariance, with the
        stamp moved by ``time_offset_s``; ``heading_variance`` (rad^2) is the keyframe's own heading
        uncertainty, for a keyframe held fixed: it swings the landmark by its range times the angle."""
        here = compose(self.here, self.velocity * time_offset_s)
        turn = rotation(float(here[2]))
        position = here[:2] + turn @ self.position
        xy_cov = turn @ self.position_covariance @ turn.T + np.eye(2) * POSITION_FLOOR_M2
        swing = np.array([-position[1], position[0]])   # d position / d keyframe heading (m/rad)
        if not self.oriented:
            return position, xy_cov + np.outer(swing, swing) * heading_variance
        yaw = float(here[2]) + self.yaw
        lever = np.array([*(rotation(yaw).T @ swing), 1.0])   # the same in the factor's (marker's) frame, and its yaw
        return (np.array([*position, yaw]),
                between_covariance(xy_cov, self.yaw_variance, yaw) + np.outer(lever, lever) * heading_variance)


@dataclass
class LandmarkGridStats:
    messages: int = 0
    sightings: int = 0
    anonymous: int = 0
    before_first_scan: int = 0
    joint_optimizations: int = 0
    time_offset_s: float = 0.0
    revisited: list[str] = field(default_factory=list)
    noise_scales: dict[str, float] = field(default_factory=dict)
    correlation_time_s: dict[str, list[float]] = field(default_factory=dict)


class LandmarkConstraints:
    """Landmark sightings as constraints of the grid SLAM's back end (a
    :class:`trundle.fusion.slam.backend.ConstraintSource`; see the module docstring): ``topic`` is the
    LandmarkList topic the facade routes here."""

    def __init__(self, config: SlamConfig | None = None, topic: str = LANDMARK_TOPIC, correlation_rounds: int = 1,
                 vce_rounds: int = 3, max_time_offset_s: float = 0.2) -> None:
        self.config = config or SlamConfig()
        self.topic = topic
        self.correlation_rounds = correlation_rounds
        self.vce_rounds = vce_rounds
        self.max_time_offset_s = max_time_offset_s
        self.stats = LandmarkGridStats()
        self._sightings: list[Sighting] = []
        self._first_node: dict[str, int] = {}
        self._estimates: dict[str, np.ndarray] = {}
        self._graph: FactorGraph | None = None
        self._variables: dict[str, tuple[bool, int]] = {}   # landmark -> (oriented, variable index)
        self._sightings_at_optimization = 0
        self._nodes_at_landmark_optimization = 0

    def add(self, msg: m.LandmarkList, anchor: tuple[int, np.ndarray, np.ndarray] | None, nodes: int) -> bool:
        """Tie the sightings to keyframe ``anchor`` = (node, the robot at their stamp in its frame, its
        velocity: vx, vy, wz); None before the first scan. ``nodes``: keyframes so far. Returns whether
        the back end should optimise now (a landmark closes a loop, and enough keyframes since)."""
        st = self.stats
        st.messages += 1
        if anchor is None:
            st.before_first_scan += len(msg.landmarks)
            return False
        node, here, velocity = anchor
        closes_loop = False
        for o in msg.landmarks:
            if not o.id:
                st.anonymous += 1
                continue
            self._sightings.append(Sighting(node, o.id, msg.stamp_ns * 1e-9, here, velocity,
                                             o.translation[:2].copy(), o.position_covariance(), o.yaw,
                                             o.yaw_variance))
            st.sightings += 1
            first = self._first_node.setdefault(o.id, node)
            closes_loop |= node - first >= self.config.loop_closure.min_node_gap
        due = nodes - self._nodes_at_landmark_optimization >= self.config.optimization.every_keyframes
        return closes_loop and due

    # --- optimisation ------------------------------------------------------------------------
    def optimize(self, pose_graph: PoseGraph, max_iterations: int, kernel: str | None) -> bool:
        """Keyframes and the landmarks seen on more than one visit in one factor graph (the keyframes'
        optimised poses go back to ``pose_graph``); then the landmarks of a single visit, which close no
        loop and would only bend the laser's locally better path, placed on the keyframes held fixed.
        A fixed keyframe's heading uncertainty (its marginal in the joint graph) joins each of its
        sightings: a marker's corners give its bearing to a few hundredths of a degree, so without it
        the small turns between successive sightings triangulate the landmark with more weight than
        the range itself has (5 cm off at 4 m in the demo), where the keyframes' heading is good to
        a few tenths of a degree only. False (nothing done) without sightings."""
        if not self._sightings:
            return False
        graph = FactorGraph.from_pose_graph(pose_graph)
        edges = graph.factors(BETWEEN)[0].shape[0]
        kernels = {BETWEEN: (kernel, LANDMARK_KERNEL_WIDTH), POSITION: ("cauchy", LANDMARK_KERNEL_WIDTH)}
        revisited = self._revisited()
        self.stats.revisited = sorted(revisited)
        variables: dict[str, tuple[bool, int]] = {}
        joint = self._add_sightings(graph, [s for s in self._sightings if s.landmark in revisited], variables)
        graph.optimize(max_iterations, kernels)
        if joint[True] or joint[False]:
            for _ in range(self.correlation_rounds):
                self._decorrelate(graph, joint)
                graph.optimize(max_iterations, kernels)
            self._estimate_noise(graph, edges, joint, kernels, max_iterations)
        single = [s for s in self._sightings if s.landmark not in revisited]
        if single:
            nodes = sorted({s.node for s in single})
            headings = dict(zip(nodes, graph.marginal_covariances(nodes, kernels=kernels)[0][:, 2, 2], strict=True))
            graph.fixed_poses = set(range(len(graph.poses)))
            graph.fixed_points = set(range(len(graph.points)))
            self._add_sightings(graph, single, variables, headings)
            graph.optimize(max_iterations, kernels)
        pose_graph.poses = graph.poses[: len(pose_graph)]
        self._graph, self._variables = graph, variables
        for name, (oriented, index) in variables.items():
            self._estimates[name] = graph.pose(index) if oriented else graph.points[index]
        self._sightings_at_optimization = len(self._sightings)
        self._nodes_at_landmark_optimization = len(pose_graph)
        self.stats.joint_optimizations += 1
        return True

    def _add_sightings(self, graph: FactorGraph, sightings: list[Sighting], variables: dict[str, tuple[bool, int]],
                       heading_variances: dict[int, float] | None = None) -> dict[bool, list[tuple[int, Sighting]]]:
        """Landmark variables (first sight: the last estimate, else placed by its keyframe) and a factor
        per sighting, with the heading variance (rad^2) of keyframes held fixed; the factors' rows by
        kind (oriented or not), with their sightings."""
        rows: dict[bool, list[tuple[int, Sighting]]] = {True: [], False: []}
        offset = self.stats.time_offset_s
        heading_variances = heading_variances or {}
        for s in sightings:
            z, covariance = s.measurement(offset, float(heading_variances.get(s.node, 0.0)))
            if s.landmark not in variables:
                keyframe = graph.pose(s.node)
                guess = self._estimates.get(s.landmark)
                if guess is None or len(guess) != len(z):
                    guess = compose(keyframe, z) if s.oriented else keyframe[:2] + rotation(float(keyframe[2])) @ z
                variables[s.landmark] = (s.oriented, graph.add_pose(guess) if s.oriented else graph.add_point(guess))
            index = variables[s.landmark][1]
            info = np.linalg.inv(covariance)
            row = (graph.add_between(s.node, index, z, info) if s.oriented
                   else graph.add_position(s.node, index, z, info))
            rows[s.oriented].append((row, s))
        return rows

    def _revisited(self) -> set[str]:
        """The landmarks seen from keyframes at least ``loop_min_node_gap`` apart: only they close loops."""
        nodes: dict[str, list[int]] = {}
        for s in self._sightings:
            nodes.setdefault(s.landmark, []).append(s.node)
        return {name for name, seen in nodes.items() if max(seen) - min(seen) >= self.config.loop_closure.min_node_gap}

    def _groups(self, graph: FactorGraph, edges: int, rows: dict[bool, list[tuple[int, Sighting]]]
                ) -> dict[str, tuple[str, np.ndarray]]:
        """The factor groups of the variance components: laser edges, marker and point sightings."""
        between = np.zeros(len(graph.factors(BETWEEN)[0]), bool)
        between[:edges] = True
        markers = np.zeros_like(between)
        markers[[row for row, _ in rows[True]]] = True
        points = np.zeros(len(graph.factors(POSITION)[0]), bool)
        points[[row for row, _ in rows[False]]] = True
        return {"edges": (BETWEEN, between), "markers": (BETWEEN, markers), "points": (POSITION, points)}

    def _estimate_noise(self, graph: FactorGraph, edges: int, rows: dict[bool, list[tuple[int, Sighting]]], kernels,
                        max_iterations: int) -> None:
        """Variance component estimation: each group's information divided by its chi2 over its redundancy."""
        groups = self._groups(graph, edges, rows)
        totals = {name: 1.0 for name in groups}
        for _ in range(self.vce_rounds):
            scales = {}
            for name, (kind, select) in groups.items():
                if select.sum() < 10:
                    continue
                redundancy = graph.redundancy(kind, select, kernels)
                if redundancy > 1.0:
                    scales[name] = float(graph.factor_chi2(kind)[select].sum()) / redundancy
            if not scales or all(abs(math.log(max(v, 1e-12))) < math.log(1.1) for v in scales.values()):
                break
            for name, scale in scales.items():
                kind, select = groups[name]
                info = graph.factors(kind)[2]
                info[select] /= scale
                graph.set_information(kind, info)
                totals[name] *= scale
            graph.optimize(max_iterations, kernels)
        self.stats.noise_scales = {name: float(math.sqrt(v)) for name, v in totals.items()}

    def _decorrelate(self, graph: FactorGraph, rows: dict[bool, list[tuple[int, Sighting]]]) -> None:
        """Reweight each kind's sightings by the correlation time of their residuals."""
        for oriented, chosen in rows.items():
            if not chosen:
                continue
            kind = BETWEEN if oriented else POSITION
            index = np.array([row for row, _ in chosen])
            mine = [s for _, s in chosen]
            info = graph.factors(kind)[2]
            nominal = np.array([np.linalg.inv(s.measurement(self.stats.time_offset_s)[1]) for s in mine])
            groups = np.unique([s.landmark for s in mine], return_inverse=True)[1]
            info[index], tau = decorrelated_information(nominal, graph.factor_errors(kind)[index], groups,
                                                        np.array([s.stamp_s for s in mine]))
            self.stats.correlation_time_s["marker" if oriented else "point"] = [float(v) for v in tau]
            graph.set_information(kind, info)

    def estimate_time_offset(self, pose_graph: PoseGraph, kernel: str | None) -> float:
        """The sightings' time offset (s) that makes each landmark's sightings, placed by the keyframes
        as the laser alone has them, agree best (least robust information-weighted scatter), searched
        over +-``max_time_offset_s``; 0 with fewer than ``MIN_SIGHTINGS_FOR_OFFSET`` sightings, and 0
        unless it explains significantly more than no offset (the scatter's drop, in units of its
        variance factor, over ``TIME_OFFSET_CHI2``): driving straight at a marker, an offset only moves
        every sighting along the line of sight, and the noise alone would pick one."""
        if len(self._sightings) < MIN_SIGHTINGS_FOR_OFFSET or self.max_time_offset_s <= 0:
            return 0.0
        laser = copy.deepcopy(pose_graph)   # the keyframes by the laser alone: the sightings have not bent them
        laser.optimize(max_iterations=100, robust_kernel=kernel, kernel_width=3.0)
        names = np.unique([s.landmark for s in self._sightings], return_inverse=True)[1]
        nodes = sorted({s.node for s in self._sightings})
        headings = dict(zip(nodes, FactorGraph.from_pose_graph(laser).marginal_covariances(nodes)[0][:, 2, 2],
                            strict=True))
        offsets = np.arange(-self.max_time_offset_s, self.max_time_offset_s + 1e-12, TIME_OFFSET_STEP_S)
        poses = laser.poses   # a copy per call: once, not once per offset
        costs = np.array([self._scatter(float(offset), poses, names, headings) for offset in offsets])
        best, zero = int(np.argmin(costs)), int(np.argmin(np.abs(offsets)))
        redundancy = 2 * (len(self._sightings) - int(names.max()) - 1) - 1   # positions less means, less the offset
        if redundancy < 1 or costs[best] <= 0:
            return 0.0
        variance_factor = costs[best] / redundancy
        return float(offsets[best]) if (costs[zero] - costs[best]) / variance_factor > TIME_OFFSET_CHI2 else 0.0

    def _scatter(self, offset: float, poses: np.ndarray, names: np.ndarray, heading_variances: dict[int, float]
                 ) -> float:
        """The robust information-weighted scatter of each landmark's sightings about their mean, placed
        by keyframe ``poses`` (with their heading variances, rad^2) with the stamps moved by ``offset``
        (s); ``names``: each sighting's landmark."""
        where_rows: list[np.ndarray] = []
        information_rows: list[np.ndarray] = []
        for s in self._sightings:
            z, covariance = s.measurement(offset, float(heading_variances[s.node]))
            turn = rotation(float(poses[s.node, 2]))
            where_rows.append(poses[s.node, :2] + turn @ z[:2])
            information_rows.append(np.linalg.inv(turn @ (covariance[:2, :2] if not s.oriented else
                                                          _position_block(z, covariance)) @ turn.T))
        where, information = np.array(where_rows), np.array(information_rows)
        cost = 0.0
        for k in range(names.max() + 1):
            mine = names == k
            total = information[mine].sum(axis=0)
            mean = np.linalg.solve(total, np.einsum("nij,nj->i", information[mine], where[mine]))
            d = where[mine] - mean
            s2 = np.einsum("ni,nij,nj->n", d, information[mine], d)
            cost += float(np.sum(LANDMARK_KERNEL_WIDTH ** 2 * np.log1p(s2 / LANDMARK_KERNEL_WIDTH ** 2)))
        return cost

    def finish(self, backend: PoseGraphBackend) -> None:
        """After the back end's final optimisation: another if sightings came since, then the sightings'
        time offset and a last optimisation with it."""
        if len(self._sightings) != self._sightings_at_optimization:
            backend.optimize(max_iterations=100)
        offset = self.estimate_time_offset(backend.graph, backend.kernel)
        if offset != self.stats.time_offset_s:
            self.stats.time_offset_s = offset
            backend.optimize(max_iterations=100)

    # --- output ------------------------------------------------------------------------------
    def landmarks(self) -> LandmarkMap:
        """The landmarks as last optimised (map frame), with marginal covariances."""
        names = sorted(self._variables)
        if self._graph is None or not names:
            return LandmarkMap([], np.zeros((0, 2)), np.zeros((0, 2, 2)), np.zeros(0, np.int64), np.zeros(0))
        oriented = [n for n in names if self._variables[n][0]]
        points = [n for n in names if not self._variables[n][0]]
        pose_covs, point_covs = self._graph.marginal_covariances([self._variables[n][1] for n in oriented],
                                                                 [self._variables[n][1] for n in points])
        covariance = {**{n: c[:2, :2] for n, c in zip(oriented, pose_covs, strict=True)},
                      **dict(zip(points, point_covs, strict=True))}
        counts: dict[str, int] = {}
        for s in self._sightings:
            counts[s.landmark] = counts.get(s.landmark, 0) + 1
        return LandmarkMap(names, np.array([self._estimates[n][:2] for n in names]),
                           np.array([covariance[n] for n in names]), np.array([counts.get(n, 0) for n in names]),
                           np.array([wrap_angle(float(self._estimates[n][2])) if len(self._estimates[n]) == 3
                                     else np.nan for n in names]))


def from_sightings(config: SlamConfig, sightings: list[Sighting]) -> LandmarkConstraints:
    """Constraints of sightings already tied to keyframes (e.g. several sessions' in one graph, each with
    its own time offset already applied, :func:`applied_sightings`); no time offset is estimated."""
    out = LandmarkConstraints(config, max_time_offset_s=0.0)
    out._sightings = list(sightings)
    out.stats.sightings = len(sightings)
    for s in sightings:
        out._first_node[s.landmark] = min(out._first_node.get(s.landmark, s.node), s.node)
    return out


def applied_sightings(constraints: LandmarkConstraints) -> list[Sighting]:
    """Every sighting of ``constraints`` with its estimated time offset applied (the robot moved along by its
    velocity times the offset), so it means the same with no offset."""
    offset = constraints.stats.time_offset_s
    return [dataclasses.replace(s, here=compose(s.here, s.velocity * offset)) for s in constraints._sightings]


def _position_block(z: np.ndarray, covariance: np.ndarray) -> np.ndarray:
    """A marker factor's position covariance back in the keyframe's frame (the factor keeps it in the marker's)."""
    turn = rotation(float(z[2]))
    return turn @ covariance[:2, :2] @ turn.T
