"""Outputs are never overwritten and nothing is left behind: a repeated command loses no
recording, a bad URL makes no empty log, a second daemon on the same config writes nothing,
`recover IN DIR` writes into DIR and leaves no temporary file. An output appears whole or not at
all; JSON is strict."""

from __future__ import annotations

import hashlib
import json
import os
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from tests.test_daemon import Running, ScriptedDriver, config, wait_for
from trundle.logs.errors import DataError, UserError
from trundle.logs.outputs import write_json, write_text, writing_file, writing_files, writing_folder
from trundle.logs.reader import LogReader
from trundle.logs.recover import recover
from trundle.tools.cli.main import main
from trundle.tools.daemon.service import Daemon

DEMO_LOG = Path(__file__).resolve().parent / "data" / "demo_short" / "demo.mcap"


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_a_repeated_command_refuses_to_overwrite_its_output(tmp_path, capsys):
    dat = tmp_path / "run.dat"
    dat.write_text("".join(" ".join([str(100_000 * k), "0", str(k), str(k)] + ["0"] * 20 + ["900"] * 683) + "\n"
                           for k in range(1, 6)))
    out = tmp_path / "run.mcap"
    assert main(["import", "breezyslam", str(dat), "-o", str(out)]) == 0
    before = digest(out)
    for argv in (["import", "breezyslam", str(dat), "-o", str(out)],
                 ["perceive", str(DEMO_LOG), "--pipeline", "markers", "-o", str(out)],
                 ["record", "--lrf", "scip2:///dev/null", "--duration", "1", "-o", str(out)],
                 ["recover", str(DEMO_LOG), str(out)]):
        capsys.readouterr()
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and f"{out} exists" in err, (argv, err)
    assert digest(out) == before
    (tmp_path / "part_0.mcap").write_text("an earlier split recording")
    assert main(["record", "--lrf", "scip2:///dev/null", "--split-size", "1", "-o", str(tmp_path / "part.mcap")]) == 2
    assert "part_0.mcap exists" in capsys.readouterr().err


def test_slam_refuses_a_folder_with_results_in_it(tmp_path, capsys):
    out = tmp_path / "map"
    out.mkdir()
    (out / "map.pgm").write_text("yesterday's map")
    assert main(["slam", str(DEMO_LOG), "-o", str(out)]) == 2
    assert "is not empty" in capsys.readouterr().err and (out / "map.pgm").read_text() == "yesterday's map"


def test_a_bad_url_leaves_no_empty_log(tmp_path, capsys):
    for url in ("foo://x", "scip2+tcp://", "rplidar:///dev/ttyUSB0?model=z9"):
        assert main(["record", "--lrf", url, "-o", str(tmp_path / "run.mcap")]) == 2
        assert capsys.readouterr().err.count("\n") == 1
    assert not list(tmp_path.iterdir())


def test_a_second_daemon_on_the_same_config_writes_nothing(tmp_path):
    cfg = config(tmp_path)
    with Running(cfg) as first:
        wait_for(lambda: first.daemon.logger is not None)
        folder = cfg.logger.folder
        before = sorted(p.name for p in folder.iterdir())
        second = Daemon(cfg, make_driver=lambda family, url, sink, options: ScriptedDriver(family, sink))
        with pytest.raises(UserError, match="another trundle daemon is answering"):
            second.run(install_signals=False)
        time.sleep(0.2)
        assert sorted(p.name for p in folder.iterdir()) == before
        assert first.daemon.status()["daemon"]["state"] == "running"


