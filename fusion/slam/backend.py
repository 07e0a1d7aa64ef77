"""The global back end of the grid SLAM (Cartographer's ``PoseGraph2D``): the keyframes in a pose graph,
loop closures (:mod:`trundle.fusion.slam.loop_closure`), robust optimisation, and what is made at the
optimised poses: trajectory, map, scan endpoints, the map self-check.

Every scan's pose is kept relative to its keyframe, so after the final optimisation
``trajectory()`` gives one optimised pose per scan. Other constraints join the optimisation
through a :class:`ConstraintSource` (landmarks: :mod:`trundle.fusion.slam.landmark_grid_slam`).
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from trundle.fusion.geometry import compose, inverse, transform_points, voxel_filter
from trundle.fusion.mapping.map_check import MapCheck, check_map
from trundle.fusion.mapping.occupancy_grid import LogOddsGrid
from trundle.fusion.mapping.submaps import Submap, SubmapStack
from trundle.fusion.matching.scan_matching import refine_pose
from trundle.fusion.optimization.pose_graph import PoseGraph
from trundle.fusion.slam.config import SlamConfig
from trundle.fusion.slam.local import Insertion
from trundle.fusion.slam.loop_closure import CHI2_3DOF_999, Closure, LoopCloser
from trundle.fusion.slam.stats import SlamStats


class ConstraintSource(Protocol):
    """Constraints beyond the laser's that the back end optimises with its pose graph."""

    def optimize(self, graph: PoseGraph, max_iterations: int, kernel: str | None) -> bool:
        """Optimise ``graph`` together with the source's constraints (the optimised keyframe poses go
        back into ``graph``); False when the source has none yet (the graph is optimised alone)."""
        ...

    def finish(self, backend: PoseGraphBackend) -> None:
        """End of the run, after the back end's final optimisation (may optimise again)."""
        ...


@dataclass(frozen=True)
class MapInputs:
    """The keyframes a map is made of: their map poses (K, 3), points (N, 2, base_link) and the ends of
    their no-return rays (or None), the laser's mount on base_link (3,) or one per keyframe (K, 3: sessions
    mapped with other mounts), and the map's resolution (m)."""

    poses: np.ndarray
    points: tuple[np.ndarray, ...]
    free: tuple[np.ndarray | None, ...]
    mount: np.ndarray
    resolution: float


