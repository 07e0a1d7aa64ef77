"""Logger and reader behaviour: independent read-back, splits, latching, drops, salvage."""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer
from rosbags.highlevel import AnyReader

from trundle.logs import messages as m
from trundle.logs import ros2
from trundle.logs.metadata import read_metadata
from trundle.logs.reader import LogReader
from trundle.logs.replay import replay
from trundle.logs.writer import Logger
from trundle.tools.cli.main import main

T0 = 1_763_784_000_000_000_000


def scan(t: int, n: int = 181) -> m.LaserScan:
    rng = np.random.default_rng(t)
    return m.LaserScan(t, "laser", -1.57, 1.57, np.pi / (n - 1), 1e-4, 0.1, 0.02, 30.0,
                       rng.uniform(0.1, 30, n), rng.uniform(0, 100, n))


def static_tf(t: int) -> m.TFMessage:
    return m.TFMessage((m.TransformStamped.planar(t, "base_link", "laser", 0.2, 0.0, 0.0, 0.3),))


def write_sample(path: Path, seconds: float = 2.0, **kwargs) -> list[tuple[str, int, m.Message]]:
    written = []
    t0 = T0
    with Logger(path, **kwargs) as logger:
        logger.write("/tf_static", static_tf(t0), t0)
        written.append(("/tf_static", t0, static_tf(t0)))
        for i in range(int(seconds * 40)):
            t = t0 + i * 25_000_000
            s = scan(t)
            logger.write("/scan", s, t + 1000)
            written.append(("/scan", t + 1000, s))
            if i % 4 == 0:
                js = m.JointState(t, "base_link", ("left", "right"), [i * 0.1, i * 0.2], [1.0, 2.0])
                logger.write("/wheels", js, t + 2000)
                written.append(("/wheels", t + 2000, js))
    return written


