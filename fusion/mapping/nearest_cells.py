"""The match fields' nearest occupied cells, compiled (numba, cached on disk): for each cell of a window, a
field of the distance to the nearest occupied cell within a radius (the search's likelihood); and for one
cell at a time, that distance and the occupied cell whose wall line the refinement reads there.

The search reads the likelihood wherever a lattice pose puts a point, only up to 4 sigma from a wall, so
each occupied cell stamps a disc of that radius into the window: exact Euclidean distances (OpenCV's
precise transform of the whole padded window gives the same to float32 rounding), each field's value
looked up per squared distance instead of computed per cell. It costs the occupied cells times the
disc, not passes over the whole padded window.

The refinement reads the capped distance (half a metre: a disc six times the likelihood's) and the
wall lines' nearest cell at a few hundred cells where the window holds tens of thousands, so it finds
them there: :func:`squared_nearest` the stamp's value, from the occupied cells of the rows around each
(bisecting a row's), :func:`chamfer_nearest` OpenCV's labelled distance transform's label, searching rings
of cells around each (``distanceTransformWithLabels``,
which takes its 5 x 5 chamfer metric for L2; Borgefors 1986), ties included. Labelling the whole padded
window cost a quarter of a match, and stamping the distance to its cap a sixth.
"""

from __future__ import annotations

import numpy as np

from trundle.fusion.compiled import kernel


def squared_distances(radius: int) -> np.ndarray:
    """The distances (cells, float32) a disc of ``radius`` cells can hold, indexed by their square, and inf
    after them (no occupied cell within the radius): what the fields' tables are made from."""
    values = np.sqrt(np.arange(radius * radius + 2, dtype=np.float64)).astype(np.float32)
    values[-1] = np.inf
    return values


@kernel
def stamped_field(rows: np.ndarray, cols: np.ndarray, row0: int, col0: int, height: int, width: int, radius: int,
                  values: np.ndarray) -> np.ndarray:
    """A field (height, width) over the window ``[row0, row0 + height) x [col0, col0 + width)`` (the
    coordinates of ``rows``, ``cols``): ``values`` at each cell's squared distance in cells to the nearest of
    the occupied cells ``(rows, cols)``.

    ``values`` (radius^2 + 2,) must not increase with the squared distance (a likelihood), the last for
    none within ``radius`` (see :func:`squared_distances`). Each occupied cell stamps the square around it
    with the larger of the cell's value and its own: the disc's values, and outside the disc the value for
    none, which changes nothing. So the value at the least squared distance, with no array of distances, no
    pass over the window to look them up, and no test per cell (a test per cell, or a disc's row ends per
    row, cost more than the cells the square adds).
    """
    none = values[values.shape[0] - 1]
    size = 2 * radius + 1
    square = np.empty(size * size, np.float32)
    for dr in range(-radius, radius + 1):
        for dc in range(-radius, radius + 1):
            squared = dr * dr + dc * dc
            square[(dr + radius) * size + dc + radius] = values[squared] if squared <= radius * radius else none
    field = np.full((height, width), none, np.float32)
    flat = field.ravel()
    for k in range(rows.shape[0]):
        r, c = rows[k] - row0, cols[k] - col0
        first, last = max(-radius, -c), min(radius, width - 1 - c)
        for dr in range(max(-radius, -r), min(radius, height - 1 - r) + 1):
            cell, stamp = (r + dr) * width + c, (dr + radius) * size + radius
            for dc in range(first, last + 1):
                flat[cell + dc] = max(flat[cell + dc], square[stamp + dc])
    return field


