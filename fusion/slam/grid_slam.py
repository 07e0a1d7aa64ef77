"""Online 2-D grid SLAM, split as Cartographer splits it; this facade routes messages and wires the parts.

- :mod:`trundle.fusion.slam.local`: the local trajectory builder. Per scan: the wheel odometry
  increment (or the motion model) predicts an EKF in the local frame, the scan is matched against
  the active submap (:mod:`trundle.fusion.slam.tracking`), and a scan that moved far enough (or
  waited long enough) becomes a keyframe inserted into the submaps.
- :mod:`trundle.fusion.slam.backend`: the global back end. Keyframes are pose-graph nodes; new ones
  are searched for loop closures in the finished submaps (:mod:`trundle.fusion.slam.loop_closure`);
  the graph is optimised with a robust kernel, and the map frame follows the optimised poses.
  Landmark sightings join it as a constraint source (:mod:`trundle.fusion.slam.landmark_grid_slam`).

Every scan's map pose is kept relative to its keyframe, so after :meth:`Slam.finish`
``trajectory()`` gives one optimised pose per scan and ``build_map()`` rebuilds the occupancy grid
from the optimised keyframes. Options: :class:`trundle.fusion.slam.config.SlamConfig`.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from trundle.fusion.geometry import compose, inverse, relative
from trundle.fusion.mapping.map_check import MapCheck
from trundle.fusion.mapping.occupancy_grid import LogOddsGrid
from trundle.fusion.matching.scan_matching import MatchResult
from trundle.fusion.odometry.diff_drive import DiffDriveOdometry
from trundle.fusion.optimization.pose_graph import PoseGraph
from trundle.fusion.slam.backend import MapInputs, PoseGraphBackend
from trundle.fusion.slam.config import SlamConfig
from trundle.fusion.slam.local import LocalTrajectoryBuilder
from trundle.fusion.slam.stats import SlamStats, summary
from trundle.logs import messages as m
from trundle.logs.frames import FrameTree

if TYPE_CHECKING:
    from trundle.fusion.slam.landmark_grid_slam import LandmarkConstraints
    from trundle.fusion.slam.landmark_slam import LandmarkMap


@dataclass
class ScanResult:
    """What happened to one scan: its map pose, the match (None if none), keyframe node (or -1)."""

    stamp_ns: int
    pose_map: np.ndarray
    match: MatchResult | None
    matched: bool
    searched: bool
    node: int


class Slam:
    """The online grid SLAM; feed it messages with :meth:`process`.

    ``odometry`` turns ``JointState`` wheel angles into odometry (None: use ``Odometry`` messages if
    any arrive); ``laser_pose`` is the laser's pose in base_link (else taken from ``/tf_static``, chained to
    base_link by :class:`trundle.logs.frames.FrameTree`; a scan frame the log never places is base_link itself);
    ``landmarks``: the sightings (``LandmarkList`` on its topic) the back end optimises with the keyframes.
    """

    def __init__(self, config: SlamConfig | None = None, odometry: DiffDriveOdometry | None = None,
                 laser_pose: tuple[float, float, float] | None = None,
                 landmarks: LandmarkConstraints | None = None) -> None:
        self.config = config or SlamConfig()
        self.wheels = odometry
        self.laser_pose = None if laser_pose is None else np.asarray(laser_pose, np.float64)
        self.stats = SlamStats()
        self.local = LocalTrajectoryBuilder(self.config, self.stats)
        self.backend = PoseGraphBackend(self.config, self.stats, self.local.submaps, landmarks)
        self.landmark_constraints = landmarks
        self.map_to_odom = np.zeros(3)
        self.frames = FrameTree()
        self.keyframe_scans_taken: list[m.LaserScan] = []  # each keyframe's scan as logged (the session bundle)
        self.keyframe_mounts: list[np.ndarray] = []

    @property
    def graph(self) -> PoseGraph:
        """The back end's pose graph of the keyframes."""
        return self.backend.graph

    # --- input -------------------------------------------------------------------------------

    def process(self, topic: str, msg: m.Message) -> ScanResult | None:
        """Route one message: scans on the configured topic return a :class:`ScanResult`."""
        if isinstance(msg, m.LaserScan):
            return self.add_scan(msg) if topic == self.config.scan.topic else None
        if isinstance(msg, m.LandmarkList):
            if self.landmark_constraints is not None and topic == self.landmark_constraints.topic:
                self.add_landmarks(msg)
        elif isinstance(msg, m.JointState) and self.wheels is not None:
            odom = self.wheels.update(msg)
            if odom is not None:
                self.add_odometry(odom)
        elif isinstance(msg, m.Odometry) and self.wheels is None:
            self.add_odometry(msg)
        else:
            self.frames.add(topic, msg)
        return None

    def add_odometry(self, odom: m.Odometry) -> None:
        """Remember an odometry pose (odom frame) for interpolation at scan times."""
        self.local.odometry.add(odom)

    def odometry_at(self, stamp_ns: int) -> np.ndarray | None:
        """Odometry pose at ``stamp_ns`` (None: none within ``[slam.odometry] timeout_s``)."""
        return self.local.odometry.at(stamp_ns)

    def add_scan(self, scan: m.LaserScan) -> ScanResult:
        """Track one scan, add a keyframe if due (closing loops); returns its map pose."""
        mount = (self.laser_pose if self.laser_pose is not None
                 else self.frames.mount(scan.frame_id, unknown_is_base=True))
        local = self.local.add_scan(scan, mount)
        node = -1 if local.insertion is None else self.backend.add_keyframe(local.insertion)
        if local.insertion is not None:
            self.keyframe_scans_taken.append(scan)
            self.keyframe_mounts.append(np.asarray(mount, np.float64).copy())
        self.backend.add_scan(local.stamp_ns, local.keyframe, local.offset, mount)
        pose_map = compose(self.backend.map_from_local, local.pose_local)
        if local.odometry is not None:
            self.map_to_odom = compose(pose_map, inverse(local.odometry))
        return ScanResult(scan.stamp_ns, pose_map, local.match, local.matched, local.searched, node)

    def add_landmarks(self, msg: m.LandmarkList) -> None:
        """Tie the sightings to the latest scan's keyframe (the robot at their stamp in its frame: the
        scan's offset and the odometry since); optimise when they close a loop."""
        assert self.landmark_constraints is not None
        latest = self.backend.latest_scan()
        anchor = None
        if latest is not None:
            node, offset = latest
            now, at_scan = self.odometry_at(msg.stamp_ns), self.local.last_scan_odometry
            here = compose(offset, relative(at_scan, now)) if now is not None and at_scan is not None else offset
            anchor = (node, here, self.local.motion.velocity)
        if self.landmark_constraints.add(msg, anchor, len(self.graph)):
            self.backend.optimize()

    def finish(self) -> None:
        """End of the run: the back end's final optimisation."""
        self.backend.finish()

    # --- output ------------------------------------------------------------------------------

    def trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """Stamps (ns) and optimised map poses (N, 3) of every scan, in arrival order."""
        return self.backend.trajectory()

    def build_map(self, resolution: float | None = None, inputs: MapInputs | None = None) -> LogOddsGrid:
        """The occupancy grid of every keyframe scan at its optimised pose (now, or as ``inputs`` took them)."""
        return self.backend.build_map(resolution, inputs)

    def map_inputs(self) -> MapInputs:
        """A snapshot of what the map is made of, for :meth:`build_map` on another thread."""
        return self.backend.map_inputs()

    def landmarks(self) -> LandmarkMap | None:
        """The landmarks as last optimised (None without landmark constraints)."""
        return None if self.landmark_constraints is None else self.landmark_constraints.landmarks()

    def report(self) -> dict[str, Any]:
        """Counts of the run, the match scores and scan-to-submap residuals (m) summarised, and the
        landmark constraints' own counts (``landmarks``) if any."""
        st = self.stats
        counts = {k: v for k, v in asdict(st).items() if k not in ("scores", "residuals")}
        out: dict[str, Any] = {**counts, "match_score": summary(st.scores),
                               "scan_to_submap_residual_m": summary(st.residuals)}
        if self.landmark_constraints is not None:
            out["landmarks"] = asdict(self.landmark_constraints.stats)
        return out

    def keyframe_stamps(self) -> np.ndarray:
        """Stamps (ns) of the keyframes."""
        return self.backend.keyframe_stamps()

    def keyframe_poses(self) -> np.ndarray:
        """Optimised map poses (K, 3) of the keyframes."""
        return self.backend.graph.poses

    def loop_edges(self) -> np.ndarray:
        """Node pairs (L, 2) of the loop-closure edges kept."""
        return self.backend.loop_edges()

    def check_map(self) -> MapCheck:
        """The map self-check at the optimised poses (:meth:`PoseGraphBackend.check_map`)."""
        return self.backend.check_map()

    def keyframe_endpoints(self) -> list[np.ndarray]:
        """Every keyframe's scan points (N, 2) at its optimised pose, map frame."""
        return self.backend.keyframe_endpoints()

    def keyframe_scans(self, first: int, last: int) -> np.ndarray:
        """Optimised map poses of the scans whose keyframes are ``first`` .. ``last`` (inclusive)."""
        return self.backend.keyframe_scans(first, last)

    def map_residuals(self, grid: LogOddsGrid) -> np.ndarray:
        """Mean distance (m) of each keyframe's points to ``grid``'s occupied cells at its optimised pose."""
        return self.backend.map_residuals(grid)
