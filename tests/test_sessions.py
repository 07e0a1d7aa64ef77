"""Multi-session mapping (issue 27) on small simulated sessions in the polygon room: the session bundle,
``trundle slam --continue`` placing a session whose start it is not told (against the simulator's
truth), cross-session closures, ``--freeze``, a log of another room refused (and ``--allow-new-area``),
and one line for every bad MAPDIR. The real-log acceptance is in tests/test_sessions_datasets.py (slow)
and tools/bench/bench_sessions.py."""

from __future__ import annotations

import csv
import json
import math
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.cli_run import trundle
from tests.session_logs import OTHER_ROOM, ROOM_MARKERS, START_NS, other_room_drive, room_loop, room_session
from trundle.fusion.evaluation.trajectory_errors import align_se2, landmark_error
from trundle.fusion.geometry import relative, wrap_angle
from trundle.fusion.mapping.map_io import load_map, read_landmarks_csv, read_trajectory_csv
from trundle.fusion.slam.sessions import session_submaps
from trundle.logs.reader import LogReader
from trundle.tools.cli.main import main
from trundle.tools.fleet.run import sessions_in_order
from trundle.tools.jobs.sessions import read_bundle

TRUNDLE = str(Path(sys.executable).with_name("trundle"))
LOOP = room_loop()
LAP = 113
B_START = 56   # the second session starts half-way round the first one's lap, a day later
DAY_NS = 86_400 * 10**9


@pytest.fixture(scope="module")
def maps(tmp_path_factory):
    """Session A (one lap from the loop's start) mapped; session B (a lap from half-way round) as a log;
    both see the room's point markers."""
    root = tmp_path_factory.mktemp("sessions")
    a = room_session(root / "a.mcap", LOOP[:LAP], markers=ROOM_MARKERS)
    b = room_session(root / "b.mcap", LOOP[B_START:B_START + LAP], START_NS + DAY_NS, seed=1000, markers=ROOM_MARKERS)
    assert main(["slam", str(a), "-o", str(root / "a")]) == 0
    return root, b


@pytest.fixture(scope="module")
def continued(maps):
    """``trundle slam B --continue A -o ab``: exit code, stdout, stderr and the folder."""
    root, b = maps
    out = root / "ab"
    code = main(["slam", str(b), "-o", str(out), "--continue", str(root / "a")])
    return code, out


def read_csv(path) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_slam_writes_a_bundle_readable_as_plain_files(maps) -> None:
    root, _ = maps
    bundle = root / "a" / "session"
    meta = json.loads((bundle / "session.json").read_text())
    assert meta["format"] == "trundle-session" and meta["version"] == 1 and len(meta["sessions"]) == 1
    assert meta["laser"]["beams"] == 181 and meta["laser"]["mount"] == [0.0, 0.0, 0.0]
    assert math.isclose(meta["laser"]["angle_max"] - meta["laser"]["angle_min"], math.radians(270.0) * 180 / 181,
                        rel_tol=1e-6)
    nodes, scans = read_csv(bundle / "nodes.csv"), read_csv(bundle / "scans.csv")
    assert len(nodes) == meta["keyframes"] and len(scans) == LAP == meta["scans"]
    with LogReader(bundle / "keyframes.mcap") as reader:
        topics = [i.topic for i in reader.messages()]
    assert topics.count("/session/keyframes/scan") == topics.count("/session/keyframes/pose") == len(nodes)
    report = json.loads((root / "a" / "report.json").read_text())
    assert json.loads((bundle / "config.json").read_text()) == report["config"]
    edges = read_csv(bundle / "edges.csv")
    assert len(edges) == meta["edges"] >= len(nodes) - 1
    stamps, poses = read_trajectory_csv(root / "a" / "trajectory.csv")
    graph, config, _ = read_bundle(root / "a")
    members = {}
    for row in read_csv(bundle / "submaps.csv"):
        members.setdefault(int(row["submap"]), []).append(int(row["node"]))
    assert [s.nodes for s in session_submaps(graph, config)] == list(members.values())  # as the submaps are built
    joined_stamps, joined, _ = graph.trajectory()
    np.testing.assert_array_equal(joined_stamps, stamps)
    np.testing.assert_allclose(joined, poses, atol=2e-6)   # the trajectory from keyframes + offsets in the bundle


