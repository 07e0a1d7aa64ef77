"""A log-odds occupancy grid that grows as needed, with compiled ray updates (ray_casting.py) and match fields.

Cell ``[row, col]`` covers ``origin + (col, row) * resolution`` to one cell further (row 0 at the
bottom, as in nav_msgs/OccupancyGrid). Each inserted scan adds ``l_hit`` to the cells holding a
return and ``l_miss`` to every other cell its rays cross (once per scan, however many rays cross
it), clamped to ``[l_min, l_max]``. A map (not a submap) also marks the cells any return fell in, so
the cells the laser only ever saw through can be made certainly free (:meth:`LogOddsGrid.clear_seen_through`):
a lone keyframe's miss (``p_miss`` 40 %) is weak evidence, too weak for a map's free threshold (25 %),
which only the cells of three keyframes' rays would reach. For matching the grid offers a distance field (metres to the
nearest occupied cell) and a likelihood field ``exp(-d^2 / (2 sigma^2))``, cached until the next
update.
"""

from __future__ import annotations

import copy
import functools
import math
import weakref
from collections.abc import Callable
from dataclasses import dataclass
from typing import TypeVar

import cv2
import numpy as np

from trundle.fusion.mapping import ray_casting
from trundle.fusion.mapping.nearest_cells import (
    all_squared_nearest,
    occupied_cells,
    squared_distances,
    stamped_field,
)
from trundle.fusion.mapping.wall_moments import line_terms
from trundle.logs.errors import UserError
from trundle.logs.messages import OccupancyGrid

T = TypeVar("T")
MAX_CELLS = 1 << 27  # 134 M cells (670 MB of log-odds and flags): 580 m square at 5 cm; beyond it, a mistake
WINDOW_SLACK_CELLS = 10   # a match-field window grows by this much more than asked (the next scans move a little)
_NO_SLOTS, _NO_ROWS = np.zeros((0, 0), np.int32), np.zeros((0, 6), np.float32)   # insert_scan's "no moments"
_NO_FREE_ENDS = np.zeros((0, 2))


def log_odds(probability: float) -> float:
    """``log(p / (1 - p))``."""
    return math.log(probability / (1.0 - probability))


@dataclass(frozen=True)
class TracedRays:
    """Rays traced on the cell lattice whose cell (0, 0) starts at ``origin`` (m): the cells crossed
    and the cells of the returns as (row, col), the returns' offsets in their cells (u, v in [0, 1))
    and the bounding box (m) of sensor, returns and free ends."""

    origin: np.ndarray
    crossed: np.ndarray
    hits: np.ndarray
    offsets: np.ndarray
    xy_min: np.ndarray
    xy_max: np.ndarray


def trace_rays(origin: np.ndarray, resolution: float, sensor_xy: np.ndarray, hits_xy: np.ndarray,
               free_ends_xy: np.ndarray | None = None) -> TracedRays:
    """Rays from ``sensor_xy`` to returns ``hits_xy`` (N, 2) and to ``free_ends_xy`` (M, 2) (metres) on
    the lattice of ``resolution`` m cells whose cell (0, 0) starts at ``origin``."""
    origin = np.asarray(origin, np.float64).reshape(2).copy()
    crossed, hits, offsets, xy_min, xy_max = ray_casting.trace(
        origin, float(resolution), np.ascontiguousarray(sensor_xy, dtype=np.float64).reshape(2),
        np.ascontiguousarray(hits_xy, dtype=np.float64).reshape(-1, 2), _free_ends(free_ends_xy))
    return TracedRays(origin, crossed, hits, offsets, xy_min, xy_max)


def _corner_cells(x0: float, y0: float, x1: float, y1: float, origin_x: float, origin_y: float, resolution: float
                  ) -> tuple[int, int, int, int]:
    """The cells (column, row) of the corners (``x0``, ``y0``) and (``x1``, ``y1``) (m) on the lattice of
    ``resolution`` m cells whose cell (0, 0) starts at (``origin_x``, ``origin_y``):
    :meth:`LogOddsGrid.world_to_cell`'s arithmetic and its floor, on Python floats (numpy's on two-element arrays
    took 14 us a new grid)."""
    return (math.floor((x0 - origin_x) / resolution), math.floor((y0 - origin_y) / resolution),
            math.floor((x1 - origin_x) / resolution), math.floor((y1 - origin_y) / resolution))


