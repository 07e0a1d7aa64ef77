"""Submaps: small occupancy grids built from a run of consecutive keyframe scans.

As in Cartographer (Hess et al. 2016), two submaps are active at a time and every keyframe scan
goes into both; scans are matched against the older, fuller one. A submap is finished once it
holds ``2 * scans_per_submap`` scans and then never changes again, so it can be matched against
for loop closure and moved as a rigid whole when the pose graph is optimised. A submap's grid
is in the frame in which the scans were tracked (the "local" frame); the pose of that frame in
the map follows from the optimised pose of the submap's anchor keyframe.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from trundle.fusion.geometry import compose, inverse, transform_points
from trundle.fusion.mapping.occupancy_grid import LogOddsGrid, TracedRays, trace_rays


@dataclass
class Submap:
    """A grid in the local frame plus the keyframes (graph nodes) that built it."""

    index: int
    anchor_node: int
    anchor_local: np.ndarray
    grid: LogOddsGrid
    nodes: list[int] = field(default_factory=list)
    positions: list[np.ndarray] = field(default_factory=list)
    finished: bool = False
    # what loop closure asks of every finished submap for every keyframe: kept, not computed again each time
    _centre: np.ndarray | None = field(default=None, init=False, repr=False, compare=False)
    _anchor_inverse: np.ndarray | None = field(default=None, init=False, repr=False, compare=False)

    @property
    def scans(self) -> int:
        return len(self.nodes)

    def insert(self, node: int, pose_local: np.ndarray, rays: TracedRays) -> None:
        """Add a keyframe (graph node) at ``pose_local`` with its scan's rays, traced in the local frame."""
        self.grid.insert_traced(rays)
        self.nodes.append(node)
        self.positions.append(np.asarray(pose_local[:2], dtype=np.float64).copy())
        self._centre = None

    def centre(self) -> np.ndarray:
        """Mean position (local frame) of the keyframes inserted."""
        if self._centre is None:
            self._centre = np.mean(self.positions, axis=0)
        return self._centre.copy()

    def local_to_map(self, anchor_map_pose: np.ndarray) -> np.ndarray:
        """The pose of this submap's (local) frame in the map, given its anchor's optimised map pose."""
        if self._anchor_inverse is None:
            self._anchor_inverse = inverse(self.anchor_local)
        return compose(anchor_map_pose, self._anchor_inverse)


class SubmapStack:
    """Every submap built so far; the last one or two are active.

    ``resolution`` m/cell of each grid; ``scans_per_submap`` keyframes before a new submap starts;
    ``grid_options`` go to each :class:`LogOddsGrid` (inverse sensor model, clamps).
    """

    def __init__(self, resolution: float = 0.05, scans_per_submap: int = 30, **grid_options: Any) -> None:
        if scans_per_submap < 1:
            raise ValueError("scans_per_submap must be at least 1")
        self.resolution = resolution
        self.scans_per_submap = int(scans_per_submap)
        self.grid_options = grid_options
        self.submaps: list[Submap] = []

    @property
    def active(self) -> list[Submap]:
        return [s for s in self.submaps[-2:] if not s.finished]

    @property
    def finished(self) -> list[Submap]:
        return [s for s in self.submaps if s.finished]

    def matching_submap(self) -> Submap | None:
        """The submap to track against: the oldest active one, if it holds any scan."""
        active = [s for s in self.active if s.scans]
        return active[0] if active else None

    def insert(self, node: int, pose_local: np.ndarray, points_robot: np.ndarray, sensor_robot: np.ndarray,
               free_ends_robot: np.ndarray | None = None) -> list[Submap]:
        """Insert a keyframe into the active submaps (starting one when due); returns submaps just finished."""
        active = self.active
        if not active or active[-1].scans >= self.scans_per_submap:
            self.submaps.append(Submap(len(self.submaps), node, np.asarray(pose_local, np.float64).copy(),
                                       LogOddsGrid(self.resolution, **self.grid_options)))
        origin = transform_points(pose_local, np.asarray(sensor_robot, dtype=np.float64).reshape(1, 2))[0]
        free = None if free_ends_robot is None else transform_points(pose_local, free_ends_robot)
        rays = trace_rays(
            self.submaps[-1].grid.origin, self.resolution, origin, transform_points(pose_local, points_robot), free
        )
        done = []
        for submap in self.active:
            submap.insert(node, pose_local, rays)
            if submap.scans >= 2 * self.scans_per_submap:
                submap.finished = True
                done.append(submap)
        return done

    def finish_all(self) -> None:
        """Mark every submap finished (end of a run)."""
        for submap in self.submaps:
            submap.finished = True
