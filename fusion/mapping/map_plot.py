"""Pictures of maps: ``map.png``, ``trajectory.png`` and ``scans.png``, all drawn the same way.

Every picture has a title, axes in metres (map frame, REP 103: x right, y up), a scale bar and a
legend naming every line, patch and symbol on it, and is sized so that the map's cells show: at
least :data:`PIXELS_PER_CELL` pixels per cell on the long side, between :data:`MIN_PIXELS` and
:data:`MAX_PIXELS` pixels for the map itself. The ``*_figure`` functions build a matplotlib
``Figure`` (no pyplot, no global state) so a test reads its title, labels and legend;
:func:`save_figure` writes it.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.artist import Artist
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import ListedColormap, to_rgb
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Ellipse, Patch
from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

from trundle.fusion.mapping.map_io import FREE, OCCUPIED, UNKNOWN, map_image
from trundle.logs import outputs
from trundle.logs.messages import OccupancyGrid

DPI = 100
PIXELS_PER_CELL = 2.0          # on the map's long side, so a one-cell wall is two pixels wide
MIN_PIXELS, MAX_PIXELS = 800, 2400   # the map's long side (pixels)
LEGEND_INCHES = 3.2            # room right of the map for the legend
MARGIN_INCHES = 1.2            # room for the axis labels and title


@dataclass(frozen=True)
class Track:
    """One path to draw: poses (N, 3) in the map frame (m, rad), its legend label, colour and width (points)."""

    poses: np.ndarray
    label: str
    colour: str
    width: float = 1.5
    alpha: float = 1.0


def _extent(grid: OccupancyGrid) -> tuple[float, float, float, float]:
    """Left, right, bottom, top of the map in metres (map frame)."""
    height, width = grid.data.shape
    return (grid.origin_x, grid.origin_x + width * grid.resolution,
            grid.origin_y, grid.origin_y + height * grid.resolution)


def scale_bar_length(span_m: float) -> float:
    """A round length (1, 2 or 5 times a power of ten, metres) near a fifth of ``span_m``."""
    target = max(span_m, 1e-6) / 5.0
    power = 10.0 ** math.floor(math.log10(target))
    return max(step * power for step in (1.0, 2.0, 5.0) if step * power <= target)


def _figure(grid: OccupancyGrid, title: str) -> tuple[Figure, Axes]:
    """A figure sized for ``grid`` (see the module doc) with one axes in metres, titled, with a scale bar."""
    height, width = grid.data.shape
    long_side = min(max(PIXELS_PER_CELL * max(height, width), MIN_PIXELS), MAX_PIXELS) / DPI   # inches
    map_w, map_h = long_side * width / max(height, width), long_side * height / max(height, width)
    map_w, map_h = max(map_w, 3.0), max(map_h, 3.0)
    fig = Figure(figsize=(map_w + LEGEND_INCHES + MARGIN_INCHES, map_h + MARGIN_INCHES), dpi=DPI,
                 layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    ax.set_title(title)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_aspect("equal")
    left, right, bottom, top = _extent(grid)
    ax.set_xlim(left, right)
    ax.set_ylim(bottom, top)
    length = scale_bar_length(right - left)
    ax.add_artist(AnchoredSizeBar(ax.transData, length, f"{length:g} m", "lower right", pad=0.4, sep=4,
                                  frameon=True, size_vertical=(top - bottom) / 200, color="black"))
    return fig, ax


def _draw_map(ax: Axes, grid: OccupancyGrid) -> list[Patch]:
    """The trinary map under everything else; returns its legend patches (occupied, free, unknown)."""
    grey = {OCCUPIED: "#000000", FREE: "#fefefe", UNKNOWN: "#cdcdcd"}
    image = map_image(grid)
    codes = np.select([image == OCCUPIED, image == FREE], [0, 1], 2)
    ax.imshow(codes, cmap=ListedColormap([grey[OCCUPIED], grey[FREE], grey[UNKNOWN]]), vmin=0, vmax=2,
              extent=_extent(grid), interpolation="nearest", origin="upper", zorder=0)
    return [Patch(facecolor=grey[OCCUPIED], edgecolor="black", label="occupied"),
            Patch(facecolor=grey[FREE], edgecolor="black", label="free"),
            Patch(facecolor=grey[UNKNOWN], edgecolor="black", label="unknown")]


def _legend(ax: Axes, handles: Sequence[Artist]) -> None:
    """The legend right of the map, naming every handle."""
    ax.legend(handles=list(handles), loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0.0,
              fontsize=9)


def map_figure(grid: OccupancyGrid, title: str) -> Figure:
    """``map.png``: the occupancy map (occupied black, free white, unknown grey) in metres."""
    fig, ax = _figure(grid, title)
    _legend(ax, _draw_map(ax, grid))
    return fig


def trajectory_figure(grid: OccupancyGrid, tracks: Sequence[Track], title: str,
                      loops: Sequence[tuple[np.ndarray, np.ndarray]] = (), highlights: Sequence[np.ndarray] = (),
                      landmarks: tuple[list[str], np.ndarray, np.ndarray] | None = None) -> Figure:
    """``trajectory.png``: ``tracks`` over the map, each starting at a circle and ending at a square.

    Tracks are drawn in order, each above the one before; give a reference (ground truth) first
    and wider so the estimates over it leave it visible. ``loops`` are pairs of poses joined by
    thin green lines (loop-closure constraints); ``highlights`` are stretches of path (each
    (N, 3)) drawn wide in magenta under the tracks (where the map fails its self-check);
    ``landmarks`` (ids, positions (M, 2) m, covariances (M, 2, 2) m^2) a cross, the id and the
    3-sigma ellipse each.
    """
    fig, ax = _figure(grid, title)
    handles: list[Artist] = list(_draw_map(ax, grid))
    for k, stretch in enumerate(highlights):
        xy = np.asarray(stretch, np.float64).reshape(-1, 3)
        ax.plot(xy[:, 0], xy[:, 1], color="magenta", lw=6, alpha=0.6, solid_capstyle="round", zorder=1,
                label="fails the map self-check" if k == 0 else None)
    if highlights:
        handles.append(Line2D([], [], color="magenta", lw=6, alpha=0.6, label="fails the map self-check"))
    for k, (a, b) in enumerate(loops):
        ax.plot([a[0], b[0]], [a[1], b[1]], color="tab:green", lw=0.8, zorder=2)
        if k == 0:
            handles.append(Line2D([], [], color="tab:green", lw=0.8, label="loop closure"))
    drawn = False
    for order, track in enumerate(tracks):
        xy = np.asarray(track.poses, np.float64).reshape(-1, 3)
        if len(xy) == 0:
            continue
        z = 3 + order
        line, = ax.plot(xy[:, 0], xy[:, 1], color=track.colour, lw=track.width, alpha=track.alpha,
                        label=track.label, zorder=z)
        ax.plot(xy[0, 0], xy[0, 1], "o", mfc="none", mec=track.colour, ms=9, mew=2, zorder=z)
        ax.plot(xy[-1, 0], xy[-1, 1], "s", mfc="none", mec=track.colour, ms=9, mew=2, zorder=z)
        handles.append(line)
        drawn = True
    if drawn:
        handles += [Line2D([], [], ls="none", marker="o", mfc="none", mec="black", ms=9, mew=2, label="start"),
                    Line2D([], [], ls="none", marker="s", mfc="none", mec="black", ms=9, mew=2, label="end")]
    if landmarks is not None and len(landmarks[0]):
        for name, xy, cov in zip(*landmarks, strict=True):
            x, y = (float(v) for v in np.asarray(xy, np.float64).reshape(2))
            values, vectors = np.linalg.eigh(np.nan_to_num(np.asarray(cov, np.float64).reshape(2, 2)))
            axes = 2 * 3.0 * np.sqrt(np.maximum(values, 0.0))
            angle = math.degrees(math.atan2(vectors[1, 1], vectors[0, 1]))
            ax.add_patch(Ellipse((x, y), max(axes[1], grid.resolution), max(axes[0], grid.resolution),
                                 angle=angle, fill=False, ec="darkmagenta", lw=1, zorder=10))
            ax.plot(x, y, "+", color="darkmagenta", ms=8, mew=1.5, zorder=10)
            ax.annotate(str(name), (x, y), xytext=(5, 5), textcoords="offset points", color="darkmagenta",
                        fontsize=8, zorder=10)
        handles.append(Line2D([], [], ls="none", marker="+", color="darkmagenta", ms=8, mew=1.5,
                              label="landmark (id, 3-sigma ellipse)"))
    _legend(ax, handles)
    return fig


def scans_figure(grid: OccupancyGrid, points: Sequence[np.ndarray], title: str,
                 highlight: np.ndarray | None = None) -> Figure:
    """``scans.png``: scan endpoints (each (N, 2) m, map frame) counted per map cell, over the map's extent.

    Nothing clears anything here, unlike the occupancy map: a wall mapped twice shows twice.
    Darker cells hold more endpoints; cells hit by the scans flagged in ``highlight`` (bool per
    scan) are magenta.
    """
    fig, ax = _figure(grid, title)
    height, width = grid.data.shape
    counts = np.zeros((height, width), np.float64)
    flagged = np.zeros((height, width), bool)
    for k, xy in enumerate(points):
        cols = np.floor((xy[:, 0] - grid.origin_x) / grid.resolution).astype(np.int64)
        rows = np.floor((xy[:, 1] - grid.origin_y) / grid.resolution).astype(np.int64)
        inside = (cols >= 0) & (rows >= 0) & (cols < width) & (rows < height)
        np.add.at(counts, (rows[inside], cols[inside]), 1.0)
        if highlight is not None and highlight[k]:
            flagged[rows[inside], cols[inside]] = True
    shade = 1.0 - np.log1p(counts) / max(float(np.log1p(counts.max())), 1e-9) * 0.9 - 0.1 * (counts > 0)
    rgb = np.repeat(np.clip(shade, 0.0, 1.0)[:, :, None], 3, axis=2)
    rgb[flagged] = (1.0, 0.0, 1.0)
    ax.imshow(rgb, extent=_extent(grid), interpolation="nearest", origin="lower", zorder=0)
    handles = [Patch(facecolor="#404040", edgecolor="black", label="scan endpoints (darker: more)"),
               Patch(facecolor="white", edgecolor="black", label="no endpoint")]
    if highlight is not None and np.any(highlight):
        handles.append(Patch(facecolor="magenta", edgecolor="black", label="scans failing the map self-check"))
    _legend(ax, handles)
    return fig


def sessions_figure(grid: OccupancyGrid, sessions: Sequence[Sequence[np.ndarray]], labels: Sequence[str],
                    colours: Sequence[str], title: str) -> Figure:
    """``sessions.png``: the map's occupied cells in grey, and over them each session's scan endpoints
    (``sessions[k]``: its keyframes' points, each (N, 2) m, map frame) in that session's colour, labelled;
    a cell several sessions hit shows them mixed."""
    fig, ax = _figure(grid, title)
    height, width = grid.data.shape
    total = np.zeros((height, width, 3))
    hits = np.zeros((height, width))
    for points, colour in zip(sessions, colours, strict=True):
        seen = np.zeros((height, width), bool)
        for xy in points:
            cols = np.floor((xy[:, 0] - grid.origin_x) / grid.resolution).astype(np.int64)
            rows = np.floor((xy[:, 1] - grid.origin_y) / grid.resolution).astype(np.int64)
            inside = (cols >= 0) & (rows >= 0) & (cols < width) & (rows < height)
            seen[rows[inside], cols[inside]] = True
        total[seen] += to_rgb(colour)
        hits += seen
    rgb = np.ones((height, width, 3))
    rgb[grid.data >= 50] = 0.75
    rgb[hits > 0] = total[hits > 0] / hits[hits > 0, None]
    ax.imshow(rgb, extent=_extent(grid), interpolation="nearest", origin="lower", zorder=0)
    handles = [Patch(facecolor=colour, edgecolor="black", label=label) for label, colour in zip(labels, colours,
                                                                                                strict=True)]
    handles.append(Patch(facecolor=(0.75, 0.75, 0.75), edgecolor="black", label="occupied, no endpoint drawn"))
    _legend(ax, handles)
    return fig


def plot_sessions(grid: OccupancyGrid, path: str | os.PathLike[str], sessions: Sequence[Sequence[np.ndarray]],
                  labels: Sequence[str], colours: Sequence[str], title: str = "sessions over the map") -> Path:
    """Write ``sessions.png`` (:func:`sessions_figure`)."""
    return save_figure(sessions_figure(grid, sessions, labels, colours, title), path)


def save_figure(fig: Figure, path: str | os.PathLike[str], replace: bool = False) -> Path:
    """Write ``fig`` as a PNG at ``path`` through the one output owner (whole or not at all)."""
    return outputs.save_figure(fig, path, dpi=DPI, replace=replace)


def plot_trajectory(grid: OccupancyGrid, path: str | os.PathLike[str], tracks: Sequence[Track],
                    title: str = "trajectory over the map",
                    loops: Sequence[tuple[np.ndarray, np.ndarray]] = (), highlights: Sequence[np.ndarray] = (),
                    landmarks: tuple[list[str], np.ndarray, np.ndarray] | None = None) -> Path:
    """Write ``trajectory.png`` (:func:`trajectory_figure`)."""
    return save_figure(trajectory_figure(grid, tracks, title, loops, highlights, landmarks), path)


def plot_scans(grid: OccupancyGrid, path: str | os.PathLike[str], points: Sequence[np.ndarray],
               highlight: np.ndarray | None = None, title: str = "scan endpoints at their poses") -> Path:
    """Write ``scans.png`` (:func:`scans_figure`)."""
    return save_figure(scans_figure(grid, points, title, highlight), path)