def _free_ends(free_ends_xy: np.ndarray | None) -> np.ndarray:
    """Free ends (M, 2) as the tracing kernels take them (float64, contiguous; none: (0, 2))."""
    return _NO_FREE_ENDS if free_ends_xy is None else np.ascontiguousarray(free_ends_xy, np.float64).reshape(-1, 2)


@dataclass(frozen=True)
class FieldWindow:
    """Match fields over the cells ``[row0, row0 + h) x [col0, col0 + w)`` of a grid: the likelihood;
    the distance (m) to the nearest occupied cell, capped, which a cell's ``squared`` distance (cells^2,
    -1 until a match first reads it, in the narrowest integer that holds ``radius^2 + 1``; see
    :meth:`distance`) looks up in ``distances`` (none within ``radius`` cells: the last); the occupied cells
    around the window from the grid's (``occupied_row0``, ``occupied_col0``), as an index (the walls'
    nearest cells are found in it) and as each row's columns
    (``occupied_cols[occupied_starts[i]:occupied_starts[i + 1]]``: the distances are found there; see
    :func:`~trundle.fusion.mapping.nearest_cells.occupied_cells`); and the walls (None without them)."""

    row0: int
    col0: int
    likelihood: np.ndarray
    squared: np.ndarray
    distances: np.ndarray
    radius: int
    occupied: np.ndarray
    occupied_starts: np.ndarray
    occupied_cols: np.ndarray
    occupied_row0: int
    occupied_col0: int
    lines: WallLines | None

    def distance(self) -> np.ndarray:
        """The distance field over the whole window (m, float32), every cell's found."""
        all_squared_nearest(self.squared, self.occupied_starts, self.occupied_cols, self.row0 - self.occupied_row0,
                            self.col0 - self.occupied_col0, self.radius)
        return self.distances[self.squared]


