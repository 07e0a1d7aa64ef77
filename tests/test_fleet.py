"""`trundle fleet` pieces without a cluster (job options, names, rows, one log's task, results,
summary) and whole runs on a local Ray: per-robot figures, URLs, Ctrl-C, the command's errors."""

from __future__ import annotations

import csv
import json
import math
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from tests.fleet_logs import START_NS, corrupt_log, robot_log
from trundle import __version__
from trundle.logs.errors import UserError
from trundle.tools.cli.main import main
from trundle.tools.fleet import jobs
from trundle.tools.fleet.inputs import expand, folder_names
from trundle.tools.fleet.jobs import options_key, parse_options
from trundle.tools.fleet.results import write_csv, write_parquet
from trundle.tools.fleet.rows import COLUMNS, flatten
from trundle.tools.fleet.summary import failed_checks, headline, markdown, summary_figure
from trundle.tools.fleet.task import Task, process_log, read_marker, robot_name

TRUNDLE = str(Path(sys.executable).with_name("trundle"))
HOUR_NS = 3600 * 10**9


@pytest.fixture(scope="module")
def log(tmp_path_factory) -> Path:
    return robot_log(tmp_path_factory.mktemp("logs") / "run1.mcap", "robot-a")


# ---------------------------------------------------------------- job options


def test_job_options_are_converted_by_the_job_functions_type_hints(tmp_path) -> None:
    config = tmp_path / "robot.toml"
    config.write_text("[slam.loop_closure]\nenabled = false\n")
    assert parse_options("slam", [f"config={config}", "local_only=yes"]) == \
        {"config": {"slam": {"loop_closure": {"enabled": False}}}, "local_only": True}
    assert parse_options("characterize", ["topic=/scan", "beam=3", "stated_min=0.02", "bits=12"]) == \
        {"topic": "/scan", "beam": 3, "stated_min": 0.02, "bits": 12}
    assert parse_options("characterize", ["topic=/scan", "beam=all"])["beam"] == "all"
    os.chdir(tmp_path)
    (tmp_path / "map").mkdir()
    assert parse_options("localize", ["map_path=map", "max_range_m=12"]) == \
        {"map_path": str(tmp_path / "map"), "max_range_m": 12.0}
    assert parse_options("perceive", ["pipeline=markers", "topics=/a,/b", 'options={"marker_size": 0.1}']) == \
        {"pipeline": "markers", "topics": ["/a", "/b"], "options": {"marker_size": 0.1}}
    assert parse_options("info", []) == {}


@pytest.mark.parametrize("job, items, message", [
    ("slam", ["loops=1"],
     "slam has no option 'loops' (options: config=None (config), local_only=False (bool), estimator=None (text), "
     "continue_from=None (path), freeze=False (bool), allow_new_area=False (bool))"),
    ("characterize", [], "characterize needs topic=... in --job-options"),
    ("localize", ["config={}"], "localize needs map_path=..."),
    ("slam", ["local_only=maybe"], "slam option local_only = 'maybe': expected true or false"),
    ("characterize", ["topic=/scan", "bits=1e3"], "characterize option bits = '1e3': expected a whole number"),
    ("characterize", ["topic=/scan", "min_still_s=inf"],
     "characterize option min_still_s = 'inf': expected a finite number"),
    ("characterize", ["topic=/scan", "bits=1.5"], "characterize option bits = '1.5': expected a whole number"),
    ("characterize", ["topic=/scan", "min_still_s=x"], "characterize option min_still_s = 'x': expected a number"),
    ("characterize", ["topic=/scan", "min_still_s=nan"],
     "characterize option min_still_s = 'nan': expected a finite number"),
    ("slam", ["local_only=1", "local_only=0"], "slam option local_only given twice"),
    ("slam", ["local_only"], "--job-options needs KEY=VALUE, got 'local_only'"),
    ("localize", ["map_path=/no/such/map"], "localize option map_path: no such file or folder: /no/such/map"),
    ("slam", ["config=/no/such.toml"], "config file not found: /no/such.toml"),
    ("slam", ['config={"slam": {"submaps": {"resolution": 0}}}'],
     "slam option config: slam.submaps.resolution = 0: expected a number >= 0.001"),
    ("slam", ["config={1: 2}"], "slam option config: invalid JSON"),
    ("slam", ["estimator=nope"],
     "slam option estimator = 'nope': expected one of graph, grid, grid-landmarks, ekf, landmark-graph"),
    ("perceive", ["pipeline=color", "options=[1]"], "config file not found: [1]"),
    ("walk", [], "unknown job 'walk'"),
])
def test_bad_job_options_are_one_clear_error(job, items, message) -> None:
    with pytest.raises(UserError, match=None) as error:
        parse_options(job, items)
    assert message in str(error.value)


