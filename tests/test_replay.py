"""`trundle replay`: the daemon on a log. Replays of the logs trundle writes (recorder, daemon, demo,
an import) with the daemon's SLAM write a log Foxglove's ROS 2 decoder reads; at rate 0 the SLAM is
exactly `trundle slam`'s; a Foxglove client joining a replay mid-way gets the latched transforms and
every scan, with the server's time in log time; --start/--end/--loop play what they say; Ctrl-C
leaves a complete output; each mistake is one line."""

from __future__ import annotations

import contextlib
import itertools
import json
import os
import re
import signal
import socket
import struct
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from websockets.sync import client as websockets_client

import trundle
from tests.cli_run import succeeds
from tests.conftest import shared_file
from tests.test_daemon import Running, config, wait_for
from tests.test_journey import recorder_log  # noqa: F401 -- the recorder's log, a module fixture
from trundle.logs.metadata import read_metadata
from trundle.logs.reader import LogReader, read_messages
from trundle.tools.cli.main import main
from trundle.tools.daemon.live_view import TIME_PERIOD_NS

DEMO_LOG = Path(__file__).resolve().parent / "data" / "demo_short" / "demo.mcap"
PACKAGE_PARENT = Path(trundle.__file__).parent.parent  # where `import trundle` found the code under test


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def decoded(path: Path, topics: set[str]) -> dict[str, list]:
    """The messages of ``topics`` as Foxglove's ROS 2 decoder (mcap-ros2-support) reads them."""
    out: dict[str, list] = {t: [] for t in topics}
    with open(path, "rb") as f:
        for _, channel, _, msg in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages(
                topics=sorted(topics)):
            out[channel.topic].append(msg)
    return out


@pytest.fixture(scope="module")
def short_demo(tmp_path_factory) -> Path:
    """The demo's log, its first 4 s (cut by replay itself, as a user would)."""
    out = tmp_path_factory.mktemp("short") / "demo4.mcap"
    assert main(["replay", str(DEMO_LOG), "--rate", "0", "--end", "4", "-o", str(out)]) == 0
    return out


def daemon_log(folder: Path) -> Path:
    """A log of the daemon with its own SLAM on (so it holds /slam/pose, /map and map -> odom)."""
    with Running(config(folder, processing={"slam": True})) as run:
        wait_for(lambda: (run.daemon.processing is not None and run.daemon.processing.slam is not None
                          and run.daemon.processing.slam.stats.scans > 30))
    (log,) = sorted((folder / "logs").glob("*.mcap"))
    return log


@pytest.fixture(params=["recorder", "daemon", "demo", "import"])
def any_log(request, tmp_path, capsys) -> tuple[Path, str]:
    """A log of each kind, and how many seconds of it to replay (the Intel lab's scans are 3 s apart)."""
    if request.param == "recorder":
        return request.getfixturevalue("recorder_log"), "6"
    if request.param == "daemon":
        return daemon_log(tmp_path), "6"
    if request.param == "demo":
        return request.getfixturevalue("short_demo"), "6"
    imported = tmp_path / "intel.mcap"
    succeeds(capsys, "import", "carmen", shared_file("intel/intel.gfs.log"), "-o", imported)
    return imported, "60"


def test_slam_replay_of_every_kind_of_log_writes_what_foxglove_reads(any_log, tmp_path, capsys):
    any_log, seconds = any_log
    out = tmp_path / "replayed.mcap"
    printed, said = succeeds(capsys, "replay", any_log, "--rate", "0", "--end", seconds, "--slam", "-o", out)
    scans = int(printed.split("slam: ")[1].split(" scans processed")[0])
    assert scans > 0 and "0 skipped to keep up" in printed and f"wrote {out}" in printed
    got = decoded(out, {"/slam/pose", "/map", "/path", "/scan"})
    assert len(got["/slam/pose"]) == scans == len(got["/scan"])  # the log's own poses (daemon) left out
    assert all(p.header.frame_id == "map" for p in got["/slam/pose"])
    last = got["/map"][-1]
    assert last.info.width * last.info.height == len(last.data) > 0 and last.header.frame_id == "map"
    assert len(got["/path"]) == 1 and len(got["/path"][0].poses) == scans
    if "/slam/pose" in LogReader(any_log).info().topics:  # the daemon's log: its outputs are replaced
        assert "the log's own /map, /slam/pose are left out: the processing makes them anew" in said
    meta = read_metadata(LogReader(out).info().metadata)
    assert meta.command == "replay" and meta.fields["source"] == str(any_log)
    assert meta.wheel_model() == read_metadata(LogReader(any_log).info().metadata).wheel_model()