class MatchFields:
    """The fields a scan match reads, computed over a window where its points fall rather than over
    the whole grid (a scan covers about a fifth of a submap's cells, measured on fr079): the
    distance (m) to the nearest occupied cell capped at ``max_distance_m``; the likelihood
    ``exp(-d^2 / (2 sigma^2))``, 0 beyond 4 sigma; and with ``lines`` the walls the returns describe
    (:meth:`LogOddsGrid.line_data`) of the occupied cells around it, which a cell reads at its nearest
    occupied cell. Every value in the window is exact: each occupied cell of the window grown by the
    margin stamps its likelihood into it (:func:`~trundle.fusion.mapping.nearest_cells.stamped_field`;
    the search reads every cell a lattice pose can reach), while a cell's distance and nearest wall cell
    are found where the refinement reads them (a few hundred cells;
    :func:`~trundle.fusion.mapping.nearest_cells.squared_nearest`, the stamp's value, and
    :func:`~trundle.fusion.mapping.nearest_cells.chamfer_nearest`, OpenCV's labelled transform's over the
    grown window). A request outside the window grows it (by ``WINDOW_SLACK_CELLS`` more, for the next
    scans and the match's steps)."""

    def __init__(
        self, grid: LogOddsGrid, max_distance_m: float, sigma_m: float, lines: bool, min_flatness: float
    ) -> None:
        # weakly: the grid caches its fields, and a reference both ways would keep a dropped grid's arrays
        # (megabytes) until Python's cyclic collector ran, and the next grid paged in fresh memory
        self._grid = weakref.ref(grid)
        self.max_distance_m = float(max_distance_m)
        self.sigma_m = float(sigma_m)
        self.lines = lines
        self.min_flatness = min_flatness
        # the cells within which the fields differ from their value far from any wall: distance capped, likelihood 0
        self.radius = int(math.ceil(max(self.max_distance_m, 4.0 * self.sigma_m) / grid.resolution))
        self.likelihood_radius = int(math.ceil(4.0 * self.sigma_m / grid.resolution))
        # a window's squared distances (0 to radius^2 + 1, -1 not found yet) in the fewest bytes that hold them:
        # the window is filled with -1 at every new window, a fill that cost 15 us a match as int32
        largest = self.radius * self.radius + 1
        self._squared_type = np.int8 if largest <= 127 else np.int16 if largest <= 32767 else np.int32
        self.margin = self.radius + 2   # the occupied cells gathered around a window: the labels' and the walls'
        self.distances, self._likelihoods = _field_tables(grid.resolution, self.max_distance_m, self.sigma_m,
                                                          self.radius, self.likelihood_radius)
        self._window: FieldWindow | None = None
        # the cells a window may hold (rows [r0, r1), cols [c0, c1)): beyond the margin of the rays' box every
        # field has its value far from any wall, and a read off the window gets that value (a grid's margin
        # for growth, 3.2 m of unknown cells each side by default, is not computed)
        self.extent = grid.swept_extent(self.margin)
        r0, r1, c0, c1 = self.extent
        self._bounds = (r1, r0, c1, c0)   # rows [r0, r1), cols [c0, c1) of the window: none yet

    @property
    def grid(self) -> LogOddsGrid:
        """The grid these fields are of."""
        grid = self._grid()
        if grid is None:
            raise ReferenceError("the grid of these match fields is gone")
        return grid

    @property
    def window(self) -> FieldWindow | None:
        """The window computed so far (None before the first request)."""
        return self._window

    def around(self, cols: np.ndarray, rows: np.ndarray) -> FieldWindow:
        """The fields over a window holding the cells at continuous cell coordinates ``cols``, ``rows``
        (x, y: column and row) and the cells next to them, within :attr:`extent`."""
        if not len(cols):
            return self._window or self._compute(0, 0, 0, 0)
        return self.around_box(float(cols.min()), float(cols.max()), float(rows.min()), float(rows.max()))

    def around_box(self, col_min: float, col_max: float, row_min: float, row_max: float) -> FieldWindow:
        """The fields over a window holding the box ``[col_min, col_max] x [row_min, row_max]`` (continuous
        cell coordinates) and the cells next to it. On floats: numpy's reductions and floors cost a tenth of
        a match (a search and a refinement ask two to four times)."""
        top, bottom, left, right = self.extent
        c_lo, c_hi = math.floor(col_min) - 1, math.floor(col_max) + 2
        r_lo, r_hi = math.floor(row_min) - 1, math.floor(row_max) + 2
        r_lo, c_lo, r_hi, c_hi = max(r_lo, top), max(c_lo, left), min(r_hi, bottom), min(c_hi, right)
        r0, r1, c0, c1 = self._bounds
        if self._window is not None and r_lo >= r0 and c_lo >= c0 and r_hi <= r1 and c_hi <= c1:
            return self._window
        slack = WINDOW_SLACK_CELLS
        return self._compute(max(min(r0, r_lo - slack), top), min(max(r1, r_hi + slack), bottom),
                             max(min(c0, c_lo - slack), left), min(max(c1, c_hi + slack), right))

    def _compute(self, r0: int, r1: int, c0: int, c1: int) -> FieldWindow:
        grid, margin = self.grid, self.margin
        height, width = grid.shape
        pr0, pr1, pc0, pc1 = max(r0 - margin, 0), min(r1 + margin, height), max(c0 - margin, 0), min(c1 + margin, width)
        rows, cols, occupied, starts = occupied_cells(grid.log_odds, pr0, pr1, pc0, pc1)
        shape = (max(r1 - r0, 0), max(c1 - c0, 0))
        # the likelihood is exact to its radius and zero from there; a distance is found where it is read
        likelihood = stamped_field(rows, cols, r0 - pr0, c0 - pc0, shape[0], shape[1], self.likelihood_radius,
                                   self._likelihoods)
        lines = None
        if self.lines:
            lines = WallLines(np.full(shape, -2, np.int32), *grid.line_data(rows + pr0, cols + pc0, self.min_flatness))
        self._bounds = (r0, r1, c0, c1)
        squared = np.full(shape, -1, self._squared_type)
        self._window = FieldWindow(r0, c0, likelihood, squared, self.distances, self.radius, occupied, starts, cols,
                                   pr0, pc0, lines)
        return self._window