@given(st.floats(allow_nan=False, allow_infinity=False), st.integers(-10**12, 10**12))
def test_numbers_round_trip_through_their_text(x: float, n: int) -> None:
    options = parse_options("characterize", ["topic=/scan", f"stated_min={x!r}", f"bits={n}", f"beam={n}"])
    assert options["stated_min"] == x and options["bits"] == n and options["beam"] == n


@given(st.text(min_size=1).filter(lambda t: "\0" not in t))
def test_a_value_keeps_every_equals_sign_after_the_first(topic: str) -> None:
    assert parse_options("characterize", [f"topic={topic}=x"])["topic"] == f"{topic}=x"


def test_the_options_key_follows_options_files_and_version(tmp_path, monkeypatch) -> None:
    (tmp_path / "map").mkdir()
    (tmp_path / "map" / "map.yaml").write_text("resolution: 0.05\n")
    options = parse_options("localize", [f"map_path={tmp_path / 'map'}"])
    key = options_key("localize", options)
    assert options_key("localize", options) == key
    assert options_key("localize", {**options, "max_range_m": 5.0}) != key
    (tmp_path / "map" / "map.yaml").write_text("resolution: 0.10\n")   # a new map: the results are stale
    assert options_key("localize", options) != key
    changed = options_key("localize", options)
    monkeypatch.setattr(jobs, "__version__", "99.0")
    assert options_key("localize", options) != changed


# ---------------------------------------------------------------- names and rows


def test_output_folders_are_the_log_names_with_parents_only_where_names_collide() -> None:
    assert folder_names(
        ["/d/robot1/run.mcap", "/d/robot2/run.mcap", "/d/robot1/x.mcap.active", "s3://b/robot1/y.mcap"]
    ) == ["robot1__run", "robot2__run", "x", "y"]
    assert folder_names(["/a/r/run.mcap", "/b/r/run.mcap"]) == ["a__r__run", "b__r__run"]


@given(st.lists(st.lists(st.sampled_from(["a", "b", "c", "run", "r1"]), min_size=1, max_size=4), min_size=1,
                max_size=12, unique_by=tuple))
def test_output_folder_names_are_distinct_and_plain_stems_when_the_stem_is_unique(paths: list[list[str]]) -> None:
    sources = ["/" + "/".join(p) + ".mcap" for p in paths]
    names = folder_names(sources)
    assert len(set(names)) == len(names) and all("/" not in n for n in names)
    stems = [p[-1] for p in paths]
    for name, stem in zip(names, stems, strict=True):
        assert name.endswith(stem)
        if stems.count(stem) == 1:
            assert name == stem


scalars = st.one_of(st.none(), st.booleans(), st.integers(), st.floats(allow_nan=False), st.text(max_size=5))
reports = st.recursive(st.dictionaries(st.text("abcxyz", min_size=1, max_size=3), scalars, max_size=4),
                       lambda inner: st.dictionaries(st.text("abcxyz", min_size=1, max_size=3),
                                                     st.one_of(inner, scalars), min_size=1, max_size=4), max_leaves=12)


@given(reports)
def test_flatten_keeps_every_leaf_under_its_dotted_path(report: dict) -> None:
    flat = flatten(report)

    def leaves(d, prefix=""):
        for k, v in d.items():
            if isinstance(v, dict) and v:
                yield from leaves(v, f"{prefix}{k}.")
            else:
                yield f"{prefix}{k}", v
    expected = dict(leaves(report))
    assert set(flat) == set(expected)
    for key, value in expected.items():
        if isinstance(value, float) and not math.isfinite(value):
            assert flat[key] is None
        elif value == {}:
            assert flat[key] == "{}"
        else:
            assert flat[key] == value


