"""Every map picture trundle draws (map.png, trajectory.png, scans.png, the demo's trajectory.png):
a title, axes in metres, a scale bar, a legend naming every line and symbol, and a size that shows
the map's cells. Read from the figure objects and from the files `trundle slam` writes."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

from tests.test_slam_command import simulated_log, trundle  # noqa: F401  (simulated_log is a fixture)
from trundle.fusion.mapping.map_plot import (
    MAX_PIXELS,
    PIXELS_PER_CELL,
    Track,
    map_figure,
    scale_bar_length,
    trajectory_figure,
)
from trundle.logs import messages as m
from trundle.tools.demo.report import plot_run, run_figure
from trundle.tools.jobs.sensor_report import beam_noise_figure, sensitivity_figure


def room(cells: tuple[int, int] = (240, 400), resolution: float = 0.05) -> m.OccupancyGrid:
    """A free room with one-cell walls, origin (-1, -2) m."""
    data = np.zeros(cells, np.int8)
    data[0, :] = data[-1, :] = data[:, 0] = data[:, -1] = 100
    return m.OccupancyGrid(0, "map", resolution, -1.0, -2.0, 0.0, data)


def legend_texts(figure) -> list[str]:
    return [t.get_text() for t in figure.axes[0].get_legend().get_texts()]


def scale_bar(figure) -> str:
    bars = [a for a in figure.axes[0].artists if isinstance(a, AnchoredSizeBar)]
    assert len(bars) == 1
    return bars[0].txt_label.get_text()


def map_pixels(figure) -> tuple[float, float]:
    """Width and height (pixels) of the map's axes once drawn."""
    figure.canvas.draw()
    box = figure.axes[0].get_window_extent()
    return box.width, box.height


def test_map_picture_has_title_metres_scale_bar_legend_and_two_pixels_per_cell() -> None:
    figure = map_figure(room(), "occupancy map of room")
    ax = figure.axes[0]
    assert ax.get_title() == "occupancy map of room"
    assert (ax.get_xlabel(), ax.get_ylabel()) == ("x (m)", "y (m)")
    assert ax.get_xlim() == pytest.approx((-1.0, 19.0)) and ax.get_ylim() == pytest.approx((-2.0, 10.0))  # 5 cm cells
    assert scale_bar(figure) == "2 m"   # a round length near a fifth of the 20 m width
    assert legend_texts(figure) == ["occupied", "free", "unknown"]
    width, height = map_pixels(figure)
    assert width >= PIXELS_PER_CELL * 400 * 0.98 and height >= PIXELS_PER_CELL * 240 * 0.98


def test_a_large_map_is_capped_and_a_tiny_one_still_readable() -> None:
    width, _ = map_pixels(map_figure(room((1000, 1500)), "big"))   # 3000 pixels at two a cell
    assert width <= 1.05 * MAX_PIXELS   # constrained layout gives the axes a few of the margin's pixels
    width, height = map_pixels(map_figure(room((20, 30)), "small"))
    assert width >= 290 and height >= 290   # at least 3 inches a side


@pytest.mark.parametrize(("span", "bar"), [(20.0, 2.0), (9.0, 1.0), (50.0, 10.0), (1.2, 0.2), (130.0, 20.0)])
def test_scale_bar_is_a_round_length(span: float, bar: float) -> None:
    assert scale_bar_length(span) == pytest.approx(bar)


def test_trajectory_picture_names_every_line_and_symbol() -> None:
    poses = np.array([[0.0, 0.0, 0.0], [5.0, 0.0, 0.0], [5.0, 5.0, 1.57]])
    figure = trajectory_figure(room(), [Track(poses, "SLAM trajectory", "tab:red")], "SLAM trajectory of x.mcap",
                               loops=[(poses[0], poses[2])], highlights=[poses[:2]],
                               landmarks=(["7"], np.array([[3.0, 3.0]]), np.eye(2)[None] * 0.01))
    assert figure.axes[0].get_title() == "SLAM trajectory of x.mcap"
    assert scale_bar(figure) == "2 m"
    assert legend_texts(figure) == ["occupied", "free", "unknown", "fails the map self-check", "loop closure",
                                    "SLAM trajectory", "start", "end", "landmark (id, 3-sigma ellipse)"]
    assert [t.get_text() for t in figure.axes[0].texts] == ["7"]


def test_demo_trajectory_shows_ground_truth_under_slam_and_names_everything(tmp_path) -> None:
    truth = np.array([[0.0, 0.0, 0.0], [5.0, 0.0, 0.0], [5.0, 5.0, 1.57]])
    args = (room(), truth, truth, truth + 0.3, [(truth[0], truth[2])],
            (["3"], np.array([[2.0, 2.0]]), np.eye(2)[None] * 0.01))
    figure = run_figure(*args)
    assert figure.axes[0].get_title() == "demo: ground truth, wheel odometry and SLAM over the SLAM map"
    assert legend_texts(figure) == ["occupied", "free", "unknown", "loop closure", "ground truth (simulator)",
                                    "wheel odometry", "SLAM estimate", "start", "end", "landmark (id, 3-sigma ellipse)"]
    lines = {line.get_label(): line for line in figure.axes[0].get_lines()}
    truth_line, slam_line = lines["ground truth (simulator)"], lines["SLAM estimate"]
    # the same path: the ground truth is a wider band below the SLAM line, so both show
    assert truth_line.get_linewidth() >= 3 * slam_line.get_linewidth()
    assert truth_line.get_zorder() < slam_line.get_zorder()
    path = plot_run(args[0], tmp_path / "trajectory.png", *args[1:])
    height, width = cv2.imread(str(path), cv2.IMREAD_COLOR).shape[:2]
    assert width >= PIXELS_PER_CELL * 400 and height >= PIXELS_PER_CELL * 240


def test_slam_command_pictures_on_disk(simulated_log, tmp_path, capsys) -> None:  # noqa: F811
    log, _ = simulated_log
    out = tmp_path / "out"
    code, _, stderr = trundle(capsys, "slam", str(log), "-o", str(out))
    assert code == 0, stderr
    cells = cv2.imread(str(out / "map.pgm"), cv2.IMREAD_UNCHANGED).shape
    for name in ("map.png", "trajectory.png", "scans.png"):
        height, width = cv2.imread(str(out / name), cv2.IMREAD_COLOR).shape[:2]
        assert width >= PIXELS_PER_CELL * max(cells) and height >= PIXELS_PER_CELL * min(cells), name


def test_characterize_pictures_have_titles_units_and_a_legend_for_every_line() -> None:
    angles = np.radians(np.linspace(-120.0, 120.0, 5))
    noise = beam_noise_figure(angles, np.array([0.01, 0.012, 0.011, 0.009, 0.01])).axes[0]
    assert noise.get_title() == "Per-beam noise while standing still"
    assert (noise.get_xlabel(), noise.get_ylabel()) == ("beam angle (deg)", "noise std (mm, log)")
    assert [t.get_text() for t in noise.get_legend().get_texts()] == ["noise std of each beam", "median 10.0 mm"]
    true = np.linspace(0.5, 3.0, 50)
    sensitivity = sensitivity_figure(true, true * 1.01).axes[0]
    assert sensitivity.get_title() == "Sensitivity: measured against true range"
    assert (sensitivity.get_xlabel(), sensitivity.get_ylabel()) == ("true value (m)", "measured (m)")
    assert [t.get_text() for t in sensitivity.get_legend().get_texts()] == ["readings", "measured = true"]
