"""Landmark SLAM over messages: odometry plus landmark sightings in, trajectory and landmark map out.

Two estimators with one interface (``process(topic, msg)``, ``finish()``, ``trajectory()``,
``landmarks()``), so the same object runs on a live stream or a log:

- :class:`EkfLandmarkSlam`: the EKF-SLAM of :mod:`trundle.fusion.slam.ekf_slam`, predicting with the
  odometry composed up to each sighting's stamp and updating with the sightings; causal, online.
- :class:`GraphLandmarkSlam`: the same EKF as front end (data association of anonymous
  sightings, outlier rejection, initial values), and a factor graph as back end: a pose node at
  every instant with sightings (and after every ``node_distance_m``, ``node_angle_rad`` or
  ``node_time_s`` without), odometry between nodes, a range-bearing factor per sighting (a
  marker's full pose: a landmark pose and a between factor), optimised when the run ends. The
  noise models come from the messages. Sightings of one landmark in quick succession share much
  of their error, so after a first fit the correlation time of the sighting errors is read from
  the residuals and each sighting weighs what it adds (:mod:`trundle.fusion.optimization.error_correlation`),
  then the graph is optimised again.

Odometry arrives as nav_msgs/Odometry poses (odom frame) with their twist; sightings as
``LandmarkList`` in the robot frame (base_link). The map frame is the robot's first pose.
``trajectory()`` holds one pose per odometry reading, map frame.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, fields
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import Field, create_model

from trundle.fusion.geometry import compose, rotation
from trundle.fusion.odometry.increments import Increment, MotionNoise, OdometryIncrements
from trundle.fusion.optimization.error_correlation import decorrelated_information
from trundle.fusion.optimization.factor_graph import BETWEEN, RANGE_BEARING, FactorGraph
from trundle.fusion.slam.ekf_slam import EkfSlam, EkfSlamConfig
from trundle.logs import messages as m
from trundle.logs.schema import Name, Schema, parse
from trundle.logs.topics import LANDMARK_TOPIC


@dataclass(frozen=True)
class LandmarkMap:
    """Mapped landmarks: ids, positions (M, 2) and marginal covariances (M, 2, 2), map frame;
    ``sightings`` per landmark, and ``yaw`` (M,) for landmarks whose orientation is estimated (NaN
    for points)."""

    ids: list[str]
    positions: np.ndarray
    covariances: np.ndarray
    sightings: np.ndarray
    yaw: np.ndarray


@dataclass
class LandmarkSlamStats:
    odometry: int = 0
    landmark_messages: int = 0
    sightings: int = 0
    stale_odometry: int = 0
    nodes: int = 0
    optimizations: int = 0
    iterations: int = 0
    correlation_time_s: dict[str, list[float]] = field(default_factory=dict)


def between_covariance(position_covariance: np.ndarray, yaw_variance: float, yaw: float) -> np.ndarray:
    """3x3 covariance of a between factor's error for a landmark pose seen at ``yaw`` (rad) with a
    position covariance in the observer's frame: the factor's translation error is expressed in the
    measured pose's own frame (``t2v(z^-1 (x_i^-1 x_j))``), so the ellipse turns by ``-yaw``."""
    turn = rotation(yaw)
    covariance = np.zeros((3, 3))
    covariance[:2, :2] = turn.T @ np.asarray(position_covariance, np.float64).reshape(2, 2) @ turn
    covariance[2, 2] = yaw_variance
    return covariance