def test_flatten_renames_figures_that_clash_with_a_column_and_drops_the_log() -> None:
    assert flatten({"log": "/x.mcap", "error": "crc", "status": {"ok": True}, "seconds": 3, "bins": [1, 2]}) == \
        {"report.error": "crc", "status.ok": True, "report.seconds": 3, "bins": "[1, 2]"}


# ---------------------------------------------------------------- one log's task (no Ray)


def task(log: Path, out: Path, job: str = "slam", options: dict | None = None, **kw) -> Task:
    options = options or {}
    return Task(job, str(log), log.stem, str(out), options, options_key(job, options), **kw)


def test_a_log_is_computed_once_then_skipped_while_input_and_options_are_the_same(tmp_path) -> None:
    log = robot_log(tmp_path / "run1.mcap", "robot-a")
    out = tmp_path / "out"
    first = process_log(task(log, out))
    assert first["status"] == "ok" and first["error"] == "" and first["robot"] == "robot-a"
    assert first["size_bytes"] == log.stat().st_size and first["scans"] == 20
    assert first["log_start"] == "2026-05-28T20:26:40.000+00:00" and first["log_duration_s"] == pytest.approx(10.0)
    import hashlib
    assert first["sha256"] == hashlib.sha256(log.read_bytes()).hexdigest()
    marker = read_marker(out / "run1")
    assert marker["row"] == first and marker["version"] == __version__
    assert json.loads((out / "run1" / "report.json").read_text())["scans"] == 20
    assert process_log(task(log, out)) == {**first, "status": "skipped"}

    os.utime(log, ns=(time.time_ns(), time.time_ns() + 10**9))   # touched, same bytes: hashed again, still done
    assert process_log(task(log, out))["status"] == "skipped"
    assert read_marker(out / "run1")["identity"].endswith(str(log.stat().st_mtime_ns))
    assert process_log(task(log, out, options={"local_only": True}))["status"] == "ok"   # other options
    assert process_log(task(log, out, options={"local_only": True}, force=True))["status"] == "ok"
    log.unlink()
    robot_log(log, "robot-a", noise_m=0.02)                                              # other bytes
    again = process_log(task(log, out, options={"local_only": True}))
    assert again["status"] == "ok" and again["sha256"] != first["sha256"]
    assert not list((out / ".fleet" / "work").iterdir())


def test_a_failing_log_fails_its_row_alone_and_keeps_the_last_complete_result(tmp_path, monkeypatch) -> None:
    log = robot_log(tmp_path / "run1.mcap", "robot-a")
    out = tmp_path / "out"
    assert process_log(task(log, out))["status"] == "ok"
    before = sorted(p.name for p in (out / "run1").iterdir())
    corrupt_log(log, log)
    row = process_log(task(log, out))
    assert (
        row["status"] == "failed"
        and row["error"] == f"{log} has no topic /scan (sensor_msgs/msg/LaserScan; topics: none)"
    )
    assert sorted(p.name for p in (out / "run1").iterdir()) == before       # the old result is still whole
    assert f"{log}\n" in (out / ".fleet" / "errors" / "run1.txt").read_text()

    def broken(job):
        def run(*args, **kwargs):
            raise ZeroDivisionError("float division by zero")
        return run
    monkeypatch.setattr(jobs, "job_function", broken)
    other = robot_log(tmp_path / "run2.mcap", "robot-a")
    row = process_log(task(other, out))
    assert row["error"] == "ZeroDivisionError: float division by zero" and not (out / "run2").exists()
    assert "Traceback" in (out / ".fleet" / "errors" / "run2.txt").read_text()
    assert process_log(task(tmp_path / "gone.mcap", out))["error"].startswith("no such file on this node")


DEMO = Path(__file__).parent / "data" / "demo_short" / "demo.mcap"


