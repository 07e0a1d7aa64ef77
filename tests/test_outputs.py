"""Outputs are never overwritten and nothing is left behind: a repeated command loses no
recording, a bad URL makes no empty log, a second daemon on the same config writes nothing,
`recover IN DIR` writes into DIR and leaves no temporary file. Every command that writes leaves
nothing under its output's name when it fails or is interrupted after writing began, and says a
read-only folder or a full disk (a small tmpfs mounted for the test) in one line with exit code 1;
every JSON file trundle writes is strict JSON."""

from __future__ import annotations

import dataclasses
import errno
import hashlib
import itertools
import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest

import trundle
from tests.test_daemon import Running, ScriptedDriver, config, wait_for
from trundle.logs.errors import DataError, OutputError, UserError
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

DISK_FAULTS = ("read-only", "full")
CAUSE = {"read-only": "Read-only file system", "full": "No space left on device", "chmod": "Permission denied"}


def _mount(folder: Path, options: str) -> None:
    """A small tmpfs at ``folder`` (mounted by the ``mount`` command), or skip saying why not."""
    result = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(folder)],
                            capture_output=True, text=True)
    if result.returncode:
        pytest.skip(f"cannot mount a tmpfs here ({result.stderr.strip() or result.returncode}): the disk-fault "
                    "tests need root with CAP_SYS_ADMIN")


def _fill(folder: Path) -> None:
    """Fill the filesystem of ``folder`` to the last byte with the file ``filler``."""
    fd = os.open(folder / "filler", os.O_WRONLY | os.O_CREAT)
    try:
        with pytest.raises(OSError) as full:
            while True:
                os.write(fd, b"\0" * 4096)
        assert full.value.errno == errno.ENOSPC
    finally:
        os.close(fd)


@pytest.fixture(params=DISK_FAULTS)
def bad_disk(request, tmp_path) -> Iterator[tuple[Path, str]]:
    """A folder whose filesystem refuses writes: read-only (a tmpfs mounted ``ro``; as another user than
    root, a folder of mode 0o555) or full (a 256 KiB tmpfs filled by ``filler``); and the cause said."""
    folder = tmp_path / "disk"
    folder.mkdir()
    if request.param == "read-only" and os.geteuid() != 0:
        folder.chmod(0o555)
        yield folder, CAUSE["chmod"]
        folder.chmod(0o755)
        return
    if os.geteuid() != 0:
        pytest.skip("a full disk is a small tmpfs, and mounting one needs root")
    _mount(folder, "ro,size=64k" if request.param == "read-only" else "size=256k")
    try:
        if request.param == "full":
            _fill(folder)
        yield folder, CAUSE[request.param]
    finally:
        if subprocess.run(["umount", str(folder)], capture_output=True).returncode:
            subprocess.run(["umount", "-l", str(folder)], check=True)


def left_in(folder: Path) -> list[str]:
    """What is in ``folder`` besides the filler of a full disk, every file below it and hidden ones too."""
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.name != "filler")


def refused(capsys, code: int, cause: str, output: Path) -> None:
    """The command ended with exit code 1 and one line on stderr naming ``output`` and ``cause``."""
    err = capsys.readouterr().err
    assert code == 1, err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    assert f"cannot write {output}" in err and cause in err and "nothing was written" in err, err


@pytest.fixture(scope="module")
def slam_map(tmp_path_factory) -> Path:
    """``trundle slam`` of the demo log: a map folder to localise on and JSON to parse."""
    out = tmp_path_factory.mktemp("slam") / "map"
    assert main(["slam", str(DEMO_LOG), "-o", str(out)]) == 0
    return out


@pytest.fixture(scope="module")
def images(tmp_path_factory) -> tuple[Path, Path]:
    """Two views of one textured scene for ``trundle match``."""
    from tests.feature_scenes import scene

    folder = tmp_path_factory.mktemp("images")
    image = scene(noise=2.0)
    first, second = folder / "a.png", folder / "b.png"
    cv2.imwrite(str(first), image)
    cv2.imwrite(str(second), cv2.warpAffine(image, np.float32([[1, 0, 6], [0, 1, 4]]), image.shape[::-1]))
    return first, second