class EkfLandmarkSlam:
    """EKF-SLAM over Odometry and LandmarkList messages (see the module docstring)."""

    def __init__(self, config: EkfSlamConfig | None = None, landmark_topic: str = LANDMARK_TOPIC) -> None:
        self.config = config or EkfSlamConfig()
        self.ekf = EkfSlam(self.config)
        self.landmark_topic = landmark_topic
        self.odometry = OdometryIncrements(self.config.motion)
        self.stats = LandmarkSlamStats()
        self._stamps: list[int] = []
        self._poses: list[np.ndarray] = []
        self._sightings: dict[str, int] = {}

    def process(self, topic: str, msg: m.Message) -> None:
        """Route one message: Odometry is kept for the next prediction, LandmarkList on
        ``landmark_topic`` predicts to its stamp and updates."""
        if isinstance(msg, m.Odometry):
            self.odometry.add(msg)
            self.stats.odometry += 1
        elif isinstance(msg, m.LandmarkList) and topic == self.landmark_topic:
            self.add_landmarks(msg)

    def _advance(self, stamp_ns: int) -> Increment:
        """Take the odometry up to ``stamp_ns``, record the trajectory on the way and predict."""
        increment = self.odometry.take(stamp_ns)
        self._stamps.extend(increment.stamps_ns.tolist())
        self._poses.append(compose(self.ekf.pose, increment.partial))
        self.ekf.predict(increment.delta, increment.covariance)
        self.stats.stale_odometry = self.odometry.stale
        return increment

    def add_landmarks(self, msg: m.LandmarkList) -> None:
        """Predict to the sightings' stamp and fuse them."""
        self.stats.landmark_messages += 1
        self.stats.sightings += len(msg.landmarks)
        if not self.odometry.started:
            return  # the map frame starts at the first odometry reading
        self._advance(msg.stamp_ns)
        report = self.ekf.update(msg.landmarks)
        for j in report.landmark[report.landmark >= 0]:
            name = self.ekf.ids[int(j)]
            self._sightings[name] = self._sightings.get(name, 0) + 1

    def finish(self) -> None:
        """Carry the trajectory on to the last odometry reading."""
        if self.odometry.pending_until is not None:
            self._advance(self.odometry.pending_until)

    def trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """Stamps (ns) and map poses (N, 3), one per odometry reading (up to the last sighting
        until :meth:`finish`)."""
        return np.array(self._stamps, np.int64), np.concatenate(self._poses or [np.zeros((0, 3))]).reshape(-1, 3)

    def build_map(self) -> None:
        """No occupancy grid: the estimator maps landmarks only."""
        return None

    def report(self) -> dict[str, Any]:
        """The run's counts (``stats``) and the EKF's (``ekf``)."""
        return {"stats": asdict(self.stats), "ekf": asdict(self.ekf.stats)}

    def landmarks(self) -> LandmarkMap:
        ids, positions, covariances = self.ekf.landmarks()
        return LandmarkMap(ids, positions, covariances, np.array([self._sightings.get(i, 0) for i in ids]),
                           np.full(len(ids), np.nan))


@dataclass
class GraphLandmarkSlamConfig:
    """Parameters of :class:`GraphLandmarkSlam` (metres, radians, seconds).

    ``node_*``: a pose node after this much motion or time without sightings (sightings always
    make one). ``robust_kernel`` and ``kernel_width`` (whitened units) act on the landmark factors,
    so an outlier the front end let through pulls with a bounded force. ``correlation_rounds``:
    rounds of estimating the sightings' error correlation time and reweighting them
    (:mod:`trundle.fusion.optimization.error_correlation`; 0: treat every sighting as independent).
    """

    ekf: EkfSlamConfig = field(default_factory=EkfSlamConfig)
    node_distance_m: float = 0.5
    node_angle_rad: float = math.radians(20.0)
    node_time_s: float = 5.0
    robust_kernel: str | None = "cauchy"
    kernel_width: float = 3.0
    correlation_rounds: int = 2
    max_iterations: int = 100


class _LandmarkTable(Schema):
    """A robot config's ``[landmarks]`` table: ``topic`` (the LandmarkList topic to use), the
    data ``association`` (jcbb, nn), the graph's node spacing (m, rad, s) and
    ``correlation_rounds``; ``motion_*`` (the :class:`MotionNoise` fields) are added below."""

    topic: Name | None = None
    association: Literal["jcbb", "nn"] = "jcbb"
    correlation_rounds: Annotated[int, Field(ge=0)] = GraphLandmarkSlamConfig.correlation_rounds
    node_distance_m: Annotated[float, Field(gt=0)] = GraphLandmarkSlamConfig.node_distance_m
    node_angle_rad: Annotated[float, Field(gt=0)] = GraphLandmarkSlamConfig.node_angle_rad
    node_time_s: Annotated[float, Field(gt=0)] = GraphLandmarkSlamConfig.node_time_s


_MOTION: dict[str, Any] = {f"motion_{f.name}": (Annotated[float, Field(ge=0)], f.default) for f in fields(MotionNoise)}
LandmarkOptions = create_model("LandmarkOptions", __base__=_LandmarkTable, __doc__=_LandmarkTable.__doc__, **_MOTION)
"""The ``[landmarks]`` table, with one ``motion_<name>`` per :class:`MotionNoise` field (m, rad, s)."""


def landmark_configs(table: Mapping[str, Any]) -> tuple[EkfSlamConfig, GraphLandmarkSlamConfig]:
    """The EKF and graph configs of a ``[landmarks]`` table; an unknown key or a bad value is a
    ConfigError naming it."""
    options = parse(LandmarkOptions, table, "landmarks")
    motion = MotionNoise(**{f.name: getattr(options, f"motion_{f.name}") for f in fields(MotionNoise)})
    ekf = EkfSlamConfig(motion=motion, association=options.association)
    graph = GraphLandmarkSlamConfig(ekf=ekf, correlation_rounds=options.correlation_rounds,
                                    node_distance_m=options.node_distance_m, node_angle_rad=options.node_angle_rad,
                                    node_time_s=options.node_time_s)
    return ekf, graph


