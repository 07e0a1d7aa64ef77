"""Long work says what it does: `trundle record` shows its topics' rates and the file's size (a
line redrawn in place on a terminal, a line every few seconds otherwise); `trundle replay` shows, on
a terminal, the log time played, the wall time and the rate achieved."""

from __future__ import annotations

import io
import re
import sys
import time
from pathlib import Path

from trundle.tools.cli import record
from trundle.tools.cli.main import main
from trundle.tools.cli.progress import StatusLine
from trundle.tools.emulators.device_server import DeviceServer
from trundle.tools.emulators.scene import load_scene
from trundle.tools.emulators.scip2_emulator import MODELS, ScipDevice


class Tty(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_record_says_its_rates_and_file_size_while_it_records(tmp_path: Path, capsys, monkeypatch) -> None:
    monkeypatch.setattr(record, "PROGRESS_PERIOD_S", 1.0)   # stderr is no terminal here: a line a second
    model = MODELS["urg-04lx"]
    device = ScipDevice(model, load_scene().range_source(model.angles, seed=9), now_ns=time.time_ns())
    out = tmp_path / "run.mcap"
    with DeviceServer(device, link_path=tmp_path / "lrf"):
        assert main(["record", "--lrf", f"scip2://{tmp_path / 'lrf'}", "-o", str(out), "--duration", "3.5"]) == 0
    lines = [line for line in capsys.readouterr().err.splitlines() if line.startswith("recording ")]
    assert lines, "no progress line"
    for line in lines:
        assert re.fullmatch(r"recording \d s of 3\.5 s: /scan \d+\.\d Hz, /scan/timing \d+\.\d Hz; "
                            r"\d+\.\d MB in run\.mcap\.active", line), line
    assert any(float(re.search(r"/scan ([\d.]+) Hz", line).group(1)) > 0 for line in lines)


def test_on_a_terminal_the_line_is_redrawn_in_place() -> None:
    stream = Tty()
    first, second = "recording 1 s (Ctrl-C stops): /scan 10.0 Hz; 0.1 MB in run.mcap.active", "recording 2 s: x"
    line = StatusLine(stream)
    line._next = 0.0   # (the once-a-second limit, not what is tested here)
    line.update(first)
    line._next = 0.0
    line.update(second)
    line.close()
    assert stream.getvalue() == f"\r{first}\r{second:<{len(first)}}\n"   # spaces over the longer line before


def test_the_progress_text_names_what_stops_a_recording_without_duration() -> None:
    class NoFile:
        current_path = None

    assert record.progress_text(12.4, None, {"/scan": 10.0, "/wheels": 100.0}, NoFile()) == (
        "recording 12 s (Ctrl-C stops): /scan 10.0 Hz, /wheels 100.0 Hz; no file open")


REPLAY_DRAWN = re.compile(r"replay \[(#*) *\] +(\d+)% log (\d+\.\d) s, wall (\d+\.\d) s, rate (\d+\.\d\d)x")


def test_replay_shows_log_time_wall_time_and_the_rate_achieved_on_a_terminal(capsys, monkeypatch) -> None:
    """Each redraw: a bar of the window played, the log seconds played, the wall seconds since the replay
    began and the rate achieved (log seconds per wall second); the figures agree to their printed digits."""
    demo_log = Path(__file__).resolve().parent / "data" / "demo_short" / "demo.mcap"
    argv = ["replay", str(demo_log), "--rate", "4", "--end", "2", "--topics", "/scan"]
    assert main(argv) == 0
    assert capsys.readouterr().err == ""   # no terminal: no bar
    terminal = Tty()
    monkeypatch.setattr(sys, "stderr", terminal)
    assert main(argv) == 0
    shown = terminal.getvalue()
    assert shown.startswith("\r") and shown.endswith("\n") and shown.count("\n") == 1
    draws = [REPLAY_DRAWN.fullmatch(text) for text in shown[1:-1].split("\r")]
    assert len(draws) >= 2 and all(draws), shown
    previous = (0.0, 0.0)
    for draw in draws:
        assert draw is not None
        bar, percent = len(draw[1]), int(draw[2])
        log_s, wall_s, rate = float(draw[3]), float(draw[4]), float(draw[5])
        assert (log_s, wall_s) >= previous   # neither goes back
        previous = (log_s, wall_s)
        fraction = log_s / 2.0   # of the 2 s window; each figure within its own rounding
        assert abs(percent / 100 - fraction) <= 0.005 + 0.025 and int(30 * (percent - 0.5) / 100) <= bar
        assert bar <= int(30 * (percent + 0.5) / 100)
        if wall_s > 0.05:
            assert (log_s - 0.05) / (wall_s + 0.05) - 0.005 <= rate <= (log_s + 0.05) / (wall_s - 0.05) + 0.005
    assert float(draws[-1][3]) > 0.0