def test_independent_reader_sees_every_message_equal(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    written = write_sample(path)
    assert not list(tmp_path.glob("*.active"))
    with AnyReader([path]) as reader:
        got = [(c.topic, t, ros2.decode(c.msgtype, raw)) for c, t, raw in reader.messages()]
        types = {c.topic: c.msgtype for c in reader.connections}
    assert types == {"/tf_static": "tf2_msgs/msg/TFMessage", "/scan": "sensor_msgs/msg/LaserScan",
                     "/wheels": "sensor_msgs/msg/JointState"}
    assert sorted(got, key=lambda g: g[1]) == sorted(written, key=lambda w: w[1])
    ours = [(x.topic, x.log_time_ns, x.msg) for x in LogReader(path).messages()]
    assert ours == sorted(written, key=lambda w: w[1])


def test_file_is_ros2_profile_with_statistics_and_latched_qos(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    write_sample(path, seconds=0.5, metadata={"robot": "r2"})
    with open(path, "rb") as f:
        reader = make_reader(f)
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        assert summary.statistics.message_count == 1 + 20 + 5
        channels = {c.topic: c for c in summary.channels.values()}
        assert "durability: 1" in channels["/tf_static"].metadata["offered_qos_profiles"]
        assert "durability: 2" in channels["/scan"].metadata["offered_qos_profiles"]
        assert all(s.encoding == "ros2msg" for s in summary.schemas.values())
        assert {c.message_encoding for c in channels.values()} == {"cdr"}
        meta = {r.name: r.metadata for r in reader.iter_metadata()}
        assert read_metadata(meta).robot_name == "r2" and "trundle_version" in meta["trundle"]
        assert json.loads(meta["trundle"]["robot"]) == {"name": "r2"}  # structured, as every reader expects


def test_info_counts_match(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "run.mcap"
    write_sample(path, seconds=2.0)
    assert main(["info", str(path), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert {t: v["count"] for t, v in info["topics"].items()} == {"/scan": 80, "/tf_static": 1, "/wheels": 20}
    assert info["topics"]["/scan"]["rate_hz"] == pytest.approx(40.0)
    assert info["complete"] and info["messages"] == 101
    assert main(["info", str(path)]) == 0
    text = capsys.readouterr().out
    assert "Topic: /scan" in text and "Count:      80" in text and "sensor_msgs/msg/LaserScan" in text


def test_split_by_duration_repeats_latched_topics(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    write_sample(path, seconds=3.0, split_duration_s=1.0)
    files = sorted(tmp_path.glob("run_*.mcap"), key=lambda p: int(p.stem.split("_")[1]))
    assert [p.name for p in files] == ["run_0.mcap", "run_1.mcap", "run_2.mcap"]
    total = 0
    for p in files:
        msgs = list(LogReader(p).messages())
        assert msgs[0].topic == "/tf_static" and msgs[0].msg == static_tf(T0)  # measurement time kept
        scans = [x for x in msgs if x.topic == "/scan"]
        assert len(scans) == 40
        total += len(scans)
    assert total == 120


def test_split_by_size_and_on_request(tmp_path: Path) -> None:
    path = tmp_path / "big.mcap"
    write_sample(path, seconds=2.0, split_bytes=20_000, chunk_size=4096, compression="none")
    parts = list(tmp_path.glob("big_*.mcap"))
    assert len(parts) >= 3
    assert sum(1 for p in parts for x in LogReader(p).messages(["/scan"])) == 80
    manual = tmp_path / "manual"
    manual.mkdir()
    with Logger(manual / "m.mcap") as logger:
        logger.write("/scan", scan(1), 1)
        time.sleep(0.05)
        logger.split()
        time.sleep(0.05)
        logger.write("/scan", scan(2), 2)
    assert logger.files == [manual / "m.mcap", manual / "m_1.mcap"]
    assert [x.log_time_ns for p in logger.files for x in LogReader(p).messages()] == [1, 2]


def test_full_queue_drops_are_counted_per_topic(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    original = Writer.add_message

    def slow(self, *args, **kwargs):
        time.sleep(0.01)
        return original(self, *args, **kwargs)

    monkeypatch.setattr(Writer, "add_message", slow)
    logger = Logger(tmp_path / "q.mcap", queue_size=5)
    accepted = sum(logger.write("/scan", scan(i), i) for i in range(100))
    logger.close()
    stats = logger.stats_dict()["/scan"]
    assert stats["written"] == accepted and stats["written"] + stats["dropped"] == 100
    assert stats["dropped"] > 0
    assert sum(1 for _ in LogReader(tmp_path / "q.mcap").messages()) == accepted
    assert logger.write("/scan", scan(0), 0) is False  # after close: dropped, counted
    assert logger.stats_dict()["/scan"]["dropped"] == stats["dropped"] + 1


def test_leftover_active_file_is_salvaged_at_start(tmp_path: Path) -> None:
    src = tmp_path / "src.mcap"
    write_sample(src, seconds=1.0, compression="none", chunk_size=2048)
    data = src.read_bytes()
    (tmp_path / "old.mcap.active").write_bytes(data[: len(data) * 2 // 3])
    src.unlink()
    logger = Logger(tmp_path / "new.mcap")
    logger.close()
    assert [s.output for s in logger.salvaged] == [tmp_path / "old.mcap"]
    assert not (tmp_path / "old.mcap.active").exists()
    assert 0 < sum(1 for _ in LogReader(tmp_path / "old.mcap").messages()) < 51


def test_replay_paces_messages_by_log_time(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    write_sample(path, seconds=0.5)
    now = [100.0]
    sleeps: list[float] = []

    def fake_sleep(d: float) -> None:
        sleeps.append(d)
        now[0] += d

    delivered: list[int] = []
    count = replay(path, lambda x: delivered.append(x.log_time_ns), rate=2.0, topics=["/scan"],
                   sleep=fake_sleep, clock=lambda: now[0])
    assert count == 20 and delivered == sorted(delivered)
    assert sum(sleeps) == pytest.approx(19 * 0.025 / 2.0)
    assert replay(path, lambda x: None, rate=0, sleep=fake_sleep, clock=lambda: now[0]) == 26


def test_export_csv_and_ndjson(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "run.mcap"
    write_sample(path, seconds=0.5)
    assert main(["export", str(path), "--topic", "/wheels", "--format", "csv"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("log_time_ns,stamp_ns,frame_id,name.0,name.1,position.0,position.1")
    assert len(lines) == 1 + 5
    assert main(["export", str(path), "--topic", "/scan", "--format", "ndjson"]) == 0
    rows = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    assert len(rows) == 20 and len(rows[0]["ranges"]) == 181


def test_active_file_copy_reads_while_logging(tmp_path: Path) -> None:
    logger = Logger(tmp_path / "live.mcap", flush_period_s=0.05)
    for i in range(10):
        logger.write("/scan", scan(i), i)
    time.sleep(0.3)
    snapshot = tmp_path / "snap.mcap.active"
    shutil.copy(tmp_path / "live.mcap.active", snapshot)
    logger.close()
    assert sum(1 for _ in LogReader(snapshot).messages()) == 10


def test_time_window_and_topic_filter(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    write_sample(path, seconds=2.0, chunk_size=4096)
    start, end = T0 + 500_000_000, T0 + 1_000_000_000
    got = list(LogReader(path).messages(["/scan"], start_ns=start, end_ns=end))
    assert [x.log_time_ns for x in got] == [T0 + i * 25_000_000 + 1000 for i in range(20, 40)]


def test_replay_command_prints_per_topic_summary(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "run.mcap"
    write_sample(path, seconds=1.0)
    assert main(["replay", str(path), "--rate", "0", "--topics", "/scan", "/wheels"]) == 0
    out = capsys.readouterr().out
    assert "replayed 50 messages" in out
    assert "/scan" in out and "40 msgs" in out and "/wheels" in out and "10 msgs" in out


def test_static_transforms_of_every_publisher_repeat_in_each_split(tmp_path: Path) -> None:
    laser = m.TFMessage((m.TransformStamped.planar(T0, "base_link", "laser", 0.2, 0.0, 0.0),))
    camera = m.TFMessage((m.TransformStamped.planar(T0, "base_link", "camera", 0.1, 0.0, 0.0),))
    with Logger(tmp_path / "tf.mcap", split_duration_s=1.0) as logger:
        logger.write("/tf_static", laser, T0)
        logger.write("/tf_static", camera, T0)
        for i in range(80):
            logger.write("/scan", scan(T0 + i * 25_000_000), T0 + i * 25_000_000)
    assert len(logger.files) == 2
    for path in logger.files:
        children = {t.child_frame_id for x in LogReader(path).messages(["/tf_static"]) for t in x.msg.transforms}
        assert children == {"laser", "camera"}


def test_a_split_keeps_what_was_queued_before_it_in_the_old_file(tmp_path: Path) -> None:
    """The writer takes messages in batches: a split request waits its turn in the queue."""
    with Logger(tmp_path / "b.mcap", batch_s=5.0) as logger:  # nothing is written until the split or close
        for i in range(3):
            logger.write("/scan", scan(i), i)
        logger.split()
        for i in range(3, 5):
            logger.write("/scan", scan(i), i)
    assert [[x.log_time_ns for x in LogReader(p).messages()] for p in logger.files] == [[0, 1, 2], [3, 4]]


@pytest.mark.parametrize("limit_mb, compression", [(0.25, "zstd"), (0.1, "none"), (0.05, "lz4")])
def test_split_files_stay_under_the_size_limit(tmp_path: Path, limit_mb: float, compression: str) -> None:
    """`--split-size 0.25` once wrote 297 kB files: the open chunk and the summary were not counted."""
    path = tmp_path / "run.mcap"
    with Logger(path, split_bytes=int(limit_mb * 1e6), compression=compression, flush_period_s=0.2) as logger:
        for i in range(2400):  # 1 kB scans, 60 s of them at 40 Hz: several splits
            t = T0 + i * 25_000_000
            logger.write("/scan", scan(t, 120), t)
            if i % 100 == 0:
                time.sleep(0.05)  # flushes happen between messages, as in a live recording
    parts = sorted(tmp_path.glob("run_*.mcap"), key=lambda p: int(p.stem.split("_")[1]))
    sizes = [p.stat().st_size for p in parts]
    assert len(parts) >= 3 and max(sizes) <= limit_mb * 1e6, sizes
    assert min(sizes[:-1]) >= 0.5 * limit_mb * 1e6, sizes  # and not split needlessly early
    assert sum(LogReader(p).info().topics["/scan"].count for p in parts) == 2400


def test_a_stamp_outside_mcaps_range_never_kills_the_writer(tmp_path: Path) -> None:
    """A scan stamped before the epoch (a device clock near zero, minus its sweep) once raised
    struct.error in the writer thread: nothing after it was written. Its publish time is now its
    log time; a log time outside MCAP's range is the caller's mistake, refused at once."""
    path = tmp_path / "clock.mcap"
    with Logger(path) as logger:
        early = scan(1000)
        early = m.LaserScan(-5_000_000, *[getattr(early, f) for f in ("frame_id", "angle_min", "angle_max",
                                                                     "angle_increment", "time_increment",
                                                                     "scan_time", "range_min", "range_max",
                                                                     "ranges", "intensities")])
        assert logger.write("/scan", early, 1000)
        with pytest.raises(ValueError, match="outside MCAP"):
            logger.write("/scan", scan(2000), -1)
        assert logger.write("/scan", scan(3000), 3000)
    with open(path, "rb") as f:
        messages = [(c.topic, msg.log_time, msg.publish_time) for _, c, msg in make_reader(f).iter_messages()]
    assert messages == [("/scan", 1000, 1000), ("/scan", 3000, 3000)]
    assert [x.msg.stamp_ns for x in LogReader(path).messages()][0] == -5_000_000
