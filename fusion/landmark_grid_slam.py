"""Grid SLAM with landmarks in its pose graph: marker sightings tighten the map as Cartographer's
landmark constraints do.

:class:`LandmarkGridSlam` is the grid SLAM of :mod:`trundle.fusion.slam` plus LandmarkList
messages. A sighting (an id is needed: the grid SLAM does not associate anonymous features) is
tied to the keyframe of the latest scan: the robot's pose at the sighting's stamp in that
keyframe's frame is the scan's offset from its keyframe composed with the odometry since the
scan, and the landmark goes through it into the keyframe's frame. A marker with its full pose is
a landmark *pose* with a between factor (x, y, yaw), like Cartographer's translation and rotation
weights; a point landmark has a relative-position factor. Whenever the pose graph is optimised
(loop closures, the end of the run, or a landmark seen again from a keyframe far from where it
was first seen) the keyframes and the landmarks are optimised together as one
:class:`trundle.fusion.factor_graph.FactorGraph`, the landmark factors under a Cauchy kernel, so
one bad sighting pulls with a bounded force. As in the landmark graph, sightings of one landmark
in quick succession share their error: after a first fit their correlation time is read from the
residuals and each weighs what it adds (:mod:`trundle.fusion.error_correlation`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from trundle.fusion.error_correlation import decorrelated_information
from trundle.fusion.factor_graph import BETWEEN, POSITION, FactorGraph
from trundle.fusion.geometry import compose, relative, rotation
from trundle.fusion.landmark_slam import LANDMARK_TOPIC, LandmarkMap
from trundle.fusion.odometry import DiffDriveOdometry
from trundle.fusion.slam import ScanResult, Slam, SlamConfig
from trundle.logs import messages as m

LANDMARK_KERNEL_WIDTH = 3.0
POSITION_FLOOR_M2 = 1e-6   # variance added to a sighting's position: the motion since the scan


@dataclass(frozen=True)
class _Sighting:
    node: int
    landmark: str
    stamp_s: float
    measurement: np.ndarray    # (x, y) or (x, y, yaw) in the keyframe's frame
    covariance: np.ndarray


@dataclass
class LandmarkGridStats:
    messages: int = 0
    sightings: int = 0
    anonymous: int = 0
    before_first_scan: int = 0
    joint_optimizations: int = 0
    correlation_time_s: dict[str, list[float]] = field(default_factory=dict)


class LandmarkGridSlam(Slam):
    """Grid SLAM whose pose graph also holds the landmarks of ``landmark_topic`` (see the module docstring)."""

    def __init__(self, config: SlamConfig | None = None, odometry: DiffDriveOdometry | None = None,
                 laser_pose: tuple[float, float, float] | None = None, landmark_topic: str = LANDMARK_TOPIC,
                 correlation_rounds: int = 1) -> None:
        super().__init__(config, odometry, laser_pose)
        self.landmark_topic = landmark_topic
        self.correlation_rounds = correlation_rounds
        self.landmark_stats = LandmarkGridStats()
        self._sightings: list[_Sighting] = []
        self._first_node: dict[str, int] = {}
        self._estimates: dict[str, np.ndarray] = {}
        self._graph: FactorGraph | None = None
        self._variables: dict[str, tuple[bool, int]] = {}   # landmark -> (oriented, variable index)
        self._sightings_at_optimization = 0
        self._nodes_at_landmark_optimization = 0

    def process(self, topic: str, msg: m.Message) -> ScanResult | None:
        if isinstance(msg, m.LandmarkList):
            if topic == self.landmark_topic:
                self.add_landmarks(msg)
            return None
        return super().process(topic, msg)

    def add_landmarks(self, msg: m.LandmarkList) -> None:
        """Tie the sightings to the latest scan's keyframe; optimise when a landmark closes a loop."""
        st = self.landmark_stats
        st.messages += 1
        if not self._scan_node:
            st.before_first_scan += len(msg.landmarks)
            return
        node, offset = self._scan_node[-1], self._scan_rel[-1]
        now, at_scan = self.odometry_at(msg.stamp_ns), self._last_scan_odom
        here = compose(offset, relative(at_scan, now)) if now is not None and at_scan is not None else offset
        closes_loop = False
        for o in msg.landmarks:
            if not o.id:
                st.anonymous += 1
                continue
            turn = rotation(float(here[2]))
            position = here[:2] + turn @ o.translation[:2]
            xy_cov = turn @ o.position_covariance() @ turn.T + np.eye(2) * POSITION_FLOOR_M2
            if o.oriented:
                measurement = np.array([*position, float(here[2]) + o.yaw])
                covariance = np.zeros((3, 3))
                covariance[:2, :2], covariance[2, 2] = xy_cov, o.yaw_variance
            else:
                measurement, covariance = position, xy_cov
            self._sightings.append(_Sighting(node, o.id, msg.stamp_ns * 1e-9, measurement, covariance))
            st.sightings += 1
            first = self._first_node.setdefault(o.id, node)
            closes_loop |= node - first >= self.config.loop_min_node_gap
        due = len(self.graph) - self._nodes_at_landmark_optimization >= self.config.optimize_every_keyframes
        if closes_loop and due:
            self.optimize()

    # --- optimisation ------------------------------------------------------------------------
    def _optimize_graph(self, max_iterations: int, kernel: str | None) -> None:
        """Keyframes and landmarks in one factor graph; the keyframes' optimised poses go back to the pose graph."""
        if not self._sightings:
            super()._optimize_graph(max_iterations, kernel)
            return
        graph = FactorGraph.from_pose_graph(self.graph)
        variables: dict[str, tuple[bool, int]] = {}
        kinds = {True: BETWEEN, False: POSITION}
        rows: dict[bool, list[int]] = {True: [], False: []}
        poses = graph.poses
        for s in self._sightings:
            oriented = len(s.measurement) == 3
            if s.landmark not in variables:
                guess = self._estimates.get(s.landmark)
                if guess is None or len(guess) != len(s.measurement):
                    guess = compose(poses[s.node], s.measurement) if oriented else \
                        poses[s.node, :2] + rotation(float(poses[s.node, 2])) @ s.measurement
                variables[s.landmark] = (oriented, graph.add_pose(guess) if oriented else graph.add_point(guess))
            _, index = variables[s.landmark]
            info = np.linalg.inv(s.covariance)
            if oriented:
                rows[True].append(graph.add_between(s.node, index, s.measurement, info))
            else:
                rows[False].append(graph.add_position(s.node, index, s.measurement, info))
        kernels = {BETWEEN: (kernel, LANDMARK_KERNEL_WIDTH), POSITION: ("cauchy", LANDMARK_KERNEL_WIDTH)}
        graph.optimize(max_iterations, kernels)
        for _ in range(self.correlation_rounds):
            self._reweight(graph, rows, kinds)
            graph.optimize(max_iterations, kernels)
        self.graph.poses = graph.poses[: len(self.graph)]
        self._graph, self._variables = graph, variables
        for name, (oriented, index) in variables.items():
            self._estimates[name] = graph.pose(index) if oriented else graph.points[index]
        self._sightings_at_optimization = len(self._sightings)
        self._nodes_at_landmark_optimization = len(self.graph)
        self.landmark_stats.joint_optimizations += 1

    def _reweight(self, graph: FactorGraph, rows: dict[bool, list[int]], kinds: dict[bool, str]) -> None:
        """Reweight each kind's landmark factors by the correlation time of their residuals."""
        stamps = {True: [], False: []}
        names = {True: [], False: []}
        for s in self._sightings:
            oriented = len(s.measurement) == 3
            stamps[oriented].append(s.stamp_s)
            names[oriented].append(s.landmark)
        for oriented, chosen in rows.items():
            if not chosen:
                continue
            kind = kinds[oriented]
            _, _, info = graph.factors(kind)
            nominal = np.array([np.linalg.inv(s.covariance) for s in self._sightings
                                if (len(s.measurement) == 3) == oriented])
            groups = np.unique(names[oriented], return_inverse=True)[1]
            info[chosen], tau = decorrelated_information(nominal, graph.factor_errors(kind)[chosen], groups,
                                                         np.array(stamps[oriented]))
            self.landmark_stats.correlation_time_s["marker" if oriented else "point"] = [float(v) for v in tau]
            graph.set_information(kind, info)

    def finish(self) -> None:
        """The final optimisation, also when only landmarks arrived since the last one."""
        super().finish()
        if len(self._sightings) != self._sightings_at_optimization:
            self.optimize(max_iterations=100)

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
        covariance = {**{n: c[:2, :2] for n, c in zip(oriented, pose_covs)}, **dict(zip(points, point_covs))}
        counts: dict[str, int] = {}
        for s in self._sightings:
            counts[s.landmark] = counts.get(s.landmark, 0) + 1
        return LandmarkMap(names, np.array([self._estimates[n][:2] for n in names]),
                           np.array([covariance[n] for n in names]), np.array([counts.get(n, 0) for n in names]),
                           np.array([self._estimates[n][2] if len(self._estimates[n]) == 3 else np.nan for n in names]))