def test_every_job_runs_through_a_task_with_its_outputs_in_the_logs_folder(tmp_path) -> None:
    sim = robot_log(tmp_path / "sim.mcap", "robot-a")
    demo = tmp_path / "demo.mcap"
    demo.write_bytes(DEMO.read_bytes())
    out = tmp_path / "out"
    cases = {  # job -> (log, options, the files its folder must hold besides report.json and fleet.json)
        "info": (demo, {}, []),
        "slam": (sim, {}, ["map.yaml", "map.pgm", "trajectory.csv", "slam.mcap"]),
        "characterize": (demo, {"topic": "/scan"}, ["report.md"]),
        "perceive": (demo, {"pipeline": "markers"}, ["perceive.mcap"]),
    }
    for job, (log, options, files) in cases.items():
        row = process_log(Task(job, str(log), job, str(out), options, options_key(job, options)))
        assert row["status"] == "ok", (job, row["error"])
        for name in files + ["report.json", "fleet.json"]:
            assert (out / job / name).is_file(), (job, name)
    assert json.loads((out / "info" / "report.json").read_text())["topics"]["/scan"]["count"] == 880
    options = {"map_path": str(out / "slam")}
    row = process_log(Task("localize", str(sim), "localize", str(out), options, options_key("localize", options)))
    assert row["status"] == "ok" and row["scans"] == 20 and (out / "localize" / "trajectory.csv").is_file()


def test_a_worker_with_another_trundle_version_refuses(log, tmp_path) -> None:
    row = process_log(task(log, tmp_path, version="0.0.1"))
    assert row["status"] == "failed" and f"this worker has trundle {__version__}, the driver 0.0.1" in row["error"]


# ---------------------------------------------------------------- results and summary

ROWS = [
    {"log": "/l/a.mcap", "name": "a", "status": "ok", "error": "", "seconds": 1.5, "robot": "r1",
     "log_start": "2026-05-28T20:00:00.000+00:00", "scans": 10, "real_time_factor": 20.0, "consistent": True,
     "config.voxel_m": 0.05},
    {"log": "/l/b.mcap", "name": "b", "status": "ok", "error": "", "seconds": 2, "robot": "r2",
     "log_start": "2026-05-29T20:00:00.000+00:00", "scans": 12, "real_time_factor": 15.5, "consistent": False,
     "config.voxel_m": 0.05},
    {"log": "/l/c.mcap", "name": "c", "status": "failed", "error": "no LaserScan topic", "seconds": 0.1},
]


def test_results_csv_and_parquet_hold_every_row_and_column(tmp_path) -> None:
    import pyarrow.parquet as pq

    write_csv(ROWS, tmp_path / "results.csv")
    with open(tmp_path / "results.csv", newline="") as f:
        table = list(csv.DictReader(f))
    header = list(table[0])
    assert header[:len(COLUMNS)] == list(COLUMNS) and header[len(COLUMNS):] == \
        ["scans", "real_time_factor", "consistent", "config.voxel_m"]
    assert [r["status"] for r in table] == ["ok", "ok", "failed"] and table[2]["scans"] == ""
    parquet = pq.read_table(write_parquet(ROWS, tmp_path / "results.parquet"))
    assert parquet.column_names == header
    types = {name: str(parquet.schema.field(name).type) for name in header}
    assert types["scans"] == "int64" and types["seconds"] == "double" and types["consistent"] == "bool"
    assert parquet.column("seconds").to_pylist() == [1.5, 2.0, 0.1] and parquet.column("scans").to_pylist() == [
        10,
        12,
        None,
    ]


def test_without_pyarrow_there_is_no_parquet_file(tmp_path, monkeypatch) -> None:
    monkeypatch.setitem(sys.modules, "pyarrow", None)
    assert write_parquet(ROWS, tmp_path / "results.parquet") is None and not (tmp_path / "results.parquet").exists()