def test_rate_0_slam_is_trundle_slam(short_demo, tmp_path, capsys):
    succeeds(capsys, "slam", short_demo, "-o", tmp_path / "slam")
    succeeds(capsys, "replay", short_demo, "--rate", "0", "--slam", "-o", tmp_path / "replay.mcap")
    ours = {t: [x.msg for x in read_messages(tmp_path / "replay.mcap", [t])] for t in ("/path", "/map", "/tf")}
    slam = {t: [x.msg for x in read_messages(tmp_path / "slam" / "slam.mcap", [t])] for t in ("/path", "/map", "/tf")}
    (path,), (reference,) = ours["/path"], slam["/path"]
    assert np.array_equal(path.stamps_ns, reference.stamps_ns) and np.array_equal(path.poses, reference.poses)
    assert np.array_equal(ours["/map"][-1].data, slam["/map"][-1].data)
    assert (ours["/map"][-1].width, ours["/map"][-1].height) == (slam["/map"][-1].width, slam["/map"][-1].height)
    map_to_odom = [tf for tf in ours["/tf"] if tf.transforms[0].frame_id == "map"]  # the replayed /tf is odom's
    assert map_to_odom == slam["/tf"]  # the online map -> odom of every scan, too


def test_the_daemons_config_turns_the_processing_on_with_its_frames(short_demo, tmp_path, capsys):
    robot = tmp_path / "robot.toml"
    robot.write_text('[processing]\nslam = true\nmap_period_s = 1.0\n\n[frames]\nmap = "world"\n')
    out = tmp_path / "configured.mcap"
    printed, _ = succeeds(capsys, "replay", short_demo, "--rate", "0", "--config", robot, "-o", out)
    got = decoded(out, {"/slam/pose", "/map", "/tf"})
    assert {p.header.frame_id for p in got["/slam/pose"]} == {"world"} and got["/slam/pose"]
    assert {(t.header.frame_id, t.child_frame_id) for tf in got["/tf"] for t in tf.transforms} == {
        ("world", "odom"), ("odom", "base_link")}  # the SLAM's and the log's own odometry
    assert len(got["/map"]) == 5  # every 1 s of log (4 s), and the final one
    assert read_metadata(LogReader(out).info().metadata).fields["config_file"] == str(robot)


def test_markers_are_detected_at_markers_hz_of_log_time(tmp_path, capsys):
    out = tmp_path / "markers.mcap"
    printed, _ = succeeds(capsys, "replay", DEMO_LOG, "--rate", "0", "--end", "3", "--markers", "-o", out)
    images = [(x.log_time_ns, x.msg.stamp_ns) for x in read_messages(out, ["/camera/image_raw/compressed"])]
    taken = [images[0]]  # [processing] markers_hz = 2: an image at least 0.5 s of log after the last one taken
    for log_time, stamp in images[1:]:
        if log_time - taken[-1][0] >= 500_000_000:
            taken.append((log_time, stamp))
    markers = decoded(out, {"/camera/markers"})["/camera/markers"]
    assert len(taken) == 5 and len(markers) == 5 and "results: /camera/marker_poses 5, /camera/markers 5" in printed
    assert [m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec for m in markers] == [s for _, s in taken]
    assert {m.id for m in markers} == {96}  # the ArUco marker on the wall the robot faces at the start


def test_start_and_end_play_that_window(tmp_path, capsys):
    out = tmp_path / "window.mcap"
    succeeds(capsys, "replay", DEMO_LOG, "--rate", "0", "--start", "2", "--end", "3.5", "-o", out)
    t0 = LogReader(DEMO_LOG).info().start_ns
    expected = [(x.topic, x.log_time_ns) for x in LogReader(DEMO_LOG).raw_messages(
        start_ns=t0 + 2_000_000_000, end_ns=t0 + 3_500_000_000)]
    # the log's one /tf_static and camera info, both before the window: sent first (the laser's mount)
    latched = [(x.topic, x.log_time_ns)
               for x in LogReader(DEMO_LOG).raw_messages(["/tf_static", "/camera/camera_info"])]
    assert len(latched) == 2 and all(t < t0 + 2_000_000_000 for _, t in latched)
    assert [(x.topic, x.log_time_ns) for x in LogReader(out).raw_messages()] == latched + expected and expected


