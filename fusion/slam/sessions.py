"""Multi-session mapping: the keyframes of several sessions in one pose graph (slam_toolbox's
"continue mapping", Cartographer's frozen trajectories).

A :class:`SessionGraph` holds every keyframe of one or more SLAM sessions: its session, stamp, map
pose, scan as logged and laser mount; the pose-graph edges (odometry, loop closures within a
session, closures across sessions) with their information matrices; each scan's pose relative to
its keyframe (the trajectory); the landmarks. It is made from a finished run (:func:`from_slam`) or
read from a session bundle (:mod:`trundle.tools.jobs.sessions`).

Continuing a map with a new session (:func:`continue_map`):

1. Placement: the new session is mapped on its own first (its own closures, as ``trundle slam``);
   then the global localization's search (:func:`trundle.fusion.localization.grid_localization.global_search`)
   looks for each of its submaps in the old map, from its first one on, until two consecutive submaps
   are found at one placement (within :attr:`SessionOptions.agree_m` / ``agree_rad``), each with a match
   score of at least the localizer's ``good_score``.
2. Cross-session closures: every searched keyframe of the new session, at its placed pose, is matched
   against the old sessions' submaps by the loop closer (:class:`trundle.fusion.slam.loop_closure.LoopCloser`,
   the same search, ICP verification and agreement test as within a session; the chain's uncertainty
   starts from the placement's). A placement no closure confirms is no placement.
3. One optimisation of the joint graph (robust kernel), with every session's landmark sightings as
   constraints (:func:`trundle.fusion.slam.landmark_grid_slam.from_sightings`: a marker seen in two
   sessions ties them as a loop closure does); cross-session closures that still disagree
   are dropped (rejected) and it is optimised again. The old sessions move only through accepted
   cross-session closures (their own edges are at their optimum), or not at all with ``freeze``.

A session that cannot be placed may join as a disconnected part of the map (``allow_new_area``): its
first keyframe is then fixed where it is, beside the old map.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from trundle.fusion.geometry import (
    compose,
    inverse,
    no_return_directions,
    relative,
    scan_to_points,
    transform_points,
    voxel_filter,
    wrap_angle,
)
from trundle.fusion.localization.grid_localization import LocalizerConfig, coarse_map, global_search
from trundle.fusion.mapping.map_check import MapCheck
from trundle.fusion.mapping.occupancy_grid import LogOddsGrid
from trundle.fusion.mapping.submaps import Submap, SubmapStack
from trundle.fusion.matching.scan_matching import samples_walls_densely
from trundle.fusion.optimization.pose_graph import PoseGraph
from trundle.fusion.slam.backend import check_keyframes, keyframe_grid
from trundle.fusion.slam.config import SlamConfig
from trundle.fusion.slam.grid_slam import Slam
from trundle.fusion.slam.landmark_grid_slam import Sighting, applied_sightings, from_sightings
from trundle.fusion.slam.landmark_slam import LandmarkMap
from trundle.fusion.slam.loop_closure import CHI2_3DOF_999, Closure, LoopCloser
from trundle.fusion.slam.stats import SlamStats
from trundle.logs import messages as m


@dataclass
class SessionGraph:
    """Keyframes of one or more sessions in one pose graph (see the module docstring). Per keyframe:
    ``session``, ``stamps`` (ns), map ``poses`` (K, 3), ``scans`` as logged, laser ``mounts`` (K, 3,
    base_link), robot-frame ``points`` and no-return ends ``free`` (derived from the scans); ``edges``:
    node pairs (E, 2), measurements (E, 3) and information matrices (E, 3, 3); per scan: stamp,
    session, keyframe and pose relative to it; ``fixed``: the nodes the optimisation keeps; ``sightings``: the
    landmark sightings, each tied to its keyframe (the joint optimisation's landmark constraints)."""

    session: np.ndarray
    stamps: np.ndarray
    poses: np.ndarray
    scans: list[m.LaserScan]
    mounts: np.ndarray
    points: list[np.ndarray]
    free: list[np.ndarray | None]
    edges: tuple[np.ndarray, np.ndarray, np.ndarray]
    scan_stamps: np.ndarray
    scan_session: np.ndarray
    scan_nodes: np.ndarray
    scan_offsets: np.ndarray
    landmarks: LandmarkMap | None = None
    fixed: set[int] = field(default_factory=lambda: {0})
    submaps: list[Submap] | None = None  # built once by :func:`session_submaps`; they move with their anchors
    sightings: list[Sighting] = field(default_factory=list)  # landmark sightings tied to keyframes (time offset in)

    def __len__(self) -> int:
        return len(self.stamps)

    @property
    def sessions(self) -> int:
        """How many sessions it holds."""
        return int(self.session.max()) + 1 if len(self.session) else 0

    def trajectory(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Stamps (ns), map poses (N, 3) and session of every scan, at the keyframes' poses."""
        return self.scan_stamps, compose(self.poses[self.scan_nodes], self.scan_offsets), self.scan_session

    def cross_edges(self) -> np.ndarray:
        """Indices of the edges between keyframes of different sessions."""
        ij = self.edges[0]
        return np.flatnonzero(self.session[ij[:, 0]] != self.session[ij[:, 1]])


def keyframe_points(scan: m.LaserScan, mount: np.ndarray, config: SlamConfig) -> tuple[np.ndarray, np.ndarray | None]:
    """A keyframe's scan as the local builder inserts it (robot frame, m): its returns within the ``[slam.scan]``
    limits and its no-return ends (None when ``no_return_clear_m`` is 0). No de-skew: the bundle keeps the scan
    as logged, not the motion during it."""
    opts = config.scan
    limits = (max(opts.min_range_m, scan.range_min), min(opts.max_range_m, scan.range_max))
    points = scan_to_points(scan, mount, *limits)
    free = None
    if opts.no_return_clear_m > 0:
        free = mount[:2] + opts.no_return_clear_m * no_return_directions(scan, mount)
    return points, free


def from_slam(slam: Slam, landmarks: LandmarkMap | None = None) -> SessionGraph:
    """One session: a finished grid SLAM run's keyframes, graph and trajectory."""
    points, free = slam.backend.keyframe_points()
    stamps, _ = slam.trajectory()
    nodes, offsets = slam.backend.scan_keyframes()
    count = len(slam.graph)
    constraints = slam.landmark_constraints
    return SessionGraph(np.zeros(count, np.int64), slam.keyframe_stamps(), slam.keyframe_poses(),
                        list(slam.keyframe_scans_taken), np.array(slam.keyframe_mounts).reshape(-1, 3), points, free,
                        slam.graph.edges, stamps, np.zeros(len(stamps), np.int64), nodes, offsets, landmarks,
                        sightings=[] if constraints is None else applied_sightings(constraints))


def session_submaps(graph: SessionGraph, config: SlamConfig) -> list[Submap]:
    """Every session's submaps rebuilt at the keyframes' map poses (each session's keyframes in order, a new
    submap every ``scans_per_submap``, as the local builder makes them); all finished. Their local frame is
    the map frame at the poses they were built at."""
    out: list[Submap] = []
    for session in range(graph.sessions):
        stack = SubmapStack(config.submaps.resolution, config.submaps.scans_per_submap, subcell=True)
        for node in np.flatnonzero(graph.session == session):
            stack.insert(int(node), graph.poses[node], graph.points[node], graph.mounts[node][:2], graph.free[node])
        stack.finish_all()
        for submap in stack.submaps:
            submap.index = len(out)
            out.append(submap)
    graph.submaps = out
    return out


def submap_members(graph: SessionGraph, config: SlamConfig) -> list[list[int]]:
    """The keyframes (nodes) of every submap :func:`session_submaps` makes, without building them: in each
    session a submap starts every ``scans_per_submap`` keyframes and holds twice that many (fewer at the end)."""
    per = config.submaps.scans_per_submap
    out = []
    for session in range(graph.sessions):
        nodes = np.flatnonzero(graph.session == session).tolist()
        out += [nodes[start:start + 2 * per] for start in range(0, len(nodes), per)]
    return out


def build_grid(graph: SessionGraph, config: SlamConfig) -> LogOddsGrid:
    """The occupancy grid of every keyframe of every session at its pose."""
    return keyframe_grid(graph.poses, graph.points, graph.free, graph.mounts, config.submaps.resolution)


def check_graph(graph: SessionGraph, config: SlamConfig) -> MapCheck:
    """The map self-check of every keyframe against every submap of every session but its own two."""
    spacing = np.array([abs(float(s.angle_increment)) for s in graph.scans])
    return check_keyframes(config, session_submaps(graph, config), graph.poses, graph.points, spacing, graph.mounts)


@dataclass(frozen=True)
class Placement:
    """Where a new session lies in the old map: ``transform`` (new map frame -> old map frame), the
    submaps of the new session that agreed on it, their match scores, how far apart their two
    placements were (m, rad), and the covariance (old map frame) of the placement."""

    transform: np.ndarray
    submaps: tuple[int, int]
    scores: tuple[float, float]
    disagreement_m: float
    disagreement_rad: float
    covariance: np.ndarray

    def as_dict(self) -> dict[str, Any]:
        return {"transform": [float(v) for v in self.transform], "submaps": list(self.submaps),
                "scores": [float(s) for s in self.scores], "disagreement_m": self.disagreement_m,
                "disagreement_rad": self.disagreement_rad,
                "sigma": [float(v) for v in np.sqrt(np.diag(self.covariance))]}


def place(old_grid: LogOddsGrid, new: SessionGraph, config: SlamConfig) -> Placement | None:
    """Find the single-session ``new`` in ``old_grid`` (see the module docstring, step 1); None: nowhere."""
    localizer = LocalizerConfig()
    coarse = coarse_map(old_grid, localizer.coarse_resolution_m)
    opts = config.sessions
    previous: tuple[int, np.ndarray, float, np.ndarray] | None = None
    for submap in session_submaps(new, config):
        if submap.scans < config.submaps.scans_per_submap:
            continue  # the last, short ones see too little
        anchor = new.poses[submap.anchor_node]
        cells = transform_points(inverse(submap.anchor_local), submap.grid.occupied_points())
        found = global_search(old_grid, voxel_filter(cells, localizer.hypothesis_voxel_m), coarse=coarse,
                              angular_step_rad=localizer.angular_step_rad, max_candidates=localizer.max_candidates,
                              max_range_m=localizer.max_range_m,
                              match_angular_step_rad=localizer.match_angular_step_rad)
        best = found[0] if found and found[0].score >= localizer.good_score else None
        if best is None:
            previous = None
            continue
        transform = compose(best.pose, inverse(anchor))
        if previous is not None:
            step = relative(previous[1], transform)
            apart_m, apart_rad = float(np.hypot(step[0], step[1])), abs(float(wrap_angle(step[2])))
            if apart_m <= opts.agree_m and apart_rad <= opts.agree_rad:
                return Placement(transform, (previous[0], submap.index), (previous[2], float(best.score)),
                                 apart_m, apart_rad, previous[3] + best.covariance)
        previous = (submap.index, transform, float(best.score), best.covariance)
    return None


def placed(new: SessionGraph, transform: np.ndarray, session: int) -> SessionGraph:
    """``new`` (one session) moved by ``transform`` into another map frame and numbered ``session``."""
    landmarks = new.landmarks
    if landmarks is not None:
        c, s = np.cos(transform[2]), np.sin(transform[2])
        rot = np.array([[c, -s], [s, c]])
        landmarks = LandmarkMap(list(landmarks.ids), transform_points(transform, landmarks.positions),
                                np.einsum("ij,njk,lk->nil", rot, landmarks.covariances, rot),
                                landmarks.sightings.copy(), landmarks.yaw + transform[2])
    return SessionGraph(np.full(len(new), session, np.int64), new.stamps, compose(transform, new.poses), new.scans,
                        new.mounts, new.points, new.free, new.edges, new.scan_stamps,
                        np.full(len(new.scan_stamps), session, np.int64), new.scan_nodes, new.scan_offsets, landmarks,
                        set(new.fixed), new.submaps, new.sightings)


@dataclass
class CrossSessionStats:
    """The cross-session closures: searched keyframes, match attempts, candidates the ICP check refused,
    accepted (kept after the optimisation) and rejected ones (disagreeing with the graph: by the loop
    closer's agreement test or after the optimisation), each as (old node, new node, the new node's pose
    in the old one's frame)."""

    searched: int = 0
    attempts: int = 0
    unverified: int = 0
    accepted: list[tuple[int, int, np.ndarray]] = field(default_factory=list)
    rejected: list[tuple[int, int, np.ndarray]] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        def said(closures: list[tuple[int, int, np.ndarray]]) -> list[dict[str, Any]]:
            return [{"old": a, "new": b, "measurement": [float(v) for v in z]} for a, b, z in closures]
        return {"searched_keyframes": self.searched, "attempts": self.attempts, "unverified": self.unverified,
                "accepted": len(self.accepted), "rejected": len(self.rejected),
                "accepted_closures": said(self.accepted), "rejected_closures": said(self.rejected)}


def cross_closures(old: SessionGraph, new: SessionGraph, placement_covariance: np.ndarray,
                   config: SlamConfig) -> tuple[list[Closure], CrossSessionStats]:
    """Closures of the placed ``new`` session's keyframes (every ``loop_closure.every_keyframes``-th) with the old
    sessions' submaps (see the module docstring, step 2); node numbers of the joint graph (``new`` after ``old``)."""
    stats = SlamStats()
    stack = SubmapStack(config.submaps.resolution, config.submaps.scans_per_submap)
    stack.submaps = session_submaps(old, config)
    closer = LoopCloser(config, stats, stack)
    for _ in range(len(old)):
        closer.add_keyframe(None, 0.0, 0.0)
    ij, _, info = new.edges
    sequential = {int(j): k for k, (i, j) in enumerate(ij) if j == i + 1}
    path = 0.0
    poses = np.concatenate([old.poses, new.poses])
    closures: list[Closure] = []
    out = CrossSessionStats()
    every = max(config.loop_closure.every_keyframes, 1)
    for node in range(len(new)):
        edge = sequential.get(node)
        if edge is None:
            closer.add_keyframe(None, 0.0, path, start_covariance=placement_covariance)
        else:
            path += float(np.hypot(*(new.poses[node, :2] - new.poses[node - 1, :2])))
            closer.add_keyframe(np.linalg.inv(info[edge]), float(new.poses[node - 1, 2]), path)
        if node % every:
            continue
        out.searched += 1
        points = voxel_filter(new.points[node], config.scan.voxel_m)
        dense = samples_walls_densely(new.points[node], config.submaps.resolution)
        closures.extend(closer.search(len(old) + node, points, poses, dense))
    out.attempts, out.unverified = stats.loop_attempts, stats.loop_unverified
    out.rejected = [(c.anchor, c.node, c.measurement) for c in closer.dropped]
    return closures, out


def join(old: SessionGraph, new: SessionGraph) -> SessionGraph:
    """``new``'s keyframes, edges and scans after ``old``'s in one graph (no edge between them yet)."""
    offset = len(old)
    ij, z, info = new.edges
    landmarks = merge_landmarks(old.landmarks, new.landmarks)
    return SessionGraph(np.concatenate([old.session, new.session]), np.concatenate([old.stamps, new.stamps]),
                        np.concatenate([old.poses, new.poses]), old.scans + new.scans,
                        np.concatenate([old.mounts, new.mounts]), old.points + new.points, old.free + new.free,
                        (np.concatenate([old.edges[0], ij + offset]), np.concatenate([old.edges[1], z]),
                         np.concatenate([old.edges[2], info])),
                        np.concatenate([old.scan_stamps, new.scan_stamps]),
                        np.concatenate([old.scan_session, new.scan_session]),
                        np.concatenate([old.scan_nodes, new.scan_nodes + offset]),
                        np.concatenate([old.scan_offsets, new.scan_offsets]), landmarks,
                        set(old.fixed) | {k + offset for k in new.fixed},
                        None if old.submaps is None or new.submaps is None else
                        old.submaps + [dataclasses.replace(s, index=len(old.submaps) + s.index,
                                                           anchor_node=s.anchor_node + offset,
                                                           nodes=[n + offset for n in s.nodes]) for s in new.submaps],
                        old.sightings + [dataclasses.replace(s, node=s.node + offset) for s in new.sightings])


def merge_landmarks(old: LandmarkMap | None, new: LandmarkMap | None) -> LandmarkMap | None:
    """Both sessions' landmarks in one map: a landmark mapped in both is their information-weighted mean."""
    if old is None or new is None:
        return old if new is None else new
    ids = list(old.ids)
    positions, covariances = list(old.positions), list(old.covariances)
    sightings, yaw = list(old.sightings), list(old.yaw)
    for k, name in enumerate(new.ids):
        if name not in ids:
            ids.append(name)
            positions.append(new.positions[k])
            covariances.append(new.covariances[k])
            sightings.append(new.sightings[k])
            yaw.append(new.yaw[k])
            continue
        i = ids.index(name)
        a, b = np.linalg.inv(covariances[i]), np.linalg.inv(new.covariances[k])
        covariances[i] = np.linalg.inv(a + b)
        positions[i] = covariances[i] @ (a @ positions[i] + b @ new.positions[k])
        sightings[i] = sightings[i] + new.sightings[k]
    return LandmarkMap(ids, np.array(positions).reshape(-1, 2), np.array(covariances).reshape(-1, 2, 2),
                       np.array(sightings), np.array(yaw, np.float64))


def optimize(graph: SessionGraph, config: SlamConfig, freeze: bool, stats: CrossSessionStats) -> SessionGraph:
    """The joint graph optimised (robust kernel); cross-session edges that still disagree (chi2 over the
    99.9 % quantile) are dropped into ``stats.rejected`` and it is optimised again. ``freeze``: the old
    sessions' keyframes stay where they are (every session before the last)."""
    pose_graph = PoseGraph()
    for pose in graph.poses:
        pose_graph.add_node(pose)
    ij, z, info = graph.edges
    for (i, j), zz, ii in zip(ij, z, info, strict=True):
        pose_graph.add_edge(int(i), int(j), zz, ii)
    fixed = set(graph.fixed)
    if freeze:
        fixed |= set(np.flatnonzero(graph.session < graph.sessions - 1).tolist())
    pose_graph.fixed = fixed
    kernel = config.optimization.kernel
    constraints = from_sightings(config, graph.sightings) if graph.sightings else None

    def optimized() -> None:
        """The joint graph optimised, with every session's landmark sightings when there are any."""
        if constraints is None or not constraints.optimize(pose_graph, 100, kernel):
            pose_graph.optimize(max_iterations=100, robust_kernel=kernel, kernel_width=3.0)

    optimized()
    last = graph.sessions - 1
    ij, z, _ = pose_graph.edges
    cross = np.flatnonzero((graph.session[ij[:, 0]] != graph.session[ij[:, 1]]) & (graph.session[ij[:, 1]] == last))
    bad = cross[pose_graph.edge_chi2()[cross] > CHI2_3DOF_999]
    if len(bad):
        stats.rejected.extend((int(a), int(b), zz) for (a, b), zz in zip(ij[bad], z[bad], strict=True))
        pose_graph.remove_edges(bad)
        optimized()
    ij, z, _ = pose_graph.edges
    stats.accepted = [(int(a), int(b), zz) for (a, b), zz in zip(ij, z, strict=True)
                      if graph.session[a] != graph.session[b] == last]
    moved = move_landmarks(graph, pose_graph.poses) if constraints is None else constraints.landmarks()
    return SessionGraph(graph.session, graph.stamps, pose_graph.poses, graph.scans, graph.mounts, graph.points,
                        graph.free, pose_graph.edges, graph.scan_stamps, graph.scan_session, graph.scan_nodes,
                        graph.scan_offsets, moved, graph.fixed, graph.submaps, graph.sightings)


def move_landmarks(graph: SessionGraph, poses: np.ndarray) -> LandmarkMap | None:
    """The landmarks carried along with the keyframes: each moved as its nearest keyframe moved."""
    landmarks = graph.landmarks
    if landmarks is None or not len(landmarks.ids):
        return landmarks
    distance = np.hypot(*(landmarks.positions[:, None, :] - graph.poses[None, :, :2]).transpose(2, 0, 1))
    nearest = np.argmin(distance, axis=1)
    shift = compose(poses[nearest], inverse(graph.poses[nearest]))
    positions = np.array([transform_points(s, p[None])[0] for s, p in zip(shift, landmarks.positions, strict=True)])
    return LandmarkMap(list(landmarks.ids), positions.reshape(-1, 2), landmarks.covariances, landmarks.sightings,
                       landmarks.yaw + shift[:, 2])


@dataclass(frozen=True)
class Continued:
    """The joint graph after continuing, where the new session was placed (None: a new area) and its
    first keyframe's pose there (old map frame), and the cross-session closures."""

    graph: SessionGraph
    placement: Placement | None
    first_pose: np.ndarray
    closures: CrossSessionStats


def continue_map(old: SessionGraph, new: SessionGraph, config: SlamConfig, freeze: bool = False,
                 allow_new_area: bool = False) -> Continued | None:
    """``new`` (one session, its own frame) placed in ``old`` and joined with it (see the module docstring);
    None when it cannot be placed and ``allow_new_area`` is off."""
    old_grid = build_grid(old, config)
    placement = place(old_grid, new, config)
    session = old.sessions
    if placement is not None:
        moved = placed(new, placement.transform, session)
        closures, stats = cross_closures(old, moved, placement.covariance, config)
        if closures:
            joined = join(old, moved)
            ij, z, info = joined.edges
            ij = np.concatenate([ij, np.array([[c.anchor, c.node] for c in closures])])
            z = np.concatenate([z, np.array([c.measurement for c in closures])])
            info = np.concatenate([info, np.array([np.linalg.inv(c.covariance) for c in closures])])
            joined.edges = (ij, z, info)
            joined.fixed = set(old.fixed)
            result = optimize(joined, config, freeze, stats)
            if stats.accepted:
                return Continued(result, placement, result.poses[len(old)], stats)
    if not allow_new_area:
        return None
    beside = beside_transform(old_grid, new, config)
    joined = join(old, placed(new, beside, session))
    return Continued(joined, None, joined.poses[len(old)], CrossSessionStats())


def beside_transform(old_grid: LogOddsGrid, new: SessionGraph, config: SlamConfig) -> np.ndarray:
    """A transform that puts ``new``'s keyframes to the right of the old map (positive x), a gap of
    ``sessions.new_area_gap_m`` apart: a disconnected part, drawn beside the old one."""
    lo, hi = old_grid.origin, old_grid.origin + np.array(old_grid.shape[::-1]) * old_grid.resolution
    points = np.concatenate([transform_points(p, q) for p, q in zip(new.poses, new.points, strict=True)]
                            + [new.poses[:, :2]])
    new_lo = points.min(axis=0)
    shift_x = hi[0] + config.sessions.new_area_gap_m - new_lo[0]
    shift_y = lo[1] - new_lo[1]
    return np.array([shift_x, shift_y, 0.0])