def breezyslam_dat(path: Path) -> Path:
    path.write_text("".join(" ".join([str(100_000 * k), "0", str(k), str(k)] + ["0"] * 20 + ["900"] * 683) + "\n"
                            for k in range(1, 40)))
    return path


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
    demo = tmp_path / "demo"  # what the user is told is kept stays, with the folder's marker
    with pytest.raises(KeyboardInterrupt), writing_folder(demo, marker=".made-by-us", keep=("run.partial*",)):
        write_text(demo / "report.md", "# half a report")
        write_text(demo / "run.partial.mcap", "the log so far")
        raise KeyboardInterrupt
    assert sorted(os.listdir(demo)) == [".made-by-us", "run.partial.mcap"]


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


def test_every_json_file_trundle_writes_is_strict(slam_map, tmp_path, capsys, monkeypatch) -> None:
    from tests.fleet_logs import robot_log
    from trundle.tools.demo import report as demo_report
    from trundle.tools.fleet.jobs import options_key
    from trundle.tools.fleet.run import FleetRun, write_results
    from trundle.tools.fleet.task import Task, process_log

    assert main(["characterize", str(DEMO_LOG), "--topic", "/scan", "-o", str(tmp_path / "sensor")]) == 0
    log = robot_log(tmp_path / "run1.mcap", "robot-a")
    rows = [process_log(Task(job, str(log), job, str(tmp_path / "fleet"), {}, options_key(job, {})))
            for job in ("slam", "info")]
    fleet = FleetRun("slam", {}, rows, elapsed_s=float("nan"))
    write_results(fleet, tmp_path / "fleet")
    monkeypatch.setattr(demo_report, "report_markdown", lambda report: "# the demo's page\n")  # of a whole report
    demo_report.write_report(tmp_path, {"trajectory": {"ate_m": float("nan")}, "figures": np.array([np.inf, 1.0])})
    files = sorted(slam_map.glob("*.json")) + sorted(tmp_path.rglob("*.json"))
    names = {str(p.relative_to(tmp_path)) for p in files if p.is_relative_to(tmp_path)}
    assert {"report.json", "sensor/report.json", "fleet/run.json", "fleet/slam/report.json",
            "fleet/slam/fleet.json", "fleet/info/fleet.json"} <= names
    for path in files:
        strict_json(path.read_text())
    assert strict_json((tmp_path / "report.json").read_text()) == {"trajectory": {"ate_m": None},
                                                                    "figures": [None, 1.0]}
    capsys.readouterr()
    main(["localize", str(DEMO_LOG), "--map", str(slam_map), "--json"])
    strict_json(capsys.readouterr().out)


# ---------------------------------------------------------------- a failure after writing began leaves nothing


def test_perceive_with_a_bad_detector_parameter_leaves_no_file(tmp_path, capsys) -> None:
    out = tmp_path / "pc7.mcap"
    argv = ["perceive", str(DEMO_LOG), "--pipeline", "features", "--param", "foo=1", "-o", str(out)]
    assert main(argv) == 2
    assert "'foo' is an invalid keyword" in capsys.readouterr().err
    assert os.listdir(tmp_path) == []
    assert main(argv[:4] + argv[6:]) == 0   # the retry is not refused
    assert os.listdir(tmp_path) == ["pc7.mcap"] and LogReader(out).info().complete