def run_replay(*argv: object) -> subprocess.Popen:
    """`trundle replay ...` as its own process (Ctrl-C goes to it alone)."""
    return subprocess.Popen([sys.executable, "-m", "trundle.tools.cli", "replay", *map(str, argv)],
                            env={**os.environ, "PYTHONPATH": str(PACKAGE_PARENT)},
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


class Client:
    """A Foxglove WebSocket client (the `websockets` package speaking `foxglove.sdk.v1`): subscribes to
    ``topics`` once they are advertised and notes every message (subscription's topic, log time) and every
    server time it is told."""

    def __init__(self, ws, topics: list[str]) -> None:
        self.ws = ws
        self.info = json.loads(self.ws.recv(timeout=10))
        self.topics, self.channels = topics, {}
        self.received: list[tuple[str, int]] = []  # subscription's topic, log time
        self.server_times: list[int] = []  # every server time told, in the order told
        self.subscribed = False

    def receive(self, until, give_up_s: float = 120.0) -> None:
        """Take messages until ``until(self)``, the server closes, or (a stuck test) ``give_up_s`` pass."""
        give_up = time.monotonic() + give_up_s
        while not until(self) and time.monotonic() < give_up:
            try:
                message = self.ws.recv(timeout=30)
            except Exception:  # noqa: BLE001 -- the replay ended and closed the server
                return
            if isinstance(message, str):
                body = json.loads(message)
                if body["op"] == "advertise":
                    self.channels.update({c["topic"]: c for c in body["channels"]})
                if not self.subscribed and set(self.topics) <= set(self.channels):
                    self.ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                        {"id": i, "channelId": self.channels[t]["id"]} for i, t in enumerate(self.topics)]}))
                    self.subscribed = True
            elif message[0] == 0x02:  # Time
                self.server_times.append(struct.unpack_from("<Q", message, 1)[0])
            elif message[0] == 0x01:  # MessageData
                subscription, log_time = struct.unpack_from("<IQ", message, 1)
                self.received.append((self.topics[subscription], log_time))

    def times(self, topic: str) -> list[int]:
        return [t for name, t in self.received if name == topic]


@contextlib.contextmanager
def connected(port: int, topics: list[str]) -> Iterator[Client]:
    """A :class:`Client` of the live view on ``port``, once the replay serves it."""
    deadline = time.monotonic() + 30
    while True:
        try:
            connection = websockets_client.connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"],
                                                   open_timeout=5)
            break
        except OSError:
            assert time.monotonic() < deadline, "the live view never came up"
            time.sleep(0.05)
    with connection as ws:
        yield Client(ws, topics)


def test_live_client_joining_mid_replay_gets_every_scan_and_pose_in_log_time(tmp_path):
    port = free_port()
    replay = run_replay(DEMO_LOG, "--rate", "1", "--start", "1", "--end", "4", "--slam", "--live", port)
    with connected(port, ["/scan", "/slam/pose", "/tf_static"]) as client:
        assert "time" in client.info["capabilities"]
        client.receive(lambda c: False)
    out, err = replay.communicate(timeout=60)
    assert replay.returncode == 0, err
    assert f"live view: ws://127.0.0.1:{port}" in out
    log = LogReader(DEMO_LOG)
    t0 = log.info().start_ns
    scans = [x.log_time_ns for x in log.raw_messages(["/scan"], t0 + 1_000_000_000, t0 + 4_000_000_000)]
    said = re.search(r"slam: (\d+) scans processed, (\d+) skipped to keep up", out)
    assert said is not None, out
    processed, skipped = (int(n) for n in said.groups())
    assert processed + skipped == len(scans) == 120  # the window's scans: each taken or said skipped (behind real time)
    got = client.times("/scan")
    assert len(got) > 20 and got == scans[scans.index(got[0]):]  # from the first it got, every scan, in order
    assert len(client.times("/tf_static")) >= 1  # latched, sent before the client came: sent again to it
    poses = client.times("/slam/pose")  # as many as the SLAM kept up with (a loaded machine skips more)
    assert 1 <= len(poses) <= processed  # each at its scan's time, within the window
    assert all(scans[0] - 100_000_000 <= t <= scans[-1] + 100_000_000 for t in poses)
    # The server's time is the log's, told at least every TIME_PERIOD_NS of it plus the longest wait for a
    # message. foxglove-sdk sends time and data through two queues and picks between them at random, so on a
    # loaded machine a time can come some messages before or after the data it followed: the order between
    # the two is not checked, the time sequence is.
    window = np.array([x.log_time_ns for x in log.raw_messages(None, t0 + 1_000_000_000, t0 + 4_000_000_000)])
    longest_wait = TIME_PERIOD_NS + int(np.diff(window).max())
    told = client.server_times  # first the latched messages' times, from before the window, then the window's
    assert len(told) > 20 and told == sorted(told) and t0 <= told[0] and told[-1] <= window[-1]
    in_window = [t for t in told if t >= window[0]]
    assert max(np.diff(in_window)) <= longest_wait and in_window[-1] >= window[-1] - longest_wait