class GraphLandmarkSlam:
    """Landmark SLAM with an EKF front end and a factor-graph back end (see the module docstring)."""

    def __init__(self, config: GraphLandmarkSlamConfig | None = None, landmark_topic: str = LANDMARK_TOPIC) -> None:
        self.config = config or GraphLandmarkSlamConfig()
        self.front = EkfLandmarkSlam(self.config.ekf, landmark_topic)
        self.landmark_topic = landmark_topic
        self.graph = FactorGraph()
        self.stats = self.front.stats
        self._node_stamps: list[int] = []
        self._odometry_factors: list[int] = []
        self._marker_factors: list[int] = []
        self._points: dict[str, int] = {}     # landmark id -> graph point
        self._oriented: dict[str, int] = {}   # landmark id -> graph pose (a marker's full pose)
        self._readings: list[tuple[int, np.ndarray, np.ndarray]] = []  # node, stamps, partial poses
        self._sightings: dict[str, int] = {}
        self._last_node_odometry: np.ndarray | None = None
        self._last_odometry: np.ndarray | None = None

    # --- input -------------------------------------------------------------------------------
    def process(self, topic: str, msg: m.Message) -> None:
        """Route one message: Odometry (a node when the robot moved far enough), LandmarkList on
        ``landmark_topic`` (a node with its sightings)."""
        if isinstance(msg, m.Odometry):
            self.front.process(topic, msg)
            here = self._last_odometry = np.array([msg.x, msg.y, msg.theta])
            if self._last_node_odometry is None:
                self._add_node(msg.stamp_ns)
                self._last_node_odometry = here
                return
            last = self._last_node_odometry
            if (math.hypot(msg.x - last[0], msg.y - last[1]) >= self.config.node_distance_m
                    or abs(math.remainder(msg.theta - last[2], 2.0 * math.pi)) >= self.config.node_angle_rad
                    or (msg.stamp_ns - self._node_stamps[-1]) * 1e-9 >= self.config.node_time_s):
                self._add_node(msg.stamp_ns)
                self._last_node_odometry = here
        elif isinstance(msg, m.LandmarkList) and topic == self.landmark_topic:
            self.add_landmarks(msg)

    def _add_node(self, stamp_ns: int) -> int:
        """A pose node at ``stamp_ns`` (the front end predicted there), odometry from the previous node."""
        front = self.front
        increment = front._advance(stamp_ns)
        node = self.graph.add_pose(front.ekf.pose)
        if self._node_stamps:
            self._readings.append((node - 1, increment.stamps_ns, increment.partial))
            covariance = increment.covariance + np.diag([1e-8, 1e-8, 1e-10])  # a floor: a robot standing still
            self._odometry_factors.append(self.graph.add_between(node - 1, node, increment.delta,
                                                                 np.linalg.inv(covariance)))
        else:
            self._readings.append((node, increment.stamps_ns, np.zeros((len(increment.stamps_ns), 3))))
        self._node_stamps.append(int(stamp_ns))
        self.stats.nodes = len(self._node_stamps)
        return node

    def add_landmarks(self, msg: m.LandmarkList) -> None:
        """A node at the sightings' stamp, the front end's update, a factor per sighting it kept."""
        self.stats.landmark_messages += 1
        self.stats.sightings += len(msg.landmarks)
        if not self.front.odometry.started:
            return
        node = self._add_node(msg.stamp_ns)
        self._last_node_odometry = self._last_odometry
        report = self.front.ekf.update(msg.landmarks)
        self.graph.set_pose(node, self.front.ekf.pose)
        for observation, j in zip(msg.landmarks, report.landmark, strict=True):
            if j < 0:
                continue
            name = self.front.ekf.ids[int(j)]
            self._sightings[name] = self._sightings.get(name, 0) + 1
            if observation.oriented:
                self._add_marker(node, name, observation)
            else:
                point = self._points.get(name)
                if point is None:
                    at = 3 + 2 * int(j)   # the landmark's position in the EKF state
                    point = self._points[name] = self.graph.add_point(self.front.ekf.mean[at:at + 2])
                self.graph.add_range_bearing(node, point, observation.range, observation.bearing,
                                             np.linalg.inv(observation.covariance))

    def _add_marker(self, node: int, name: str, observation: m.LandmarkObservation) -> None:
        """A marker's full pose: a landmark pose variable and a between factor from the robot's node."""
        seen = np.array([observation.translation[0], observation.translation[1], observation.yaw])
        landmark = self._oriented.get(name)
        if landmark is None:
            landmark = self._oriented[name] = self.graph.add_pose(compose(self.graph.pose(node), seen))
        covariance = between_covariance(observation.position_covariance(), observation.yaw_variance, float(seen[2]))
        self._marker_factors.append(self.graph.add_between(node, landmark, seen, np.linalg.inv(covariance)))

    # --- optimisation ------------------------------------------------------------------------
    def _kernels(self) -> dict[str, tuple[str | None, float]]:
        return {RANGE_BEARING: (self.config.robust_kernel, self.config.kernel_width)}

    def finish(self) -> None:
        """Carry the trajectory to the last reading, then optimise with noise re-estimation."""
        last = self.front.odometry.pending_until
        if last is not None and self._node_stamps:
            self._add_node(last)
        self.optimize()

    def optimize(self) -> None:
        """Levenberg-Marquardt; then ``correlation_rounds`` rounds of estimating the sightings' error
        correlation time from the residuals, reweighting them and optimising again."""
        cfg = self.config
        if len(self._node_stamps) < 2:
            return
        kernels = self._kernels()
        result = self.graph.optimize(cfg.max_iterations, kernels)
        self.stats.optimizations += 1
        self.stats.iterations += result.iterations
        stamps = np.zeros(len(self.graph.poses))
        robot = np.setdiff1d(np.arange(len(stamps)), list(self._oriented.values()))
        stamps[robot] = np.array(self._node_stamps) * 1e-9
        between = self.graph.factors(BETWEEN)
        markers = np.zeros(len(between[0]), bool)
        markers[self._marker_factors] = True
        nominal = {RANGE_BEARING: self.graph.factors(RANGE_BEARING)[2], BETWEEN: between[2]}
        for _ in range(cfg.correlation_rounds):
            tau = {}
            for kind, select, group_column in ((RANGE_BEARING, None, 1), (BETWEEN, markers, 1)):
                variables, _, _ = self.graph.factors(kind)
                chosen = np.ones(len(variables), bool) if select is None else select
                if chosen.sum() == 0:
                    continue
                reweighted = nominal[kind].copy()
                reweighted[chosen], tau[kind] = decorrelated_information(
                    nominal[kind][chosen], self.graph.factor_errors(kind)[chosen], variables[chosen, group_column],
                    stamps[variables[chosen, 0]])
                self.graph.set_information(kind, reweighted)
            self.stats.correlation_time_s = {("range_bearing" if k == RANGE_BEARING else "marker"):
                                             [float(v) for v in t] for k, t in tau.items()}
            result = self.graph.optimize(cfg.max_iterations, kernels)
            self.stats.optimizations += 1
            self.stats.iterations += result.iterations

    # --- output ------------------------------------------------------------------------------
    def trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """Stamps (ns) and map poses (N, 3), one per odometry reading, each from its node's pose."""
        if not self._readings:
            return np.zeros(0, np.int64), np.zeros((0, 3))
        nodes = self.graph.poses
        stamps = np.concatenate([s for _, s, _ in self._readings])
        poses = np.concatenate([compose(nodes[k], p) for k, _, p in self._readings]).reshape(-1, 3)
        return stamps.astype(np.int64), poses

    def build_map(self) -> None:
        """No occupancy grid: the estimator maps landmarks only."""
        return None

    def report(self) -> dict[str, Any]:
        """The run's counts (``stats``) and the front end's EKF's (``ekf``)."""
        return {"stats": asdict(self.stats), "ekf": asdict(self.front.ekf.stats)}

    def node_poses(self) -> tuple[np.ndarray, np.ndarray]:
        """Stamps (ns) and poses (K, 3) of the graph's robot nodes."""
        robot = np.setdiff1d(np.arange(len(self.graph.poses)), list(self._oriented.values()))
        return np.array(self._node_stamps, np.int64), self.graph.poses[robot]

    def landmarks(self) -> LandmarkMap:
        """The optimised landmarks with marginal covariances (points and markers)."""
        names = list(self._points) + list(self._oriented)
        pose_covs, point_covs = self.graph.marginal_covariances(list(self._oriented.values()),
                                                                list(self._points.values()), self._kernels())
        points, poses = self.graph.points, self.graph.poses
        positions = np.vstack([points[list(self._points.values())].reshape(-1, 2),
                               poses[list(self._oriented.values())][:, :2].reshape(-1, 2)])
        covariances = np.concatenate([point_covs, pose_covs[:, :2, :2]])
        yaw = np.concatenate([np.full(len(self._points), np.nan), poses[list(self._oriented.values())][:, 2]])
        return LandmarkMap(names, positions, covariances, np.array([self._sightings.get(n, 0) for n in names]), yaw)