@pytest.fixture(scope="module")
def camera_log(tmp_path_factory) -> Path:
    """A camera log of 627 frames, as in the issue: the demo log's 67 JPEG frames again and again at
    3 Hz, with its camera info and mount."""
    from trundle.logs.writer import Logger

    path = tmp_path_factory.mktemp("camera") / "camera.mcap"
    frames = [x.msg for x in LogReader(DEMO_LOG).messages(["/camera/image_raw/compressed"])]
    latched = list(LogReader(DEMO_LOG).raw_messages(["/tf_static", "/camera/camera_info"]))
    start = max(raw.log_time_ns for raw in latched)
    with Logger(path, salvage=False, metadata={"command": "test"}) as logger:
        for raw in latched:
            logger.write_encoded(raw.topic, raw.ros_type, raw.data, raw.log_time_ns, raw.publish_time_ns)
        for k in range(627):
            stamp = start + (k + 1) * 1_000_000_000 // 3
            logger.write("/camera/image_raw/compressed", dataclasses.replace(frames[k % len(frames)], stamp_ns=stamp),
                         stamp)
    return path


def test_perceive_stopped_by_ctrl_c_leaves_no_file(camera_log, tmp_path) -> None:
    """Ctrl-C (SIGINT to the command's own process) once frames are being written: no pc.mcap, no partial file."""
    out = tmp_path / "pc.mcap"
    perceive = subprocess.Popen([sys.executable, "-m", "trundle.tools.cli", "perceive", str(camera_log),
                                 "--pipeline", "markers", "-o", str(out)],
                                env={**os.environ, "PYTHONPATH": str(Path(trundle.__file__).parent.parent)},
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        writing = tmp_path / f".pc.mcap.{perceive.pid}.partial.active"  # the output helper's name, the logger's suffix
        wait_for(lambda: writing.exists() and writing.stat().st_size > 1_000_000, timeout_s=60)
        perceive.send_signal(signal.SIGINT)
        printed, said = perceive.communicate(timeout=60)
    finally:
        perceive.kill()
    assert perceive.returncode == 130 and said == "trundle perceive: interrupted\n", said
    assert "wrote" not in printed
    assert os.listdir(tmp_path) == []


def interrupt_after(monkeypatch, owner: object, name: str, calls: int) -> None:
    """Make ``owner.name`` raise KeyboardInterrupt (Ctrl-C) on its ``calls``-th call."""
    real = getattr(owner, name)
    count = itertools.count(1)

    def cut(*args, **kwargs):
        if next(count) == calls:
            raise KeyboardInterrupt
        return real(*args, **kwargs)
    monkeypatch.setattr(owner, name, cut)


@pytest.mark.parametrize("form", ["csv", "ndjson"])
def test_export_interrupted_leaves_no_file(tmp_path, capsys, monkeypatch, form) -> None:
    import trundle.tools.cli.export as export

    interrupt_after(monkeypatch, export, "flatten" if form == "csv" else "_plain_message", 1350)
    assert main(["export", str(DEMO_LOG), "--topic", "/odom", "--format", form, "-o", str(tmp_path / "o")]) == 130
    assert capsys.readouterr().err == "trundle export: interrupted\n"
    assert os.listdir(tmp_path) == []


def test_recover_inject_faults_and_import_interrupted_leave_no_file(tmp_path, capsys, monkeypatch) -> None:
    import trundle.logs.importers.breezyslam as breezyslam
    import trundle.logs.recover as recover_module

    interrupt_after(monkeypatch, recover_module, "_register", 3)
    assert main(["recover", str(DEMO_LOG), str(tmp_path / "r.mcap")]) == 130
    interrupt_after(monkeypatch, recover_module, "_register", 3)
    assert main(["inject-faults", str(DEMO_LOG), "--slip", "5:2:0.3", "-o", str(tmp_path / "f.mcap")]) == 130
    dat = breezyslam_dat(tmp_path.parent / f"{tmp_path.name}-run.dat")
    real = breezyslam.messages

    def cut(lines):
        yield from itertools.islice(real(lines), 30)
        raise KeyboardInterrupt
    monkeypatch.setattr(breezyslam, "messages", cut)
    assert main(["import", "breezyslam", str(dat), "-o", str(tmp_path / "i.mcap")]) == 130
    assert capsys.readouterr().err.count("interrupted\n") == 3
    assert os.listdir(tmp_path) == []


def test_import_with_a_missing_reference_writes_neither_file(tmp_path, capsys) -> None:
    from tests.test_import_mrclam import _folder

    folder = _folder(tmp_path, "".join(f"{100 + 0.5 * k:.3f} 0.2 0.5\n" for k in range(5)), "100.750 18 2.0 0.1\n")
    out = tmp_path / "out"
    out.mkdir()
    assert main(["import", "mrclam", str(folder), "--robot", "2", "-o", str(out / "r2.mcap"),
                 "--reference", str(out / "truth.csv")]) == 2
    assert "no Robot2_Groundtruth.dat" in capsys.readouterr().err
    assert os.listdir(out) == []


@pytest.mark.parametrize("fault", ["Ctrl-C", "name taken"])
def test_localize_and_match_stopped_while_writing_leave_nothing_half_written(fault, slam_map, images, tmp_path,
                                                                             capsys, monkeypatch) -> None:
    """Ctrl-C, or another program making a file of the output's name, at the last moment: the result
    is whole under its temporary name, not yet under its own. Nothing of the run stays; the other
    program's file is kept and said."""
    import trundle.logs.outputs as outputs

    real = outputs._install

    def at_install(tmp: Path, final: Path, replace: bool) -> None:
        assert tmp.stat().st_size > 0 and not final.exists()
        if fault == "Ctrl-C":
            raise KeyboardInterrupt
        final.write_text("theirs")
        real(tmp, final, replace)
    monkeypatch.setattr(outputs, "_install", at_install)
    poses, picture = tmp_path / "poses.csv", tmp_path / "matches.png"
    for argv, out in ((["localize", str(DEMO_LOG), "--map", str(slam_map), "-o", str(poses)], poses),
                      (["match", *map(str, images), "--features", "orb", "--draw", str(picture)], picture)):
        code = main(argv)
        err = capsys.readouterr().err
        if fault == "Ctrl-C":
            assert (code, err) == (130, f"trundle {argv[0]}: interrupted\n")
        else:
            assert (code, err) == (2, f"trundle {argv[0]}: {out} appeared while it was being written: it is kept, "
                                      "and this result was not written (run again with another name)\n")
            assert out.read_text() == "theirs"
    assert sorted(os.listdir(tmp_path)) == ([] if fault == "Ctrl-C" else ["matches.png", "poses.csv"])


def test_slam_interrupted_while_writing_leaves_no_folder(tmp_path, capsys, monkeypatch) -> None:
    import trundle.tools.jobs.slam as slam_job

    interrupt_after(monkeypatch, slam_job, "write_log", 1)
    assert main(["slam", str(DEMO_LOG), "-o", str(tmp_path / "new" / "map")]) == 130
    assert os.listdir(tmp_path) == []


def test_characterize_failing_while_writing_keeps_only_what_was_there(tmp_path, capsys, monkeypatch) -> None:
    import trundle.tools.jobs.characterize as characterize_job

    out = tmp_path / "sensor"
    out.mkdir()
    (out / "notes.md").write_text("the user's notes")
    interrupt_after(monkeypatch, characterize_job, "markdown", 1)
    assert main(["characterize", str(DEMO_LOG), "--topic", "/scan", "-o", str(out)]) == 130
    assert os.listdir(out) == ["notes.md"]


def test_record_with_no_working_device_keeps_no_log(tmp_path, capsys) -> None:
    out = tmp_path / "run.mcap"
    assert main(["record", "--lrf", "scip2:///dev/null", "--duration", "1", "-o", str(out)]) == 1
    captured = capsys.readouterr()
    assert "wrote" not in captured.out
    assert captured.err.endswith(f"trundle record: no device recorded anything: no log was kept ({out} not "
                                 "written)\n"), captured.err
    assert os.listdir(tmp_path) == []


# ---------------------------------------------------------------- read-only folders and full disks: one line, exit 1


def test_record_on_a_bad_disk(bad_disk, capsys) -> None:
    disk, cause = bad_disk
    before = left_in(disk)
    code = main(["record", "--lrf", "scip2:///dev/null", "--duration", "1", "-o", str(disk / "run.mcap")])
    refused(capsys, code, cause, disk / "run.mcap")
    assert left_in(disk) == before


@pytest.mark.parametrize("command", ["export", "perceive", "recover", "inject-faults", "import", "replay"])
def test_a_log_writing_command_on_a_bad_disk(bad_disk, command, tmp_path, capsys) -> None:
    disk, cause = bad_disk
    before = left_in(disk)
    out = disk / ("out.csv" if command == "export" else "out.mcap")
    argv = {"export": ["export", str(DEMO_LOG), "--topic", "/odom", "-o", str(out)],
            "perceive": ["perceive", str(DEMO_LOG), "--pipeline", "markers", "-o", str(out)],
            "recover": ["recover", str(DEMO_LOG), str(out)],
            "inject-faults": ["inject-faults", str(DEMO_LOG), "--slip", "5:2:0.3", "-o", str(out)],
            "import": ["import", "breezyslam", str(breezyslam_dat(tmp_path / "run.dat")), "-o", str(out)],
            "replay": ["replay", str(DEMO_LOG), "--rate", "0", "--end", "2", "-o", str(out)]}[command]
    refused(capsys, main(argv), cause, out)
    assert left_in(disk) == before


def test_slam_on_a_bad_disk(bad_disk, capsys) -> None:
    disk, cause = bad_disk
    before = left_in(disk)
    code = main(["slam", str(DEMO_LOG), "-o", str(disk / "map")])
    refused(capsys, code, cause, disk / "map")
    assert left_in(disk) == before


def test_characterize_localize_and_match_on_a_bad_disk(bad_disk, slam_map, images, capsys) -> None:
    disk, cause = bad_disk
    before = left_in(disk)
    code = main(["characterize", str(DEMO_LOG), "--topic", "/scan", "-o", str(disk / "sensor")])
    refused(capsys, code, cause, disk / "sensor")
    code = main(["localize", str(DEMO_LOG), "--map", str(slam_map), "-o", str(disk / "poses.csv")])
    refused(capsys, code, cause, disk / "poses.csv")
    code = main(["match", *map(str, images), "--features", "orb", "--draw", str(disk / "matches.png")])
    refused(capsys, code, cause, disk / "matches.png")
    assert left_in(disk) == before


def test_fleet_and_demo_on_a_bad_disk(bad_disk, capsys) -> None:
    """Both said before their long work (Ray's start, the recording); the folders they made go again."""
    disk, cause = bad_disk
    refused(capsys, main(["fleet", "info", str(DEMO_LOG), "-o", str(disk / "fleet")]), cause, disk / "fleet")
    refused(capsys, main(["demo", "-o", str(disk / "demo")]), cause, disk / "demo")
    assert left_in(disk) == []


@pytest.mark.parametrize("job", ["slam", "info"])  # info: the job itself writes nothing, its report.json fails
@pytest.mark.parametrize("bad_disk", ["full"], indirect=True)
def test_a_fleet_task_and_its_results_on_a_full_disk(bad_disk, job, tmp_path) -> None:
    """A failed task's row says the cause; the results files are refused whole (Ray's own start is left out)."""
    from tests.fleet_logs import robot_log
    from trundle.tools.fleet.jobs import options_key
    from trundle.tools.fleet.run import FleetRun, write_results
    from trundle.tools.fleet.task import Task, process_log

    disk, _ = bad_disk
    log = robot_log(tmp_path / "run1.mcap", "robot-a")
    (disk / ".fleet").mkdir()  # what the run's lock made
    row = process_log(Task(job, str(log), "run1", str(disk), {}, options_key(job, {})))
    assert row["status"] == "failed" and "No space left on device" in row["error"], row
    with pytest.raises(OutputError, match=f"cannot write {disk / 'results.csv'}: No space left on device"):
        write_results(FleetRun(job, {}, [row]), disk)
    assert [name for name in left_in(disk) if not (disk / name).is_dir()] == []  # the run's state folders, empty