def test_summary_names_failures_failed_checks_and_per_robot_figures() -> None:
    done = ROWS[:2]
    assert headline("slam", done) == ["real_time_factor", "scans"]   # preferred first; config.* never
    assert failed_checks(done) == {"consistent": ["/l/b.mcap"]}
    page = markdown("slam", ROWS, {"elapsed_s": 3.0, "wall_s": 10.6, "ray_start_s": 7.7, "cpus": 2,
                                   "logs_per_minute": 60.0, "options": {}}, "summary.png")
    assert ("2 ok, 1 failed, 0 skipped, 0 cancelled in 10.6 s (Ray's start 7.7 s; the logs 3.0 s on 2 CPUs, "
            "60.0 logs per minute)") in page
    assert "| /l/c.mcap | failed | no LaserScan topic |" in page
    assert "| consistent | 1 of 2 | /l/b.mcap |" in page
    assert "| r1 | 1 | 0 | 20 | 10 |" in page and "| r2 | 1 | 0 | 15.5 | 12 |" in page


def test_summary_takes_no_median_of_stamps_and_no_latched_topic_for_a_failed_check() -> None:
    rows = [dict(ROWS[0], start_ns=1, end_ns=5, **{"topics./scan.latched": False, "topics./tf_static.latched": True}),
            dict(ROWS[1], start_ns=2, end_ns=9, **{"topics./scan.latched": False})]
    assert headline("slam", rows) == ["real_time_factor", "scans"]
    assert failed_checks(rows) == {"consistent": ["/l/b.mcap"]}
    page = markdown("slam", rows, {}, None)
    assert "latched" not in page and "start_ns" not in page


def test_summary_picture_plots_over_start_time_or_over_the_logs_when_a_start_is_no_clock_time() -> None:
    figure = summary_figure("slam", ROWS[:2])
    assert figure is not None
    axes = figure.axes
    assert [ax.get_ylabel() for ax in axes] == ["real_time_factor", "scans"]
    assert axes[0].get_title() == "trundle fleet slam: figures per log over the log's start time (UTC)"
    assert axes[-1].get_xlabel() == "log start (UTC)"
    assert [t.get_text() for t in axes[0].get_legend().get_texts()] == ["r1", "r2"]
    imported = [dict(ROWS[0], log_start="1970-01-01T00:00:01.000+00:00", robot="imported carmen"), ROWS[1]]
    figure = summary_figure("slam", imported)
    assert figure is not None
    assert figure.axes[0].get_title().startswith("trundle fleet slam: figures per log (in the order given")
    assert figure.axes[-1].get_xlabel() == "log"
    assert [t.get_text() for t in figure.axes[-1].get_xticklabels()] == ["a", "b"]
    assert [t.get_text() for t in figure.axes[0].get_legend().get_texts()] == ["imported carmen", "r2"]


@pytest.mark.parametrize(("record", "robot"), [
    ({"robot": '{"name": "rover-3"}', "host": "vm", "command": "daemon"}, "rover-3"),
    ({"command": "import carmen", "host": "vm"}, "imported carmen"),
    ({"command": "record", "host": "rover-7"}, "rover-7"),
    ({}, ""),
])
def test_a_logs_robot_is_its_robots_name_an_imported_dataset_or_the_recording_host(record, robot) -> None:
    assert robot_name({"trundle": record}) == robot


# ---------------------------------------------------------------- inputs


def test_folders_globs_and_urls_name_logs_once_and_never_the_output(tmp_path) -> None:
    for name in ("r1/a.mcap", "r1/b.mcap", "r2/deep/c.mcap", "r2/notes.txt", "out/r1__a/slam.mcap"):
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_bytes(b"x")
    out = tmp_path / "out"
    assert expand([str(tmp_path)], exclude=out) == [
        str(tmp_path / p) for p in ("r1/a.mcap", "r1/b.mcap", "r2/deep/c.mcap")
    ]
    assert expand([str(tmp_path / "**" / "c.mcap"), str(tmp_path / "r2")], exclude=out) == [
        str(tmp_path / "r2/deep/c.mcap")
    ]
    assert expand([f"file://{tmp_path}/r1/*.mcap"]) == [f"file://{tmp_path}/r1/a.mcap", f"file://{tmp_path}/r1/b.mcap"]
    with pytest.raises(UserError, match="no log matches .*nothing"):
        expand([str(tmp_path / "nothing*.mcap")])
    with pytest.raises(UserError, match="cannot open nosuch://x"):
        expand(["nosuch://x/y.mcap"])


# ---------------------------------------------------------------- the command