def test_continue_places_the_session_and_closes_loops_across_sessions(maps, continued) -> None:
    root, b = maps
    code, out = continued
    assert code == 0
    report = json.loads((out / "report.json").read_text())
    # B starts where A's scan B_START was taken: placed where A's map has that scan (A's own mapping error,
    # a few cm against the truth, is no placement error)
    _, a_poses = read_trajectory_csv(root / "a" / "trajectory.csv")
    error = relative(a_poses[B_START], np.array(report["placement"]["first_pose"]))
    assert math.hypot(error[0], error[1]) < 0.03 and abs(error[2]) < math.radians(0.5)
    closures = report["cross_session_closures"]
    assert closures["accepted"] >= 1 and closures["rejected"] == 0
    assert report["map_check"]["status"] == "passed"
    rows = read_csv(out / "trajectory.csv")
    assert list(rows[0]) == ["t_ns", "x", "y", "theta", "session"]
    sessions = np.array([int(r["session"]) for r in rows])
    assert (sessions == 0).sum() == LAP and (sessions == 1).sum() == LAP
    # every B scan taken where an A scan was (the truth says which) lies where the joint map has that A scan
    _, poses = read_trajectory_csv(out / "trajectory.csv")
    a_truth, b_truth = LOOP[:LAP], LOOP[B_START:B_START + LAP]
    pairs = [(int(np.argmin(np.abs(a_truth - p).sum(axis=1))), k) for k, p in enumerate(b_truth)]
    pairs = [(i, k) for i, k in pairs if np.abs(a_truth[i] - b_truth[k]).sum() < 1e-9]
    assert len(pairs) > LAP // 2
    same = relative(poses[:LAP][[i for i, _ in pairs]], poses[LAP:][[k for _, k in pairs]])
    assert np.hypot(same[:, 0], same[:, 1]).max() < 0.03 and np.abs(wrap_angle(same[:, 2])).max() < math.radians(1.0)
    for name in ("map.pgm", "map.yaml", "map.png", "sessions.png", "trajectory.png", "slam.mcap"):
        assert (out / name).is_file()
    joint, alone = load_map(out / "map.yaml"), load_map(root / "a" / "map.yaml")
    assert np.abs(np.subtract(joint.data.shape, alone.data.shape)).max() <= 4   # one room, not two side by side
    meta = json.loads((out / "session" / "session.json").read_text())
    assert [s["log"] for s in meta["sessions"]] == [json.loads((root / "a" / "report.json").read_text())["log"],
                                                    str(b)]
    # the old session moved only as the cross-session closures asked (its own edges are at their optimum)
    before = read_bundle(root / "a")[0].poses
    graph = read_bundle(out)[0]
    moved = relative(before, graph.poses[graph.session == 0])
    assert np.hypot(moved[:, 0], moved[:, 1]).max() < 0.03
    assert np.abs(wrap_angle(moved[:, 2])).max() < math.radians(0.5)


def test_freeze_keeps_the_old_session_where_it_was(maps, capsys) -> None:
    root, b = maps
    code, _, stderr = trundle(capsys, "slam", str(b), "-o", str(root / "frozen"), "--continue", str(root / "a"),
                              "--freeze")
    assert code == 0, stderr
    before = read_csv(root / "a" / "session" / "nodes.csv")
    after = read_csv(root / "frozen" / "session" / "nodes.csv")
    assert [(r["x"], r["y"], r["theta"]) for r in after[:len(before)]] == [(r["x"], r["y"], r["theta"]) for r in before]
    assert json.loads((root / "frozen" / "report.json").read_text())["cross_session_closures"]["accepted"] >= 1


def test_a_log_of_another_room_is_refused_and_may_join_as_a_new_area(maps, tmp_path, capsys) -> None:
    root, _ = maps
    other = room_session(tmp_path / "other.mcap", other_room_drive(), START_NS + DAY_NS, walls=OTHER_ROOM, seed=77)
    code, stdout, stderr = trundle(capsys, "slam", str(other), "-o", str(tmp_path / "o"), "--continue", str(root / "a"))
    assert code == 2 and len(stderr.strip().splitlines()) == 1 and "cannot be placed" in stderr, stdout + stderr
    assert not (tmp_path / "o").exists()
    code, stdout, stderr = trundle(capsys, "slam", str(other), "-o", str(tmp_path / "n"), "--continue", str(root / "a"),
                                   "--allow-new-area")
    assert code == 0, stderr
    report = json.loads((tmp_path / "n" / "report.json").read_text())
    assert not report["placement"]["placed"] and report["cross_session_closures"]["accepted"] == 0
    graph, _, _ = read_bundle(tmp_path / "n")
    assert graph.sessions == 2 and graph.cross_edges().size == 0
    old, new = graph.poses[graph.session == 0], graph.poses[graph.session == 1]
    assert new[:, 0].min() > old[:, 0].max() + 5.0   # a disconnected part beside the old map
    # session B still continues this two-part map
    _, b = maps
    code, _, stderr = trundle(capsys, "slam", str(b), "-o", str(tmp_path / "nb"), "--continue", str(tmp_path / "n"))
    assert code == 0, stderr
    assert len(json.loads((tmp_path / "nb" / "session" / "session.json").read_text())["sessions"]) == 3


