"""What `trundle status` and `trundle info` print reads as text: no Python dicts, no rate for a
latched topic's few messages."""

from __future__ import annotations

from pathlib import Path

from trundle.logs import messages as m
from trundle.logs.writer import Logger
from trundle.tools.cli.main import main
from trundle.tools.daemon.status import format_status

STATUS = {
    "daemon": {"robot": "rover", "state": "running", "pid": 42, "uptime_s": 3725.0},
    "devices": [],
    "logger": {"recording": False, "paused": None, "written": 10, "dropped": 0},
    "processing": {"queue": 0, "dropped": 1, "skipped_scans": 0, "errors": 0, "last_error": "",
                   "slam": {"scans": 309, "keyframes": 120, "matched": 300, "loop_closures": 2},
                   "markers": {"3": 12, "96": 4}, "landmark_messages": 16},
}


def test_status_says_slam_and_markers_in_words() -> None:
    assert format_status(STATUS).splitlines()[-3:] == [
        "processing: queue 0, dropped 1, errors 0",
        "  slam: 309 scans, 120 keyframes, 300 matched, 2 loop closures",
        "  markers seen: id 3 12 times, id 96 4 times; 16 landmark messages",
    ]
    assert "{" not in format_status(STATUS)


def test_info_gives_no_rate_for_a_latched_topic(tmp_path: Path, capsys) -> None:
    path = tmp_path / "run.mcap"
    static = m.TFMessage((m.TransformStamped.planar(0, "base_link", "laser", 0.1, 0.0, 0.0),))
    with Logger(path, salvage=False) as logger:
        logger.write("/tf_static", static, 1_000_000_000)
        logger.write("/tf_static", static, 1_002_000_000)   # 2 ms apart: "500 Hz"
        for k in range(11):
            t = 1_000_000_000 + k * 100_000_000
            logger.write("/odom", m.Odometry(t, "odom", "base_link", 0.1 * k, 0.0, 0.0), t)
    assert main(["info", str(path)]) == 0
    lines = capsys.readouterr().out.splitlines()
    odom = next(line for line in lines if "/odom" in line)
    static_line = next(line for line in lines if "/tf_static" in line)
    assert "Count:      11 | Rate:    10.00 Hz |" in odom
    assert "Count:       2 | Rate:        -    |" in static_line and static_line.endswith("| latched")