def test_trundle_help_imports_no_ray_and_fleet_help_lists_every_jobs_options() -> None:
    code = ("import sys\nfrom trundle.tools.cli.main import main\n"
            "try:\n    main(sys.argv[1:])\nexcept SystemExit:\n    pass\nprint('ray' in sys.modules)")
    top = subprocess.run([sys.executable, "-c", code, "--help"], capture_output=True, text=True, check=True)
    assert "fleet" in top.stdout and top.stdout.strip().endswith("False")
    fleet = subprocess.run([sys.executable, "-c", code, "fleet", "--help"], capture_output=True, text=True, check=True)
    assert fleet.stdout.strip().endswith("False")
    assert "characterize  topic=... (text), reference=None (path), beam='all' (int-or-text)" in fleet.stdout
    assert "slam          config=None (config), local_only=False (bool), estimator=None (text)" in fleet.stdout


def test_command_errors_are_one_line(tmp_path, capsys, monkeypatch, log) -> None:
    assert main(["fleet", "slam", str(tmp_path / "none*.mcap"), "-o", str(tmp_path / "o")]) == 2
    assert capsys.readouterr().err == f"trundle fleet: no log matches {tmp_path / 'none*.mcap'}\n"
    assert main(["fleet", "characterize", str(log), "-o", str(tmp_path / "o")]) == 2
    assert capsys.readouterr().err.startswith("trundle fleet: characterize needs topic=... in --job-options")
    assert main(["fleet", "slam", str(log), "-o", str(tmp_path / "o"), "--job-options", "estimator=nope"]) == 2
    assert capsys.readouterr().err == ("trundle fleet: slam option estimator = 'nope': expected one of graph, grid, "
                                       "grid-landmarks, ekf, landmark-graph\n")
    assert not (tmp_path / "o").exists()   # refused before Ray started or anything was written
    assert main(["fleet", "info", str(log), "-o", str(tmp_path / "o"), "--retries", "-1"]) == 2
    assert (
        capsys.readouterr().err
        == "trundle fleet: argument --retries: -1 must be at least 0 (see trundle fleet --help)\n"
    )
    import socket
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]          # closed again: nothing listens there
    assert main(["fleet", "info", str(log), "-o", str(tmp_path / "o"), "--address", f"127.0.0.1:{port}"]) == 2
    assert capsys.readouterr().err.startswith(f"trundle fleet: cannot reach the Ray cluster at 127.0.0.1:{port}: ")
    (tmp_path / "file").write_text("")
    assert main(["fleet", "info", str(log), "-o", str(tmp_path / "file")]) == 2
    assert capsys.readouterr().err == f"trundle fleet: output {tmp_path / 'file'} is a file, not a folder\n"
    import importlib.util
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "ray" else real(name, *a))
    assert main(["fleet", "info", str(log), "-o", str(tmp_path / "o")]) == 2
    assert capsys.readouterr().err == "trundle fleet: trundle fleet needs Ray: pip install 'trundle[fleet]'\n"


def _descendants(pid: int) -> set[int]:
    found, todo = set(), [pid]
    while todo:
        p = todo.pop()
        try:
            with open(f"/proc/{p}/task/{p}/children") as f:
                children = {int(c) for c in f.read().split()}
        except OSError:
            children = set()
        todo += list(children - found)
        found |= children
    return found


def _listening(pids: set[int]) -> list[str]:
    out = subprocess.run(["ss", "-Hltnp"], capture_output=True, text=True).stdout
    return [line.split()[3] for line in out.splitlines() if any(f"pid={p}," in line for p in pids)]