class MapBuilder:
    """The occupancy map of the keyframes kept up to date: each keyframe's rays are cast once, when it is
    new, and the whole map is cast again only when a pose it was cast at has moved (the graph was
    optimised: a loop closed), the mount or the resolution changed. The grid so made equals the one
    cast from the start, cell for cell (the same rays in the same order). Thread-safe: a map thread
    builds while the caller's ``finish`` may build too."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._grid: LogOddsGrid | None = None
        self._cast = MapInputs(np.zeros((0, 3)), (), (), np.zeros(3), 0.0)   # what the grid holds

    def build(self, inputs: MapInputs) -> LogOddsGrid:
        """The map of ``inputs``, seen-through cells cleared (a copy: the builder's grid goes on)."""
        with self._lock:
            done, cast = len(self._cast.poses), self._cast
            mounts = _per_keyframe(inputs.mount, len(inputs.poses))
            moved = (not np.array_equal(inputs.poses[:done], cast.poses)
                     or not np.array_equal(mounts[:done], _per_keyframe(cast.mount, done)))
            if self._grid is None or moved or inputs.resolution != cast.resolution:
                self._grid, done = LogOddsGrid(inputs.resolution, mark_returns=True), 0
            grid = self._grid
            for pose, laser, points, free in zip(inputs.poses[done:], mounts[done:], inputs.points[done:],
                                                 inputs.free[done:], strict=True):
                origin = compose(pose, laser)[:2]
                c, s = math.cos(pose[2]), math.sin(pose[2])
                rot = np.array([[c, -s], [s, c]])
                hits = points @ rot.T + pose[:2]
                free_ends = None if free is None else free @ rot.T + pose[:2]
                grid.insert_rays(origin, hits, free_ends)
            self._cast = inputs
            out = grid.copy()
        out.clear_seen_through()
        return out


def _per_keyframe(mount: np.ndarray, count: int) -> np.ndarray:
    """The laser's mount (3,) or mounts (K, 3) as one row per keyframe (``count``, 3)."""
    return np.broadcast_to(np.asarray(mount, np.float64), (count, 3))


def keyframe_grid(poses: np.ndarray, points: list[np.ndarray], free: list[np.ndarray | None], mount: np.ndarray,
                  resolution: float) -> LogOddsGrid:
    """A fresh occupancy grid (``resolution`` m/cell) from keyframe scans: ``points`` and no-return ends
    ``free`` (robot frame) at ``poses`` (map frame), a laser at ``mount`` (base_link; one for all or one per
    keyframe), free wherever the laser only ever saw through: :class:`MapBuilder` once."""
    return MapBuilder().build(MapInputs(np.asarray(poses, np.float64), tuple(points), tuple(free),
                                        np.asarray(mount, np.float64), resolution))


def check_keyframes(config: SlamConfig, submaps: list[Submap], poses: np.ndarray, points: list[np.ndarray],
                    spacing: np.ndarray, mount: np.ndarray) -> MapCheck:
    """The map self-check (:func:`trundle.fusion.mapping.map_check.check_map`) of keyframes at ``poses``:
    each against the ``submaps`` outside the two it was tracked against and inserted into (a laser at
    ``mount``, one for all or one per keyframe; ``spacing``: each keyframe's angle between beams, rad)."""
    frames = np.array([s.local_to_map(poses[s.anchor_node]) for s in submaps]).reshape(-1, 3)
    thinned = [voxel_filter(p, config.scan.voxel_m) for p in points]
    mounts = _per_keyframe(mount, len(poses))
    ranges = [np.hypot(*(p - laser[:2]).T) for p, laser in zip(thinned, mounts, strict=True)]
    opts = config.map_check
    return check_map(submaps, frames, poses, thinned, ranges, np.asarray(spacing),
                     2 * config.submaps.scans_per_submap, opts.tolerance_cells, opts.min_stretch)


class PoseGraphBackend:
    """Keyframes of the local builder in a pose graph, closed and optimised (see the module docstring)."""

    def __init__(self, config: SlamConfig, stats: SlamStats, submaps: SubmapStack,
                 constraints: ConstraintSource | None = None) -> None:
        self.config = config
        self.stats = stats
        self.submaps = submaps
        self.constraints = constraints
        self.graph = PoseGraph()
        self.loops = LoopCloser(config, stats, submaps)
        self.map_from_local = np.zeros(3)
        self.mount = np.zeros(3)  # the laser's mount (base_link) of the latest scan
        self._local: list[np.ndarray] = []
        self._points: list[np.ndarray] = []
        self._free: list[np.ndarray | None] = []
        self._stamps: list[int] = []
        self._spacing: list[float] = []  # angle between beams of each keyframe's scan (rad)
        self._scan_node: list[int] = []
        self._scan_rel: list[np.ndarray] = []
        self._scan_stamp: list[int] = []
        self._loop_edges: list[int] = []
        self._map = MapBuilder()
        self._nodes_at_last_optimization = 0
        self._loops_at_last_optimization = 0

    @property
    def kernel(self) -> str | None:
        return self.config.optimization.kernel

    def add_keyframe(self, insertion: Insertion) -> int:
        """A node with its edge from the previous keyframe; searched for loop closures when due, and the
        graph optimised when loops were added and enough keyframes since the last time. Returns the node."""
        node = self.graph.add_node(compose(self.map_from_local, insertion.pose_local))
        edge_covariance, heading = None, 0.0
        if insertion.edge is not None:
            measurement, edge_covariance, heading = insertion.edge
            self.graph.add_edge(node - 1, node, measurement, np.linalg.inv(edge_covariance))
        self.loops.add_keyframe(edge_covariance, heading, insertion.path_m)
        self._local.append(insertion.pose_local)
        self._points.append(insertion.points)
        self._free.append(insertion.free_ends)
        self._stamps.append(insertion.stamp_ns)
        self._spacing.append(insertion.spacing_rad)
        opts = self.config.loop_closure
        if opts.enabled and node % max(opts.every_keyframes, 1) == 0:
            points = voxel_filter(insertion.points, self.config.scan.voxel_m)
            for closure in self.loops.search(node, points, self.graph.poses, insertion.dense):
                self._add_closure(closure)
        due = len(self.graph) - self._nodes_at_last_optimization >= self.config.optimization.every_keyframes
        if len(self._loop_edges) > self._loops_at_last_optimization and due:
            self.optimize()
        return node

    def _add_closure(self, closure: Closure) -> None:
        edge = self.graph.add_edge(closure.anchor, closure.node, closure.measurement, np.linalg.inv(closure.covariance))
        self._loop_edges.append(edge)
        self.stats.loop_closures += 1

    def add_scan(self, stamp_ns: int, keyframe: int, offset: np.ndarray, mount: np.ndarray) -> None:
        """A scan's pose as ``offset`` from its ``keyframe``, taken by a laser at ``mount``."""
        self._scan_node.append(keyframe)
        self._scan_rel.append(offset)
        self._scan_stamp.append(stamp_ns)
        self.mount = mount

    def scan_keyframes(self) -> tuple[np.ndarray, np.ndarray]:
        """Every scan's keyframe (node) and its pose relative to it (N, 3)."""
        return np.array(self._scan_node, np.int64), np.array(self._scan_rel, np.float64).reshape(-1, 3)

    def latest_scan(self) -> tuple[int, np.ndarray] | None:
        """The latest scan's keyframe and its pose relative to it (None before the first scan)."""
        return (self._scan_node[-1], self._scan_rel[-1]) if self._scan_node else None

    def optimize(self, max_iterations: int = 50) -> None:
        """Optimise the pose graph (robust kernel), drop loop edges that still disagree, move the map frame."""
        if len(self.graph) < 2:
            return
        self._optimize_graph(max_iterations)
        chi2 = self.graph.edge_chi2()
        ij = self.graph.edges[0]
        loops = np.flatnonzero(np.abs(ij[:, 1] - ij[:, 0]) > 1)
        bad = loops[chi2[loops] > CHI2_3DOF_999]
        if len(bad):
            self.graph.remove_edges(bad)
            self.stats.loop_closures -= len(bad)
            self.stats.loop_rejected += len(bad)
            self._optimize_graph(max_iterations)
        self._loop_edges = list(np.flatnonzero(np.abs(self.graph.edges[0][:, 1] - self.graph.edges[0][:, 0]) > 1))
        self._nodes_at_last_optimization = len(self.graph)
        self._loops_at_last_optimization = len(self._loop_edges)
        self.stats.optimizations += 1
        last = len(self._local) - 1
        self.map_from_local = compose(self.graph.poses[last], inverse(self._local[last]))

    def _optimize_graph(self, max_iterations: int) -> None:
        """One robust optimisation of the pose graph, with the constraint source's constraints if it has any."""
        if self.constraints is None or not self.constraints.optimize(self.graph, max_iterations, self.kernel):
            self.graph.optimize(max_iterations=max_iterations, robust_kernel=self.kernel, kernel_width=3.0)

    def finish(self) -> None:
        """End of the run: a final optimisation when loops were added since the last one; then the
        constraint source's own end."""
        if len(self._loop_edges) != self._loops_at_last_optimization or self.stats.optimizations == 0:
            self.optimize(max_iterations=100)
        if self.constraints is not None:
            self.constraints.finish(self)

    # --- output ------------------------------------------------------------------------------

    def trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """Stamps (ns) and optimised map poses (N, 3) of every scan, in arrival order."""
        if not self._scan_stamp:
            return np.zeros(0, np.int64), np.zeros((0, 3))
        nodes = self.graph.poses[np.array(self._scan_node)]
        return np.array(self._scan_stamp, np.int64), compose(nodes, np.array(self._scan_rel))

    def keyframe_stamps(self) -> np.ndarray:
        """Stamps (ns) of the keyframes."""
        return np.array(self._stamps, np.int64)

    def loop_edges(self) -> np.ndarray:
        """Node pairs (L, 2) of the loop-closure edges kept."""
        ij = self.graph.edges[0]
        return ij[np.abs(ij[:, 1] - ij[:, 0]) > 1]

    def map_inputs(self, resolution: float | None = None) -> MapInputs:
        """What the map is made of now (the keyframes' optimised poses, points and free ends, the mount): a
        snapshot another thread may build the map from while this one goes on."""
        return MapInputs(self.graph.poses.copy(), tuple(self._points), tuple(self._free), self.mount.copy(),
                         resolution or self.config.submaps.resolution)

    def build_map(self, resolution: float | None = None, inputs: MapInputs | None = None) -> LogOddsGrid:
        """An occupancy grid of every keyframe scan at its optimised pose (of ``inputs``, else now), free
        wherever the laser only ever saw through (:meth:`LogOddsGrid.clear_seen_through`): a short or
        stationary log's few keyframes carve free space too. Built incrementally (:class:`MapBuilder`)."""
        return self._map.build(inputs or self.map_inputs(resolution))

    def check_map(self) -> MapCheck:
        """The map self-check at the optimised poses (:func:`check_keyframes`)."""
        return check_keyframes(self.config, self.submaps.submaps, self.graph.poses, self._points,
                               np.array(self._spacing), self.mount)

    def keyframe_points(self) -> tuple[list[np.ndarray], list[np.ndarray | None]]:
        """Every keyframe's scan points and no-return ends (robot frame, m; None: none cleared)."""
        return list(self._points), list(self._free)

    def keyframe_spacing(self) -> np.ndarray:
        """Every keyframe's angle between beams (rad)."""
        return np.array(self._spacing)

    def keyframe_endpoints(self) -> list[np.ndarray]:
        """Every keyframe's scan points (N, 2) at its optimised pose, map frame."""
        return [transform_points(pose, points) for pose, points in zip(self.graph.poses, self._points, strict=True)]

    def keyframe_scans(self, first: int, last: int) -> np.ndarray:
        """Optimised map poses of the scans whose keyframes are ``first`` .. ``last`` (inclusive)."""
        _, poses = self.trajectory()
        nodes = np.array(self._scan_node)
        return poses[(nodes >= first) & (nodes <= last)]

    def map_residuals(self, grid: LogOddsGrid) -> np.ndarray:
        """Mean distance (m) of each keyframe's points to ``grid``'s occupied cells at its optimised pose."""
        voxel = self.config.scan.voxel_m
        residuals = [refine_pose(grid, voxel_filter(points, voxel), pose, max_iterations=0).residual_m
                     for pose, points in zip(self.graph.poses, self._points, strict=True)]
        return np.array(residuals)
