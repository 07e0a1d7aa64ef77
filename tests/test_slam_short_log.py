"""A short, stationary log through `trundle slam`: free space from the first scan on, and a map
self-check with nothing to compare said as "not checked", never as passed (issue 23, item 8)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from tests.planar_world import ROOM, scan
from trundle.fusion.mapping.map_io import load_map
from trundle.logs import messages as m
from trundle.logs.importers import write_log
from trundle.tools.cli.main import main
from trundle.tools.fleet.summary import markdown, not_checked

LASER = np.array([0.1, 0.0, 0.0])  # the laser's pose in the room: 0.1 m ahead of base_link at the origin
MAX_RANGE_M = 10.0


@pytest.fixture(scope="module")
def stationary_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """9.9 s of a robot standing still in the room: 10 Hz odometry (zero) and 270-degree scans."""
    items: list[tuple[str, m.Message, int]] = [
        ("/tf_static", m.TFMessage((m.TransformStamped.planar(0, "base_link", "laser", 0.1, 0.0, 0.0),)), 0)]
    for k in range(100):
        stamp = 10**9 + k * 10**8
        items.append(("/odom", m.Odometry(stamp, "odom", "base_link", 0.0, 0.0, 0.0), stamp))
        items.append(("/scan", scan(ROOM, LASER, beams=181, fov=math.radians(270.0), noise_m=0.01, seed=k,
                                    stamp_ns=stamp, max_range=MAX_RANGE_M), stamp))
    path = tmp_path_factory.mktemp("short") / "standing.mcap"
    write_log(items, path, metadata={"command": "test"})
    return path


def test_stationary_log_map_has_free_space_and_an_unchecked_self_check(
        stationary_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    assert main(["slam", str(stationary_log), "-o", str(out)]) == 0
    captured = capsys.readouterr()
    assert "100 scans (2 keyframes)" in captured.out  # keyframes at 0 and 5 s: a free cell is crossed twice at most
    assert captured.err.splitlines() == [
        "trundle slam: the map's self-check was not made: no keyframe lies outside the submaps it was part of, so "
        "nothing could be compared (a short or stationary log); report.json says 'not checked'"]

    text = (out / "report.json").read_text()
    assert "NaN" not in text
    check = json.loads(text)["map_check"]
    assert check == {"status": "not checked", "passed": None, "consistency": None, "compared_keyframes": 0,
                     "inconsistent_keyframes": 0, "min_stretch": 5, "stretches": []}

    grid = load_map(out / "map.yaml")  # map_server's reading of map.pgm: 0 free, 100 occupied, -1 unknown
    rows, cols = np.nonzero(grid.data == 0)
    centres = np.array([grid.origin_x, grid.origin_y]) + (np.stack([cols, rows], axis=1) + 0.5) * grid.resolution
    assert len(centres) > 1000  # 2.5 m^2 and more: the room the laser looked into, not a few stray cells
    assert np.hypot(*(centres - LASER[:2]).T).max() < MAX_RANGE_M  # within the first scan's range
    lo, hi = ROOM[:4, :2].min(axis=0), ROOM[:4, :2].max(axis=0)
    assert np.all((centres > lo) & (centres < hi))  # inside the room's outer walls: nothing seen through them
    # the middle beam (90 of 181: -0.75 degrees) of the first scan, taken at the map's origin, crosses the room
    # to the east wall (x = 5.01 m): free all along, but for its last cells
    first = scan(ROOM, LASER, beams=181, fov=math.radians(270.0))
    angle = first.angle_min + 90 * first.angle_increment
    free = {(int(c), int(r)) for c, r in zip(cols, rows, strict=True)}
    along = LASER[:2] + np.arange(0.2, 4.7, 0.01)[:, None] * np.array([math.cos(angle), math.sin(angle)])
    crossed = {(int(c), int(r)) for c, r in (along - (grid.origin_x, grid.origin_y)) // grid.resolution}
    assert crossed <= free


def test_fleet_summary_lists_a_check_not_made_apart_from_failed_ones() -> None:
    rows = [{"log": "/l/short.mcap", "name": "short", "status": "ok", "error": "", "seconds": 1.0,
             "map_check.status": "not checked", "map_check.passed": None},
            {"log": "/l/long.mcap", "name": "long", "status": "ok", "error": "", "seconds": 9.0,
             "map_check.status": "passed", "map_check.passed": True}]
    assert not_checked(rows) == {"map_check.status": ["/l/short.mcap"]}
    page = markdown("slam", rows, {"elapsed_s": 10.0, "cpus": 2, "logs_per_minute": 12.0, "options": {}}, None)
    assert "## Checks that failed" not in page
    assert "- map_check.status: not checked for 1 of 2 logs (nothing to compare): /l/short.mcap\n" in page