@kernel
def occupied_cells(log_odds: np.ndarray, r0: int, r1: int, c0: int, c1: int
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The occupied cells (log-odds above 0) of ``log_odds[r0:r1, c0:c1]``: their rows and columns in that
    window, in ``np.nonzero``'s (row-major) order; the window's index of them (int32: each occupied
    cell's position in that order, -1 elsewhere), which :func:`chamfer_nearest` searches; and where each
    row's cells start in that order (``starts[i]:starts[i + 1]``: row i's, its columns ascending), which
    :func:`squared_nearest` searches. One pass where numpy made a mask and its nonzero."""
    height, width = r1 - r0, c1 - c0
    index = np.full((height, width), -1, np.int32)
    rows = np.empty(height * width, np.int64)
    cols = np.empty(height * width, np.int64)
    starts = np.empty(height + 1, np.int64)
    count = 0
    for i in range(height):
        starts[i] = count
        values, found = log_odds[r0 + i, c0:c1], index[i]   # a row's views: no index arithmetic per cell
        for j in range(width):
            if values[j] > np.float32(0.0):
                found[j] = count
                rows[count], cols[count] = i, j
                count += 1
    starts[height] = count
    return rows[:count].copy(), cols[:count].copy(), index, starts


# OpenCV's 5 x 5 chamfer steps (1, 1.4 and 2.1969 cells: straight, diagonal, knight's move) in the fixed
# point its labelled transform adds them in (cvRound(w * 2^16)), so that equal sums are equal here too
STRAIGHT, DIAGONAL, KNIGHT = 65536, 91750, 143976


@kernel(inline=True)
def chamfer(d_row: int, d_col: int) -> int:
    """The 5 x 5 chamfer distance of a cell offset, in :data:`STRAIGHT` units: the cheapest sum of the
    three steps that makes it (knight's moves and straight steps up to a slope of 1/2, knight's moves and
    diagonals above it)."""
    u, v = abs(d_col), abs(d_row)
    if u < v:
        u, v = v, u
    if 2 * v <= u:
        return v * KNIGHT + (u - 2 * v) * STRAIGHT
    return (u - v) * KNIGHT + (2 * v - u) * DIAGONAL


@kernel(inline=True)
def _first_pass_reaches(d_row: int, d_col: int) -> bool:
    """Does the first (top-down) pass of the two-pass transform carry a seed at offset (``d_row``, ``d_col``)
    to a cell: a seed above it at most two columns to the right per row up, or left of it on its row."""
    return (d_row < 0 and d_col <= -2 * d_row) or (d_row == 0 and d_col < 0)


@kernel(inline=True)
def _wins_tie(d_row: int, d_col: int, m: int, other_row: int, other_col: int, other: int) -> bool:
    """Does occupied cell ``m`` at offset (``d_row``, ``d_col``) keep a cell's label from ``other``, equally near?
    OpenCV's passes keep the first of equals they meet: one the first pass carries wins over one it does
    not; the first pass meets its own in row-major order, the second in reverse."""
    mine, theirs = _first_pass_reaches(d_row, d_col), _first_pass_reaches(other_row, other_col)
    if mine != theirs:
        return mine
    return m < other if mine else m > other


@kernel
def _nearest(occupied: np.ndarray, row: int, col: int, rings: int) -> int:
    """The occupied cell (its value in ``occupied``; -1: none) nearest the cell (``row``, ``col``) within
    ``rings`` rings of cells around it in the 5 x 5 chamfer metric (:func:`chamfer`), equally near cells
    decided as OpenCV does (:func:`_wins_tie`). The rings go out to where none can hold a nearer cell (a
    ring k cells out is at least k straight steps away)."""
    height, width = occupied.shape
    best, found, found_row, found_col = 1 << 62, -1, 0, 0
    for k in range(rings + 1):
        if k * STRAIGHT > best:
            break
        for d_row in range(-k, k + 1):
            i = row + d_row
            if i < 0 or i >= height:
                continue
            step = 1 if d_row == -k or d_row == k else 2 * k   # the ring's top and bottom rows, else its ends
            for d_col in range(-k, k + 1, step):
                j = col + d_col
                if j < 0 or j >= width or occupied[i, j] < 0:
                    continue
                m = occupied[i, j]
                e = chamfer(d_row, d_col)
                if e < best or (e == best and _wins_tie(d_row, d_col, m, found_row, found_col, found)):
                    best, found, found_row, found_col = e, m, d_row, d_col
    return found


@kernel
def squared_nearest(starts: np.ndarray, cols: np.ndarray, row: int, col: int, radius: int) -> int:
    """The squared distance (cells^2) from cell (``row``, ``col``) to the nearest occupied cell (row i's columns
    are ``cols[starts[i]:starts[i + 1]]``, ascending; see :func:`occupied_cells`), ``radius^2 + 1`` when none is
    within ``radius`` cells: the value a stamp of every occupied cell's disc would give that cell.

    Row by row outwards from the cell's, each row's nearest column found by bisection, until a row is as far
    as the nearest found. A cell far from every wall read the (2 radius + 1)^2 cells around it one by one
    (441 at the defaults): the refinement's first evaluations spent two thirds of their time there."""
    height = starts.shape[0] - 1
    best = radius * radius + 1
    for k in range(radius + 1):
        if k * k >= best:
            break
        for i in (row - k, row + k):   # k = 0: the cell's row twice
            if i < 0 or i >= height or starts[i] == starts[i + 1]:
                continue
            low, high = starts[i], starts[i + 1]
            # the first column at or right of the cell's (np.searchsorted on the row's slice: 15-20 us a
            # match more, its view and call per row)
            while low < high:
                middle = (low + high) >> 1
                if cols[middle] < col:
                    low = middle + 1
                else:
                    high = middle
            if low < starts[i + 1]:
                best = min(best, k * k + (cols[low] - col) * (cols[low] - col))
            if low > starts[i]:
                best = min(best, k * k + (col - cols[low - 1]) * (col - cols[low - 1]))
    return best


@kernel(inline=True)
def kept_squared(squared: np.ndarray, width: int, starts: np.ndarray, cols: np.ndarray, d_row: int, d_col: int,
                 radius: int, flat: int) -> int:
    """The squared distance of a window's cell at flat index ``flat``: kept in ``squared`` (the window's, ``width``
    cells a row, flattened; -1: not found yet), else found (:func:`squared_nearest`, the occupied cells
    ``starts``, ``cols``) and kept. The window's cell (0, 0) is the occupied cells' (``d_row``, ``d_col``)."""
    kept = squared[flat]
    if kept < 0:
        kept = squared_nearest(starts, cols, flat // width + d_row, flat % width + d_col, radius)
        squared[flat] = kept
    return kept


@kernel
def all_squared_nearest(squared: np.ndarray, starts: np.ndarray, cols: np.ndarray, d_row: int, d_col: int,
                        radius: int) -> np.ndarray:
    """Every cell of ``squared`` (a window's squared distances, -1: not found yet) found, in place
    (:func:`kept_squared`)."""
    flat = squared.reshape(-1)
    for cell in range(flat.shape[0]):
        kept_squared(flat, squared.shape[1], starts, cols, d_row, d_col, radius, cell)
    return squared


@kernel(inline=True)
def kept_nearest(nearest: np.ndarray, occupied: np.ndarray, row: int, col: int, d_row: int, d_col: int) -> int:
    """The nearest occupied cell of a window's cell (``row``, ``col``): kept in ``nearest`` (the window's; -2: not
    found yet), else found (:func:`chamfer_nearest`) and kept. The window's cell (0, 0) is ``occupied``'s
    (``d_row``, ``d_col``)."""
    kept = nearest[row, col]
    if kept < -1:
        kept = chamfer_nearest(occupied, row + d_row, col + d_col)
        nearest[row, col] = kept
    return kept


@kernel
def chamfer_nearest(occupied: np.ndarray, row: int, col: int) -> int:
    """The occupied cell (its value in ``occupied``, see :func:`occupied_cells`; -1: none) nearest the cell
    (``row``, ``col``) of ``occupied`` in the 5 x 5 chamfer metric: the label less one that OpenCV's
    ``distanceTransformWithLabels(image, DIST_L2, ..., DIST_LABEL_PIXEL)`` gives that cell, where the
    image is 0 on ``occupied``'s occupied cells."""
    height, width = occupied.shape
    return _nearest(occupied, row, col, max(row, height - 1 - row, col, width - 1 - col))