@functools.lru_cache(maxsize=16)
def _field_tables(resolution: float, max_distance_m: float, sigma_m: float, radius: int, likelihood_radius: int
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The match fields' values per squared distance (cells), read-only and made once per setting (a grid
    makes new fields at every update): the capped distance (m) to ``radius`` and the likelihood to
    ``likelihood_radius``, as :func:`~trundle.fusion.mapping.nearest_cells.stamped_field` takes it."""
    distances = np.minimum(squared_distances(radius) * np.float32(resolution), np.float32(max_distance_m))
    likelihoods = _likelihood(squared_distances(likelihood_radius), resolution, sigma_m)
    distances.flags.writeable = likelihoods.flags.writeable = False
    return distances, likelihoods


def _likelihood(cells: np.ndarray, resolution: float, sigma_m: float) -> np.ndarray:
    """``exp(-d^2 / (2 sigma^2))`` of distances ``cells`` (in cells), 0 beyond 4 sigma."""
    scale = np.float32(resolution / sigma_m)
    field = np.exp(np.float32(-0.5) * np.square(np.minimum(cells, np.float32(4.0 / scale)) * scale))
    field[cells * scale >= 4.0] = 0.0
    return field.astype(np.float32, copy=False)


@dataclass(frozen=True)
class WallLines:
    """Walls of a grid as its returns describe them, per occupied cell of a window's index: the ``mean``
    (K, 2, metres, grid frame) of its returns, the ``normal`` (K, 2) of the line through its
    neighbourhood's returns and whether they lie on one (``is_line``; otherwise the returns are matched as
    a point). A cell of the window reads its nearest occupied cell's, kept in ``nearest`` (H, W) the first
    time a match finds it (:func:`~trundle.fusion.mapping.nearest_cells.chamfer_nearest`; -2: not yet)."""

    nearest: np.ndarray
    mean: np.ndarray
    normal: np.ndarray
    is_line: np.ndarray


@dataclass
class ReturnMoments:
    """The moments of the returns in each cell, stored for the cells that hold any: ``slots`` (H, W, int32)
    is each cell's row of ``rows`` (0: none, and row 0 stays zero), ``rows`` (capacity, 6, float32) the
    count and sums of u, v, u^2, uv, v^2 of the returns' offsets in their cell (cell units), ``count``
    the rows in use. A dense (6, H, W) array paid 24 bytes for every cell of every submap (a submap is
    mostly free space and margin: 2.3 GB on fr079); this pays 4, plus 24 per cell that holds a return."""

    slots: np.ndarray
    rows: np.ndarray
    count: int = 1


class LogOddsGrid:
    """Occupancy in log-odds over a growing 2-D array.

    ``resolution`` m/cell; ``p_hit`` / ``p_miss`` the inverse sensor model; ``l_min``/``l_max``
    clamp the log-odds so the map can still change; ``grow_cells`` is the margin added when a scan
    falls outside (growth is amortised). With ``subcell`` each cell also keeps the moments of the
    returns that fell in it, so matching can use the walls those returns describe rather than the
    cell lattice (see :meth:`line_data`); with ``mark_returns`` it keeps whether any return fell in
    it (``returned``, for :meth:`clear_seen_through`).
    """

    def __init__(self, resolution: float = 0.05, *, p_hit: float = 0.7, p_miss: float = 0.4,
                 l_min: float = -2.0, l_max: float = 3.5, origin_xy: tuple[float, float] = (0.0, 0.0),
                 grow_cells: int = 64, subcell: bool = False, mark_returns: bool = False) -> None:
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
        self.moments = ReturnMoments(np.zeros((0, 0), np.int32), np.zeros((64, 6), np.float32)) if subcell else None
        self.returned: np.ndarray | None = np.zeros((0, 0), bool) if mark_returns else None
        # the box (m: x0, y0, x1, y1) of every ray inserted into these arrays, where any occupied cell lies; a
        # grid whose arrays were set otherwise (a loaded map) has none, and its cells may be occupied anywhere
        self._swept = np.array([math.inf, math.inf, -math.inf, -math.inf])
        self._swept_cells: np.ndarray | None = self.log_odds
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
        height, width = self.shape
        (x0, y0), (x1, y1) = np.asarray(xy_min, np.float64).tolist(), np.asarray(xy_max, np.float64).tolist()
        (ox, oy), res = self.origin.tolist(), self.resolution
        if ray_casting.box_inside(x0, y0, x1, y1, ox, oy, res, height, width):   # on floats: an insert asks every scan
            return
        if not all(math.isfinite(v) for v in (x0, y0, x1, y1)):
            raise ValueError(f"the box to hold, {[x0, y0]} to {[x1, y1]}, is not finite")
        col_lo, row_lo, col_hi, row_hi = _corner_cells(x0, y0, x1, y1, ox, oy, res)
        grow = self.grow_cells
        if not height:
            pad_col, pad_row = grow - col_lo, grow - row_lo
            new_w, new_h = col_hi - col_lo + 1 + 2 * grow, row_hi - row_lo + 1 + 2 * grow
        else:
            pad_col, pad_row = (max(-lo, 0) + (grow if lo < 0 else 0) for lo in (col_lo, row_lo))
            new_w = width + pad_col + max(col_hi - (width - 1), 0) + (grow if col_hi >= width else 0)
            new_h = height + pad_row + max(row_hi - (height - 1), 0) + (grow if row_hi >= height else 0)
        if new_h * new_w > MAX_CELLS:
            raise UserError(f"the map would grow to {new_w} x {new_h} cells at {self.resolution:g} m per "
                            f"cell ({new_w * self.resolution:.0f} x {new_h * self.resolution:.0f} m), over "
                            f"the {MAX_CELLS:,} cell limit: use a coarser [slam.submaps] resolution")
        old = (slice(pad_row, pad_row + height), slice(pad_col, pad_col + width))
        grown = np.zeros((new_h, new_w), np.float32)
        seen = np.zeros((new_h, new_w), bool)
        if height:
            grown[old] = self.log_odds
            seen[old] = self.observed
        if self.moments is not None:
            slots = np.zeros((new_h, new_w), np.int32)
            if height:
                slots[old] = self.moments.slots
            self.moments.slots = slots
        if self.returned is not None:
            returned = np.zeros((new_h, new_w), bool)
            returned[old] = self.returned
            self.returned = returned
        if self._swept_cells is self.log_odds:
            self._swept_cells = grown
        self.log_odds, self.observed = grown, seen
        self.origin = np.array([ox - pad_col * res, oy - pad_row * res])
        self._changed()

    def insert_rays(self, sensor_xy: np.ndarray, hits_xy: np.ndarray, free_ends_xy: np.ndarray | None = None) -> None:
        """Update with rays from ``sensor_xy`` (2,): returns at ``hits_xy`` (N, 2), free space to ``free_ends_xy``.

        Coordinates in metres in the grid's frame. ``free_ends_xy`` (M, 2) are the ends of rays that
        saw nothing (cleared, but no hit marked), e.g. no-return beams cut at a chosen distance. Rays
        inside the grid are traced and inserted in one compiled call; others grow it first.
        """
        hits = np.ascontiguousarray(hits_xy, dtype=np.float64).reshape(-1, 2)
        sensor = np.ascontiguousarray(sensor_xy, dtype=np.float64).reshape(2)
        if self.log_odds.flags.writeable:
            slots, rows, count = self._moment_rows(len(hits))
            inserted, count, hit_flat = ray_casting.trace_and_insert(
                self.log_odds, self.observed, slots, rows, count, self.origin, self.resolution, sensor, hits,
                _free_ends(free_ends_xy), self.l_hit, self.l_miss, self.l_min, self.l_max, self._swept)
            if inserted:
                self._inserted(count, hit_flat)
                return
        # outside the grid (traced again: a grid grows seldom, its margins amortise it) or read-only
        self.insert_traced(trace_rays(self.origin, self.resolution, sensor, hits, free_ends_xy))

    def insert_traced(self, rays: TracedRays) -> None:
        """Update with rays traced on this grid's cell lattice (:func:`trace_rays`): one trace serves
        every grid on the lattice, as the two active submaps that take each keyframe are."""
        self.ensure_contains(rays.xy_min, rays.xy_max)
        if not self.log_odds.flags.writeable:
            raise ValueError("this grid is read-only (a map loaded to localize in)")
        # this grid's cell of the trace's cell (0, 0), on floats (numpy's rint and allclose took 40 us an insert)
        shift = [(a - b) / self.resolution for a, b in zip(rays.origin.tolist(), self.origin.tolist(), strict=True)]
        col_shift, row_shift = (round(v) for v in shift)   # half to even, as np.rint
        if not all(abs(v - k) <= 1e-6 + 1e-5 * abs(k) for v, k in zip(shift, (col_shift, row_shift), strict=True)):
            raise ValueError("rays traced on another cell lattice")
        slots, rows, count = self._moment_rows(len(rays.hits))
        # each cell once per scan, hits winning over misses; the returns' moments in their cells
        count, hit_flat = ray_casting.insert_scan(self.log_odds, self.observed, slots, rows, count, rays.hits,
                                                  rays.offsets, rays.crossed, row_shift, col_shift, self.l_hit,
                                                  self.l_miss, self.l_min, self.l_max, self._swept, rays.xy_min,
                                                  rays.xy_max)
        self._inserted(count, hit_flat)

    def _moment_rows(self, returns: int) -> tuple[np.ndarray, np.ndarray, int]:
        """The moments' slots, rows and rows in use for an insert of ``returns`` returns (room made for a new
        row each), or empty ones without moments."""
        moments = self.moments
        if moments is None:
            return _NO_SLOTS, _NO_ROWS, 0
        if moments.count + returns > len(moments.rows):
            grown = np.zeros((2 * (moments.count + returns), 6), np.float32)
            grown[:moments.count] = moments.rows[:moments.count]
            moments.rows = grown
        return moments.slots, moments.rows, moments.count

    def _inserted(self, count: int, hit_flat: np.ndarray) -> None:
        """After an insert: the moment rows in use, the returns' cells marked (``mark_returns``), caches dropped."""
        if self.moments is not None:
            self.moments.count = count
        if self.returned is not None:
            self.returned.reshape(-1)[hit_flat] = True
        self._changed()

    def clear_seen_through(self) -> None:
        """Make every cell that rays crossed and no return ever fell in certainly free (``l_min``): the
        laser saw through it each time it looked, from the first scan on. Cells with a return keep
        their log-odds (a wall, or something that moved). Needs ``mark_returns``."""
        if self.returned is None:
            raise ValueError("clear_seen_through needs a grid made with mark_returns=True")
        self.log_odds[self.observed & ~self.returned] = self.l_min
        self._changed()

    def copy(self) -> LogOddsGrid:
        """An independent copy of the grid (its cells, flags and moments; no cached fields)."""
        clone = copy.copy(self)
        clone.origin, clone.log_odds, clone.observed = self.origin.copy(), self.log_odds.copy(), self.observed.copy()
        clone._swept = self._swept.copy()
        if self.moments is not None:
            clone.moments = ReturnMoments(self.moments.slots.copy(), self.moments.rows.copy(), self.moments.count)
        clone.returned = None if self.returned is None else self.returned.copy()
        clone._swept_cells = clone.log_odds if self._swept_cells is self.log_odds else None
        clone._cache = {}
        return clone

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

    def swept_extent(self, margin: int) -> tuple[int, int, int, int]:
        """The cells (rows [r0, r1), columns [c0, c1)) of the box every inserted ray lies in, grown by ``margin``
        cells and clipped to the grid: no cell outside it was ever occupied, so a field that depends only on
        the occupied cells within ``margin`` is the same everywhere outside. The whole grid if its arrays were
        set otherwise than by inserts (a loaded map); empty if no ray went in."""
        height, width = self.shape
        if self._swept_cells is not self.log_odds:
            return 0, height, 0, width
        x0, y0, x1, y1 = self._swept.tolist()
        if x0 > x1:
            return 0, 0, 0, 0
        (ox, oy), res = self.origin.tolist(), self.resolution
        c0, r0, c1, r1 = _corner_cells(x0, y0, x1, y1, ox, oy, res)
        return max(r0 - margin, 0), min(r1 + margin + 1, height), max(c0 - margin, 0), min(c1 + margin + 1, width)

    def cached(self, key: tuple, factory: Callable[[], T]) -> T:
        """``factory()`` computed once per grid version (fields and pyramids for matching)."""
        if key not in self._cache:
            self._cache[key] = factory()
        return self._cache[key]  # type: ignore[return-value]

    def release_cache(self) -> None:
        """Drop what :meth:`cached` holds (computed again, equal, when next asked for): how a map of
        many submaps keeps the matching fields of only those it still matches against."""
        self._cache.clear()

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

    def match_fields(self, max_distance_m: float, sigma_m: float, lines: bool = False,
                     min_flatness: float = 0.8) -> MatchFields:
        """The fields a scan match reads (:class:`MatchFields`), for this version of the grid."""
        return self.cached(("match", float(max_distance_m), float(sigma_m), bool(lines), float(min_flatness)),
                           lambda: MatchFields(self, max_distance_m, sigma_m, lines, min_flatness))

    def line_data(self, rows: np.ndarray, cols: np.ndarray, min_flatness: float = 0.8
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The walls the returns describe at occupied cells ``(rows, cols)`` (a grid built with ``subcell``):
        the mean of each cell's returns (m) and, where the returns of its 3 x 3 occupied neighbourhood
        lie on a line (``flatness`` at least ``min_flatness``, as in
        :class:`trundle.fusion.matching.icp.LineReference`), that line's normal; returns mean (N, 2),
        normal (N, 2), is_line (N,).

        Occupied cells put every wall on the cell lattice, up to half a cell from where it is, and a
        match inherits that error, the same each time the wall is seen. The returns themselves know better.
        """
        if self.moments is None:
            raise ValueError("wall lines need a grid built with subcell=True")
        mean, twice_sxy, difference, is_line = line_terms(
            self.moments.slots, self.moments.rows, self.log_odds, np.asarray(rows, np.int64),
            np.asarray(cols, np.int64), self.origin, self.resolution, float(min_flatness))
        angle = 0.5 * np.arctan2(twice_sxy, difference)  # direction of the largest spread: the wall
        return mean, np.stack([-np.sin(angle), np.cos(angle)], axis=1), is_line

    def likelihood_field(self, sigma_m: float) -> np.ndarray:
        """``exp(-d^2 / (2 sigma^2))`` of the distance to the nearest occupied cell, 0 beyond 4 sigma."""
        return self.cached(("likelihood", float(sigma_m)),
                           lambda: _likelihood(self._distance_cells(), self.resolution, sigma_m))

    def to_message(self, stamp_ns: int, frame_id: str = "map") -> OccupancyGrid:
        """The grid as nav_msgs/OccupancyGrid: percent occupancy, -1 where never observed."""
        data = np.rint(100.0 * self.probability()).astype(np.int8)
        data[~self.observed] = -1
        return OccupancyGrid(
            stamp_ns, frame_id, self.resolution, float(self.origin[0]), float(self.origin[1]), 0.0, data
        )

    def _changed(self) -> None:
        self.version += 1
        self._cache.clear()