def test_characterize_over_two_robots_on_a_local_ray_gives_per_robot_noise(tmp_path) -> None:
    logs = tmp_path / "logs"
    for i in range(2):
        robot_log(logs / "r1" / f"still{i}.mcap", "robot-1", START_NS + i * HOUR_NS, still=True, noise_m=0.01)
        robot_log(logs / "r2" / f"still{i}.mcap", "robot-2", START_NS + i * HOUR_NS, still=True, noise_m=0.03)
    out = tmp_path / "out"
    url = f"file://{logs}/r2/still1.mcap"
    run = subprocess.run([TRUNDLE, "fleet", "characterize", str(logs / "r1"), str(logs / "r2" / "still0.mcap"), url,
                          "-o", str(out), "--num-cpus", "1", "--job-options", "topic=/scan"],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert run.stderr.startswith("starting a local Ray (1 CPU) ...\nRay ready in ")
    assert re.search(r"^4 logs: 4 ok in [\d.]+ s \(Ray's start [\d.]+ s; the logs [\d.]+ s on 1 CPU, "
                     r"[\d.]+ logs/min\)$", run.stdout, re.MULTILINE), run.stdout
    with open(out / "results.csv", newline="") as f:
        table = list(csv.DictReader(f))
    assert [r["name"] for r in table] == ["r1__still0", "r1__still1", "r2__still0", "r2__still1"]
    assert table[3]["log"] == url and table[3]["node"] == "127.0.0.1"
    noise = {r["name"]: float(r["static.beam_noise_std_median"]) for r in table}
    assert all(
        abs(noise[f"r1__still{i}"] - 0.01) < 0.002 and abs(noise[f"r2__still{i}"] - 0.03) < 0.005 for i in range(2)
    )
    for r in table:
        assert json.loads((out / r["name"] / "report.json").read_text())["sensor"] == "laser"
        assert (out / r["name"] / "report.md").is_file()
    summary = (out / "summary.md").read_text()
    assert "| robot-1 | 2 |" in summary and "| robot-2 | 2 |" in summary and "static.beam_noise_std_median" in summary
    assert (out / "summary.png").stat().st_size > 10_000
    import pyarrow.parquet as pq
    assert pq.read_table(out / "results.parquet").column("static.beam_noise_std_median").to_pylist() == \
        pytest.approx([noise[r["name"]] for r in table])
    assert json.loads((out / "run.json").read_text())["ok"] == 4


def test_ctrl_c_cancels_the_rest_leaves_complete_results_and_a_rerun_finishes(tmp_path) -> None:
    # the first log short, the others long enough that Ctrl-C, sent the moment the first is done,
    # finds them still to do on a loaded machine as on a quiet one
    logs = [robot_log(tmp_path / "logs" / f"run{i}.mcap", "robot-a", START_NS + i * HOUR_NS,
                      scans=40 if i == 0 else 160, offset=12 * i) for i in range(5)]
    out = tmp_path / "out"
    argv = [TRUNDLE, "fleet", "slam", str(tmp_path / "logs"), "-o", str(out), "--num-cpus", "1"]
    run = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    line = ""
    while not line.startswith("Ray ready in "):
        line = run.stderr.readline()
        assert line or run.poll() is None, run.stderr.read()
    addresses = _listening(_descendants(run.pid))  # Ray's own ports, while it works on the first log
    assert addresses and all(a.startswith(("127.0.0.1:", "[::ffff:127.0.0.1]:")) for a in addresses), addresses
    while not line.startswith("[1] "):
        line = run.stderr.readline()
        assert line or run.poll() is None, run.stderr.read()
    run.send_signal(signal.SIGINT)
    stdout, stderr = run.communicate(timeout=120)
    assert run.returncode == 130, stderr
    assert "trundle fleet: interrupted; cancelled" in stderr
    with open(out / "results.csv", newline="") as f:
        statuses = {Path(r["log"]).stem: r["status"] for r in csv.DictReader(f)}
    assert set(statuses) == {p.stem for p in logs} and "cancelled" in statuses.values() and "ok" in statuses.values()
    for name, status in statuses.items():
        complete = (out / name / "fleet.json").is_file()
        assert complete == (status == "ok") and (not (out / name).exists() or complete)
    assert not (out / ".fleet" / "work").exists()
    time.sleep(0.5)
    assert not _descendants(run.pid)

    rerun = subprocess.run(argv, capture_output=True, text=True, timeout=300)
    assert rerun.returncode == 0, rerun.stderr
    with open(out / "results.csv", newline="") as f:
        after = {Path(r["log"]).stem: r["status"] for r in csv.DictReader(f)}
    assert after == {n: "skipped" if s == "ok" else "ok" for n, s in statuses.items()}