def test_loop_plays_the_window_again_until_ctrl_c(tmp_path):
    port = free_port()
    replay = run_replay(DEMO_LOG, "--rate", "2", "--start", "1", "--end", "1.5", "--topics", "/scan", "--loop",
                        "--live", port)
    with connected(port, ["/scan"]) as client:
        client.receive(lambda c: sum(1 for a, b in itertools.pairwise(c.times("/scan")) if b < a) >= 2)
        replay.send_signal(signal.SIGINT)
    out, err = replay.communicate(timeout=30)
    assert replay.returncode == 0 and "Traceback" not in err, err
    log = LogReader(DEMO_LOG)
    t0 = log.info().start_ns
    window = [x.log_time_ns for x in log.raw_messages(["/scan"], t0 + 1_000_000_000, t0 + 1_500_000_000)]
    got = client.times("/scan")
    first_wrap = next(i for i in range(1, len(got)) if got[i] < got[i - 1])
    assert got[first_wrap:first_wrap + len(window)] == window  # a whole pass, from the window's start
    assert "(stopped by Ctrl-C)" in out and " passes)" in out


def test_ctrl_c_leaves_a_complete_output(tmp_path):
    out = tmp_path / "cut.mcap"
    replay = run_replay(DEMO_LOG, "--rate", "0.5", "--slam", "-o", out)  # 45 s: Ctrl-C comes long before the end
    active = tmp_path / f".cut.mcap.{replay.pid}.partial.active"  # the output helper's name until it is complete
    wait_for(active.exists, timeout_s=30)
    wait_for(lambda: active.stat().st_size > 200_000, timeout_s=30)
    replay.send_signal(signal.SIGINT)
    printed, err = replay.communicate(timeout=60)
    assert replay.returncode == 0 and "Traceback" not in err, err
    assert "(stopped by Ctrl-C)" in printed
    info = LogReader(out).info()
    assert info.complete and os.listdir(tmp_path) == ["cut.mcap"]
    assert info.topics["/path"].count == 1 and info.topics["/map"].count >= 1  # the SLAM finished


def test_what_the_log_lacks_is_said_before_it_starts(capsys):
    out, err = succeeds(capsys, "replay", DEMO_LOG, "--rate", "0", "--end", "1", "--slam", "--markers",
                       "--topics", "/tf_static", "/wheels", "/nope")
    assert err.splitlines() == [f"trundle replay: {DEMO_LOG} has no /nope: playing the other topics",
                                f"trundle replay: {DEMO_LOG} has no scans on /scan (SLAM maps nothing), "
                                "no camera images (no markers to detect)"]
    assert "slam: 0 scans processed" in out


def test_a_log_without_odometry_is_said_before_it_starts(tmp_path, capsys):
    scans_only, with_wheels = tmp_path / "scans.mcap", tmp_path / "wheels.mcap"
    succeeds(capsys, "replay", DEMO_LOG, "--rate", "0", "--end", "2", "--topics", "/scan", "/tf_static",
            "-o", scans_only)
    succeeds(capsys, "replay", DEMO_LOG, "--rate", "0", "--end", "2", "--topics", "/scan", "/tf_static", "/wheels",
            "-o", with_wheels)
    out, err = succeeds(capsys, "replay", scans_only, "--rate", "0", "--slam")
    assert err.splitlines() == [f"trundle replay: {scans_only} has no odometry (SLAM matches the scans alone)"]
    scans = LogReader(scans_only).info().topics["/scan"].count
    assert f"slam: {scans} scans processed, 0 skipped to keep up" in out and scans > 0
    _, err = succeeds(capsys, "replay", with_wheels, "--rate", "0", "--slam")
    assert err == ""  # the wheels' joint states and the log's wheel model are its odometry


@pytest.mark.parametrize(("argv", "words"), [
    (["--topics", "/nope"], "--topics /nope: no such topic in"),
    (["--start", "5", "--end", "3"], "--start 5 is not before --end 3"),
    (["--start", "100"], "has no message after 100 s into the log (it is 22.4 s long)"),
    (["--start", "3", "--end", "3.001", "--topics", "/tf_static"], "has no message of those topics 3-3.001 s"),
    (["--loop", "-o", "{tmp}/x.mcap"], "--loop plays until Ctrl-C: it cannot write -o"),
    (["-o", "{tmp}/exists.mcap"], "exists: give another name"),
    (["-o", "{tmp}/x.txt"], "output must be an .mcap file"),
    (["--live", ":80"], "has no host before ':'"),
    (["--live", "70000"], "70000 must be at most 65535"),
    (["--end", "0"], "0 must be above 0"),
    (["--config", "{tmp}/none.toml", "--slam"], "none.toml"),
])
def test_each_mistake_is_one_line(argv, words, tmp_path, capsys):
    (tmp_path / "exists.mcap").write_bytes(b"mine")
    code = main(["replay", str(DEMO_LOG), *[a.format(tmp=tmp_path) for a in argv]])
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1 and words in err and "Traceback" not in err, err
    assert (tmp_path / "exists.mcap").read_bytes() == b"mine" and not (tmp_path / "x.mcap").exists()