def test_every_bad_mapdir_is_one_line_and_writes_nothing(maps, tmp_path, capsys) -> None:
    root, b = maps
    older = tmp_path / "older"
    shutil.copytree(root / "a", older)
    shutil.rmtree(older / "session")
    version = tmp_path / "version"
    shutil.copytree(root / "a", version)
    meta = json.loads((version / "session" / "session.json").read_text())
    (version / "session" / "session.json").write_text(json.dumps({**meta, "version": 99}))
    edges = tmp_path / "edges"
    shutil.copytree(root / "a", edges)
    lines = (edges / "session" / "edges.csv").read_text().splitlines()
    (edges / "session" / "edges.csv").write_text("\n".join(lines[:-3]) + "\n")
    scans = tmp_path / "scans"
    shutil.copytree(root / "a", scans)
    (scans / "session" / "keyframes.mcap").write_bytes(b"\x89MCAP0\r\n" + b"\0" * 100)
    nan = tmp_path / "nan"
    shutil.copytree(root / "a", nan)
    text = (nan / "session" / "nodes.csv").read_text().splitlines()
    text[5] = ",".join(text[5].split(",")[:3] + ["nan"] + text[5].split(",")[4:])
    (nan / "session" / "nodes.csv").write_text("\n".join(text) + "\n")
    config = tmp_path / "coarse.toml"
    config.write_text("[slam.submaps]\nresolution = 0.1\n")
    wide = room_session(tmp_path / "wide.mcap", LOOP[:12], beams=361)
    cases = [((str(b), "--continue", str(older)), "older trundle"),
             ((str(b), "--continue", str(version)), "version 99"),
             ((str(b), "--continue", str(edges)), "damaged session bundle: edges.csv"),
             ((str(b), "--continue", str(scans)), "damaged session bundle: keyframes.mcap"),
             ((str(b), "--continue", str(nan)), "damaged session bundle: nodes.csv"),
             ((str(b), "--continue", str(tmp_path / "none")), "no such folder"),
             ((str(b), "--continue", str(root / "a"), "--config", str(config)),
              "another [slam] config: submaps.resolution 0.05 there, 0.1 here"),
             ((str(wide), "--continue", str(root / "a")), "another laser: 181 beams over 268.5 deg"),
             ((str(b), "--freeze"), "--freeze and --allow-new-area go with --continue")]
    for argv, message in cases:
        out = tmp_path / "out"
        code, _, stderr = trundle(capsys, "slam", *argv, "-o", str(out))
        assert code == 2 and message in stderr and len(stderr.strip().splitlines()) == 1, (argv, stderr)
        assert "Traceback" not in stderr and not out.exists()


def test_fleet_orders_each_robots_sessions_in_time(tmp_path) -> None:
    logs = [room_session(tmp_path / name, LOOP[:3], START_NS + k * DAY_NS, robot=robot) for name, k, robot in
            (("late.mcap", 2, "robot-a"), ("early.mcap", 0, "robot-a"), ("other.mcap", 1, "robot-b"),
             ("middle.mcap", 1, "robot-a"))]
    previous = sessions_in_order([str(p) for p in logs], ["late", "early", "other", "middle"])
    assert previous == [3, None, None, 1]


def test_fleet_slam_continue_chains_one_robots_sessions(maps, tmp_path) -> None:
    root, b = maps
    logs = tmp_path / "logs"
    later = room_session(logs / "c.mcap", LOOP[B_START + 20:B_START + 90], START_NS + 2 * DAY_NS, seed=2000)
    room_session(logs / "b.mcap", LOOP[B_START:B_START + 70], START_NS + DAY_NS, seed=1000)
    out = tmp_path / "out"
    run = subprocess.run([TRUNDLE, "fleet", "slam", str(later), str(logs / "b.mcap"), "-o", str(out), "--num-cpus", "1",
                          "--continue", str(root / "a")], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    first = json.loads((out / "b" / "session" / "session.json").read_text())
    second = json.loads((out / "c" / "session" / "session.json").read_text())
    assert [Path(s["log"]).name for s in first["sessions"]] == ["a.mcap", "b.mcap"]
    assert [Path(s["log"]).name for s in second["sessions"]] == ["a.mcap", "b.mcap", "c.mcap"]
    assert json.loads((out / "c" / "report.json").read_text())["cross_session_closures"]["accepted"] >= 1


def test_landmarks_of_both_sessions_are_optimised_together(maps, continued) -> None:
    root, _ = maps
    code, out = continued
    assert code == 0
    graph, _, _ = read_bundle(root / "a")
    assert len(graph.sightings) == len(read_csv(root / "a" / "session" / "sightings.csv")) > 0
    joint = read_bundle(out)[0]
    assert len(joint.sightings) > len(graph.sightings) and {s.node for s in joint.sightings} & set(
        np.flatnonzero(joint.session == 1).tolist())
    # the joint map placed on the truth by its trajectories (as the demo scores markers): every marker where it is
    _, poses, sessions = joint.trajectory()
    truth = np.concatenate([LOOP[:LAP], LOOP[B_START:B_START + LAP]])
    order = np.concatenate([np.flatnonzero(sessions == 0), np.flatnonzero(sessions == 1)])
    alignment = align_se2(poses[order, :2], truth[:, :2])
    ids, positions, _ = read_landmarks_csv(out / "landmarks.csv")
    error = landmark_error(ids, positions, list(ROOM_MARKERS), np.array(list(ROOM_MARKERS.values())), alignment)
    assert error.count == len(ROOM_MARKERS) and error.max_m < 0.03, error
