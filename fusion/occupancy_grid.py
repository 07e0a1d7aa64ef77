"""A log-odds occupancy grid that grows as needed, with vectorised ray updates and match fields.

Cell ``[row, col]`` covers ``origin + (col, row) * resolution`` to one cell further (row 0 at the
bottom, as in nav_msgs/OccupancyGrid). Each inserted scan adds ``l_hit`` to the cells holding a
return and ``l_miss`` to every other cell its rays cross (once per scan, however many rays cross
it), clamped to ``[l_min, l_max]``. For matching the grid offers a distance field (metres to the
nearest occupied cell) and a likelihood field ``exp(-d^2 / (2 sigma^2))``, cached until the next
update.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, TypeVar

import cv2
import numpy as np

from trundle.logs.errors import UserError
from trundle.logs.messages import OccupancyGrid

T = TypeVar("T")
MAX_CELLS = 1 << 27  # 134 M cells (670 MB of log-odds and flags): 580 m square at 5 cm; beyond it, a mistake


def log_odds(probability: float) -> float:
    """``log(p / (1 - p))``."""
    return math.log(probability / (1.0 - probability))


def ray_cells(start: np.ndarray, ends: np.ndarray) -> np.ndarray:
    """Cells ``(row, col)`` crossed by rays from ``start`` (2,) to each of ``ends`` (N, 2), end cells excluded.

    Coordinates are in cells (x = column, y = row; cell k spans [k, k+1)). Each ray is sampled at
    ``ceil(max(|dx|, |dy|))`` equal steps (a DDA line, like Bresenham's), all rays at once.
    """
    start = np.asarray(start, dtype=np.float64)
    ends = np.asarray(ends, dtype=np.float64).reshape(-1, 2)
    delta = ends - start
    steps = np.ceil(np.abs(delta).max(axis=1)).astype(np.int64) if len(ends) else np.zeros(0, np.int64)
    total = int(steps.sum())
    if total == 0:
        return np.zeros((0, 2), np.int64)
    ray = np.repeat(np.arange(len(ends)), steps)
    k = np.arange(total) - np.repeat(np.cumsum(steps) - steps, steps)
    t = k / steps[ray]
    xy = np.floor(start + t[:, None] * delta[ray]).astype(np.int64)
    end_cells = np.floor(ends).astype(np.int64)[ray]
    keep = np.any(xy != end_cells, axis=1)
    return xy[keep][:, ::-1]


@dataclass(frozen=True)
class WallLines:
    """Walls of a grid as its returns describe them: ``nearest`` (H, W) the index of each cell's nearest
    occupied cell (-1: none), and per occupied cell the ``mean`` (K, 2, metres, grid frame) of its
    returns, the ``normal`` (K, 2) of the line through its neighbourhood's returns and whether they
    lie on one (``is_line``; otherwise the returns are matched as a point)."""

    nearest: np.ndarray
    mean: np.ndarray
    normal: np.ndarray
    is_line: np.ndarray


class LogOddsGrid:
    """Occupancy in log-odds over a growing 2-D array.

    ``resolution`` m/cell; ``p_hit`` / ``p_miss`` the inverse sensor model; ``l_min``/``l_max``
    clamp the log-odds so the map can still change; ``grow_cells`` is the margin added when a scan
    falls outside (growth is amortised). With ``subcell`` each cell also keeps the moments of the
    returns that fell in it, so matching can use the walls those returns describe rather than the
    cell lattice (see :meth:`wall_lines`).
    """

    def __init__(self, resolution: float = 0.05, *, p_hit: float = 0.7, p_miss: float = 0.4,
                 l_min: float = -2.0, l_max: float = 3.5, origin_xy: tuple[float, float] = (0.0, 0.0),
                 grow_cells: int = 64, subcell: bool = False) -> None:
        if resolution <= 0:
            raise ValueError("resolution must be positive")
        self.resolution = float(resolution)
        self.l_hit, self.l_miss = log_odds(p_hit), log_odds(p_miss)
        self.l_min, self.l_max = float(l_min), float(l_max)
        self.grow_cells = int(grow_cells)
        self.origin = np.array(origin_xy, dtype=np.float64)
        self.log_odds = np.zeros((0, 0), np.float32)
        self.observed = np.zeros((0, 0), bool)
        # per cell: returns, sum of their x and y offsets in the cell, and of x^2, xy, y^2 (cell units)
        self.moments: np.ndarray | None = np.zeros((6, 0, 0), np.float32) if subcell else None
        self.version = 0
        self._cache: dict[tuple, object] = {}

    @property
    def shape(self) -> tuple[int, int]:
        return self.log_odds.shape

    def world_to_cell(self, xy: np.ndarray) -> np.ndarray:
        """Continuous cell coordinates (x = column, y = row) of points (N, 2) in metres."""
        return (np.asarray(xy, dtype=np.float64) - self.origin) / self.resolution

    def cell_centers(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """World coordinates (N, 2) of the centres of cells ``(rows, cols)``."""
        return self.origin + (np.stack([cols, rows], axis=-1) + 0.5) * self.resolution

    def ensure_contains(self, xy_min: np.ndarray, xy_max: np.ndarray) -> None:
        """Grow the array (keeping the cell lattice) so the box ``xy_min``..``xy_max`` lies inside."""
        lo = np.floor(self.world_to_cell(xy_min)).astype(np.int64)
        hi = np.floor(self.world_to_cell(xy_max)).astype(np.int64)
        height, width = self.shape
        if height and lo[0] >= 0 and lo[1] >= 0 and hi[0] < width and hi[1] < height:
            return
        if not height:
            pad_lo = -lo + self.grow_cells
            new_w, new_h = hi - lo + 1 + 2 * self.grow_cells
        else:
            pad_lo = np.maximum(-lo, 0) + np.where(lo < 0, self.grow_cells, 0)
            pad_hi = np.maximum(hi - (width - 1, height - 1), 0) + np.where(hi >= (width, height), self.grow_cells, 0)
            new_w, new_h = width + pad_lo[0] + pad_hi[0], height + pad_lo[1] + pad_hi[1]
        if int(new_h) * int(new_w) > MAX_CELLS:
            raise UserError(f"the map would grow to {int(new_w)} x {int(new_h)} cells at {self.resolution:g} m per "
                            f"cell ({int(new_w) * self.resolution:.0f} x {int(new_h) * self.resolution:.0f} m), over "
                            f"the {MAX_CELLS:,} cell limit: use a coarser [slam] resolution")
        grown = np.zeros((int(new_h), int(new_w)), np.float32)
        seen = np.zeros((int(new_h), int(new_w)), bool)
        if height:
            grown[pad_lo[1]:pad_lo[1] + height, pad_lo[0]:pad_lo[0] + width] = self.log_odds
            seen[pad_lo[1]:pad_lo[1] + height, pad_lo[0]:pad_lo[0] + width] = self.observed
        if self.moments is not None:
            moments = np.zeros((6, int(new_h), int(new_w)), np.float32)
            if height:
                moments[:, pad_lo[1]:pad_lo[1] + height, pad_lo[0]:pad_lo[0] + width] = self.moments
            self.moments = moments
        self.log_odds, self.observed = grown, seen
        self.origin = self.origin - pad_lo * self.resolution
        self._changed()

    def insert_rays(self, sensor_xy: np.ndarray, hits_xy: np.ndarray, free_ends_xy: np.ndarray | None = None) -> None:
        """Update with rays from ``sensor_xy`` (2,): returns at ``hits_xy`` (N, 2), free space to ``free_ends_xy``.

        Coordinates in metres in the grid's frame. ``free_ends_xy`` (M, 2) are the ends of rays that
        saw nothing (cleared, but no hit marked), e.g. no-return beams cut at a chosen distance.
        """
        sensor_xy = np.asarray(sensor_xy, dtype=np.float64).reshape(2)
        hits_xy = np.asarray(hits_xy, dtype=np.float64).reshape(-1, 2)
        free_ends_xy = np.zeros((0, 2)) if free_ends_xy is None else np.asarray(free_ends_xy, np.float64).reshape(-1, 2)
        everything = np.vstack([sensor_xy[None], hits_xy, free_ends_xy])
        self.ensure_contains(everything.min(axis=0), everything.max(axis=0))
        width = self.shape[1]
        start = self.world_to_cell(sensor_xy)
        hit_coords = self.world_to_cell(hits_xy)
        hit_cells = np.floor(hit_coords).astype(np.int64)
        if self.moments is not None and len(hit_cells):
            u, v = (hit_coords - hit_cells).T
            flat_hits = hit_cells[:, 1] * width + hit_cells[:, 0]
            for k, values in enumerate((np.ones_like(u), u, v, u * u, u * v, v * v)):
                np.add.at(self.moments[k].reshape(-1), flat_hits, values.astype(np.float32))
        crossed = ray_cells(start, np.vstack([self.world_to_cell(hits_xy), self.world_to_cell(free_ends_xy)]))
        # Each cell once per scan, hits winning over misses. A mark per cell beats sorting for grids
        # up to a few dozen times the number of cells the rays touch; beyond, sort.
        crossed_flat = crossed[:, 0] * width + crossed[:, 1]
        hit_flat = hit_cells[:, 1] * width + hit_cells[:, 0]
        if self.log_odds.size <= 32 * (len(crossed_flat) + len(hit_flat)):
            mark = np.zeros(self.log_odds.size, np.int8)
            mark[crossed_flat] = 1
            mark[hit_flat] = 2
            touched = np.flatnonzero(mark)
            kind = mark[touched]
            free_flat, hit_flat = touched[kind == 1], touched[kind == 2]
        else:
            hit_flat = np.unique(hit_flat)
            free_flat = np.setdiff1d(np.unique(crossed_flat), hit_flat, assume_unique=True)
        flat = self.log_odds.reshape(-1)
        flat[free_flat] = np.maximum(flat[free_flat] + self.l_miss, self.l_min)
        flat[hit_flat] = np.minimum(flat[hit_flat] + self.l_hit, self.l_max)
        seen = self.observed.reshape(-1)
        seen[free_flat] = True
        seen[hit_flat] = True
        self._changed()

    def probability(self) -> np.ndarray:
        """Occupancy probability of every cell (0.5 where never observed)."""
        return 1.0 / (1.0 + np.exp(-self.log_odds))

    def occupied(self, threshold: float = 0.0) -> np.ndarray:
        """Boolean mask of cells whose log-odds exceed ``threshold`` (0 = more likely occupied than free)."""
        return self.log_odds > threshold

    def occupied_points(self, threshold: float = 0.0) -> np.ndarray:
        """Centres (N, 2) of the occupied cells, in metres."""
        rows, cols = np.nonzero(self.occupied(threshold))
        return self.cell_centers(rows, cols)

    def cached(self, key: tuple, factory: Callable[[], T]) -> T:
        """``factory()`` computed once per grid version (fields and pyramids for matching)."""
        if key not in self._cache:
            self._cache[key] = factory()
        return self._cache[key]  # type: ignore[return-value]

    def _distance_cells(self) -> np.ndarray:
        """Exact Euclidean distance (cells) from each cell centre to the nearest occupied one (inf if none)."""
        def compute() -> np.ndarray:
            free = np.where(self.occupied(), 0, 255).astype(np.uint8)
            if not free.size or free.all():
                return np.full(self.shape, np.inf, np.float32)
            return cv2.distanceTransform(free, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
        return self.cached(("distance_cells",), compute)

    def distance_field(self, max_distance_m: float = 1.0) -> np.ndarray:
        """Metres from each cell centre to the nearest occupied cell centre, capped at ``max_distance_m``."""
        return self.cached(("distance", float(max_distance_m)),
                           lambda: np.minimum(self._distance_cells() * np.float32(self.resolution),
                                              np.float32(max_distance_m)))

    def wall_lines(self, min_flatness: float = 0.8) -> WallLines:
        """The walls the returns describe, for point-to-line matching (a grid built with ``subcell``).

        Occupied cells put every wall on the cell lattice, up to half a cell from where it is, and a
        match inherits that error, the same each time the wall is seen. The returns themselves know
        better: each occupied cell gets the mean of its returns and, where the returns of its 3 x 3
        occupied neighbourhood lie on a line (``flatness``, as in :class:`trundle.fusion.icp.LineReference`),
        that line's normal; and each cell the index of its nearest occupied cell.
        """
        return self.cached(("wall_lines", float(min_flatness)), lambda: self._wall_lines(min_flatness))

    def _wall_lines(self, min_flatness: float) -> WallLines:
        if self.moments is None:
            raise ValueError("wall_lines needs a grid built with subcell=True")
        occupied = self.occupied() & (self.moments[0] > 0)
        height, width = self.shape
        if not occupied.any():
            return WallLines(np.full(self.shape, -1, np.int32), np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, bool))
        free = np.where(occupied, 0, 255).astype(np.uint8)
        _, labels = cv2.distanceTransformWithLabels(free, cv2.DIST_L2, cv2.DIST_MASK_PRECISE,
                                                    labelType=cv2.DIST_LABEL_PIXEL)
        rows, cols = np.nonzero(occupied)
        m = self.moments[:, rows, cols].astype(np.float64)
        mean = np.stack([cols + m[1] / m[0], rows + m[2] / m[0]], axis=1)  # returns' mean, absolute cell units
        sums = np.zeros((len(rows), 6))  # moments of the occupied neighbourhood about the cell's mean
        for dr in (-1, 0, 1):
            for dc in (-1, 0, 1):
                r, c = rows + dr, cols + dc
                ok = (r >= 0) & (c >= 0) & (r < height) & (c < width)
                ok[ok] &= occupied[r[ok], c[ok]]
                n = self.moments[:, r[ok], c[ok]].astype(np.float64)
                ox, oy = c[ok] - mean[ok, 0], r[ok] - mean[ok, 1]
                sums[ok] += np.stack([n[0], n[1] + ox * n[0], n[2] + oy * n[0], n[3] + 2 * ox * n[1] + ox * ox * n[0],
                                      n[4] + ox * n[2] + oy * n[1] + ox * oy * n[0],
                                      n[5] + 2 * oy * n[2] + oy * oy * n[0]], axis=1)
        mx, my = sums[:, 1] / sums[:, 0], sums[:, 2] / sums[:, 0]
        sxx, sxy, syy = (sums[:, 3] / sums[:, 0] - mx * mx, sums[:, 4] / sums[:, 0] - mx * my,
                         sums[:, 5] / sums[:, 0] - my * my)
        angle = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)  # direction of the largest spread: the wall
        spread = np.sqrt(((sxx - syy) / 2.0) ** 2 + sxy ** 2)
        centre = (sxx + syy) / 2.0
        flat = 1.0 - (centre - spread) / np.maximum(centre + spread, 1e-12)
        index = np.zeros(int(labels.max()) + 1, np.int32)
        index[labels[rows, cols]] = np.arange(len(rows), dtype=np.int32)
        return WallLines(index[labels], self.origin + mean * self.resolution,
                         np.stack([-np.sin(angle), np.cos(angle)], axis=1), (flat >= min_flatness) & (sums[:, 0] >= 3))

    def likelihood_field(self, sigma_m: float) -> np.ndarray:
        """``exp(-d^2 / (2 sigma^2))`` of the distance to the nearest occupied cell, 0 beyond 4 sigma."""
        def compute() -> np.ndarray:
            cells = self._distance_cells()
            scale = np.float32(self.resolution / sigma_m)
            field = np.exp(np.float32(-0.5) * np.square(np.minimum(cells, np.float32(4.0 / scale)) * scale))
            field[cells * scale >= 4.0] = 0.0
            return field.astype(np.float32, copy=False)
        return self.cached(("likelihood", float(sigma_m)), compute)

    def to_message(self, stamp_ns: int, frame_id: str = "map") -> OccupancyGrid:
        """The grid as nav_msgs/OccupancyGrid: percent occupancy, -1 where never observed."""
        data = np.rint(100.0 * self.probability()).astype(np.int8)
        data[~self.observed] = -1
        return OccupancyGrid(stamp_ns, frame_id, self.resolution, float(self.origin[0]), float(self.origin[1]), 0.0, data)

    def _changed(self) -> None:
        self.version += 1
        self._cache.clear()