def test_recover_into_a_folder_leaves_no_temporary_file(tmp_path, capsys):
    cut = tmp_path / "run.mcap.active"
    data = DEMO_LOG.read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    folder = tmp_path / "salvaged"
    folder.mkdir()
    assert main(["recover", str(cut), str(folder)]) == 0
    assert f"into {folder / 'run.mcap'}" in capsys.readouterr().out
    assert sorted(p.name for p in folder.iterdir()) == ["run.mcap"] and LogReader(folder / "run.mcap").info().complete
    header_only = tmp_path / "header.mcap"
    header_only.write_bytes(data[:8])
    with pytest.raises(DataError, match="nothing could be recovered"):
        recover(header_only, folder / "nothing.mcap")
    assert sorted(p.name for p in folder.iterdir()) == ["run.mcap"]
    assert not list(tmp_path.glob("**/*.tmp"))


def test_a_recorder_killed_mid_import_is_not_needed(tmp_path):
    """The same guard holds between threads: two loggers racing for one name, one wins, one is refused."""
    from trundle.logs.writer import Logger

    results: list[object] = []

    def make() -> None:
        try:
            results.append(Logger(tmp_path / "race.mcap", salvage=False))
        except (UserError, FileExistsError) as error:
            results.append(error)

    threads = [threading.Thread(target=make) for _ in range(2)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    loggers = [r for r in results if isinstance(r, Logger)]
    assert len(loggers) == 1
    loggers[0].close()


# ---------------------------------------------------------------- one output helper: whole or nothing


def test_an_output_appears_whole_or_not_at_all(tmp_path) -> None:
    target = tmp_path / "result.txt"
    with writing_file(target) as tmp:
        assert tmp == tmp_path / f".result.txt.{os.getpid()}.partial"
        tmp.write_text("done")
        assert not target.exists()
    assert target.read_text() == "done" and os.listdir(tmp_path) == ["result.txt"]
    with pytest.raises(KeyboardInterrupt), writing_file(tmp_path / "cut.txt") as tmp:
        tmp.write_text("half")
        raise KeyboardInterrupt
    assert os.listdir(tmp_path) == ["result.txt"]
    with (pytest.raises(UserError, match="appeared while it was being written: it is kept"),
          writing_file(tmp_path / "raced.txt") as tmp):
        tmp.write_text("mine")
        (tmp_path / "raced.txt").write_text("theirs")
    assert (tmp_path / "raced.txt").read_text() == "theirs"
    assert sorted(os.listdir(tmp_path)) == ["raced.txt", "result.txt"]
    with pytest.raises(ValueError), writing_files(tmp_path / "a.csv", tmp_path / "b.csv") as (a, b):
        a.write_text("a")
        b.write_text("b")
        raise ValueError("the second result failed")
    assert sorted(os.listdir(tmp_path)) == ["raced.txt", "result.txt"]


def test_a_results_folder_loses_only_what_the_failed_run_wrote(tmp_path) -> None:
    kept = tmp_path / "kept"
    kept.mkdir()
    (kept / "notes.txt").write_text("the user's")
    with pytest.raises(KeyboardInterrupt), writing_folder(kept, empty=False):
        write_text(kept / "report.md", "# half a report")
        raise KeyboardInterrupt
    assert os.listdir(kept) == ["notes.txt"]
    new = tmp_path / "a" / "b" / "new"
    with pytest.raises(DataError), writing_folder(new):
        write_json(new / "report.json", {"x": 1})
        raise DataError("the last step failed")
    assert sorted(os.listdir(tmp_path)) == ["kept"]


def test_json_is_strict_with_non_finite_numbers_as_null(tmp_path) -> None:
    path = write_json(tmp_path / "r.json", {"nan": float("nan"), "inf": np.float32("inf"), "n": np.int64(3),
                                            "a": np.array([1.5, -np.inf]), "t": (1, float("-inf")), "p": tmp_path})
    assert strict_json(path.read_text()) == {"nan": None, "inf": None, "n": 3, "a": [1.5, None], "t": [1, None],
                                             "p": str(tmp_path)}


def strict_json(text: str) -> object:
    """``text`` parsed by a strict parser: NaN, Infinity and -Infinity are refused."""
    def refuse(constant: str) -> object:
        raise ValueError(f"not strict JSON: {constant}")
    return json.loads(text, parse_constant=refuse)
