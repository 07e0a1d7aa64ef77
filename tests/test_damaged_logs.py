"""A damaged log is said and recorded, never processed without a word (issue 23, item 6).

The user overwrote 3 KB inside a log: every command that reads it says in one line on stderr what
it skipped (chunks, messages, seconds of log), still does its job on the rest (exit 0), and every
report records it as ``log_damage`` (null for an intact log). The expected counts come from the
undamaged original, read with the mcap library: the messages of the chunk the 3 KB fell into.
"""

from __future__ import annotations

import csv
import io
import json
import math
import re
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader
from mcap.records import Chunk, ChunkIndex, Message
from mcap.stream_reader import StreamReader, breakup_chunk

from tests.planar_world import ROOM, scan
from tests.test_daemon import Running, config, wait_for
from tests.test_slam import loop_path
from trundle.logs import messages as m
from trundle.logs.errors import DataError
from trundle.logs.metadata import read_metadata
from trundle.logs.reader import LogReader
from trundle.logs.writer import Logger
from trundle.tools.cli.main import main
from trundle.tools.fleet.jobs import options_key
from trundle.tools.fleet.results import write_csv
from trundle.tools.fleet.summary import markdown
from trundle.tools.fleet.task import Task, process_log

START_NS = 1_780_000_000 * 10**9
STEPS = 60                        # odometry and scan pairs, 2 a second
IMAGE_TOPIC = "/camera/image_raw/compressed"
OVERWRITTEN = 3072                # bytes the user overwrote


def write_robot_log(path: Path) -> Path:
    """A drive through the polygon room as trundle's logger writes it (32 KiB chunks): the laser mount,
    odometry and a 270-degree scan twice a second, a small camera image once a second."""
    poses = loop_path(laps=2, step_m=0.3)[:STEPS]
    rng = np.random.default_rng(3)
    with Logger(path, chunk_size=32 * 1024, salvage=False, metadata={"command": "test"}) as logger:
        logger.write("/tf_static", m.TFMessage((m.TransformStamped.planar(START_NS, "base_link", "laser", 0, 0, 0),)),
                     START_NS)
        for k, pose in enumerate(poses):
            stamp = START_NS + 10**9 * (k + 1) // 2
            logger.write("/odom", m.Odometry(stamp, "odom", "base_link", *pose), stamp)
            logger.write("/scan", scan(ROOM, pose, beams=181, fov=math.radians(270.0), noise_m=0.01, seed=k,
                                       stamp_ns=stamp, max_range=10.0), stamp)
            if k % 2 == 0:
                image = cv2.imencode(".jpg", rng.integers(0, 256, (48, 64, 3), dtype=np.uint8))[1].tobytes()
                logger.write(IMAGE_TOPIC, m.CompressedImage(stamp, "camera_optical", "jpeg", image), stamp)
    return path


def chunk_messages(path: Path, index: ChunkIndex) -> list[Message]:
    """The messages stored in the chunk ``index`` describes, parsed by the mcap library."""
    with open(path, "rb") as f:
        f.seek(index.chunk_start_offset)
        data = f.read(index.chunk_length)
    record = next(iter(StreamReader(io.BytesIO(data), skip_magic=True, emit_chunks=True).records))
    assert isinstance(record, Chunk)
    return [r for r in breakup_chunk(record, validate_crc=True) if isinstance(r, Message)]


@dataclass(frozen=True)
class Damaged:
    """The original log, its damaged copy, and what the overwrite destroyed (from the original)."""

    original: Path
    bad: Path
    total: int                     # messages in the original
    per_topic: dict[str, int]      # of them, per topic
    lost: dict[str, int]           # messages per topic in the overwritten chunk
    seconds: float                 # log time the chunk spans

    @property
    def line(self) -> str:
        return (f"{self.bad} is damaged: skipped 1 corrupt chunk ({sum(self.lost.values())} messages, "
                f"{self.seconds:.2f} s of log)")


@pytest.fixture(scope="module")
def damaged(tmp_path_factory: pytest.TempPathFactory) -> Damaged:
    folder = tmp_path_factory.mktemp("damaged")
    original = write_robot_log(folder / "drive.mcap")
    with open(original, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        topics = {c.id: c.topic for c in summary.channels.values()}
        counts = {topic: summary.statistics.channel_message_counts[cid] for cid, topic in topics.items()}
    chunks = summary.chunk_indexes
    assert len(chunks) >= 5
    target = max(chunks[1:-1], key=lambda c: c.chunk_length)   # a chunk in the middle, the largest one
    assert target.chunk_length > OVERWRITTEN + 1024
    inside = chunk_messages(original, target)
    lost: dict[str, int] = {}
    for msg in inside:
        lost[topics[msg.channel_id]] = lost.get(topics[msg.channel_id], 0) + 1
    seconds = (max(x.log_time for x in inside) - min(x.log_time for x in inside)) * 1e-9
    data = bytearray(original.read_bytes())
    at = target.chunk_start_offset + target.chunk_length // 2 - OVERWRITTEN // 2
    data[at:at + OVERWRITTEN] = np.random.default_rng(23).bytes(OVERWRITTEN)
    bad = folder / "bad.mcap"
    bad.write_bytes(bytes(data))
    return Damaged(original, bad, sum(counts.values()), counts, lost, seconds)


def said(capsys: pytest.CaptureFixture[str], command: str, damaged: Damaged) -> str:
    """The command's stdout, after checking its stderr says the damage in exactly one line."""
    out, err = capsys.readouterr()
    lines = [line for line in err.splitlines() if "damaged" in line]
    assert lines == [f"trundle {command}: {damaged.line}"], err
    assert "Traceback" not in err
    return out


def recorded(entry: dict[str, Any] | None, damaged: Damaged) -> None:
    """The report's ``log_damage`` is the damage of the overwritten chunk."""
    assert entry is not None
    assert {k: v for k, v in entry.items() if k not in ("cause", "seconds_lost")} == {
        "file": str(damaged.bad), "size_bytes": damaged.bad.stat().st_size, "corrupt_chunks": 1,
        "torn_after_byte": None, "chunks_after_tear": None, "messages_lost": sum(damaged.lost.values()),
        "said": damaged.line}
    assert entry["seconds_lost"] == pytest.approx(damaged.seconds, abs=1e-9)
    assert entry["cause"].startswith("corrupt chunk skipped")


def silent(capsys: pytest.CaptureFixture[str]) -> str:
    """The command's stdout, after checking it said nothing about damage."""
    out, err = capsys.readouterr()
    assert "damaged" not in err, err
    return out


def test_the_overwrite_hit_one_chunk_of_every_topic_the_commands_read(damaged: Damaged) -> None:
    assert set(damaged.lost) == {"/odom", "/scan", IMAGE_TOPIC}
    assert 0 < damaged.lost["/scan"] < damaged.per_topic["/scan"] // 2


def test_info_says_it_in_one_line_and_json_records_it(damaged: Damaged, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["info", str(damaged.bad)]) == 0
    out = said(capsys, "info", damaged)
    assert "INCOMPLETE" in out
    assert f"Messages:          {damaged.total - sum(damaged.lost.values())}" in out
    assert main(["info", str(damaged.bad), "--json"]) == 0
    recorded(json.loads(said(capsys, "info", damaged))["log_damage"], damaged)
    assert main(["info", str(damaged.original), "--json"]) == 0
    assert json.loads(silent(capsys))["log_damage"] is None


def chunks_of(path: Path) -> list[ChunkIndex]:
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    return summary.chunk_indexes


def test_a_log_cut_inside_a_chunk_says_where_its_readable_part_ends(damaged: Damaged, tmp_path: Path,
                                                                    capsys: pytest.CaptureFixture[str]) -> None:
    third = chunks_of(damaged.original)[2]
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(damaged.original.read_bytes()[:third.chunk_start_offset + third.chunk_length // 2])
    assert main(["info", str(cut)]) == 0
    assert capsys.readouterr().err == (f"trundle info: {cut} is damaged: skipped the unreadable rest after byte "
                                       f"{third.chunk_start_offset} of {cut.stat().st_size} (messages unknown, "
                                       "seconds of log unknown)\n")


def test_a_crash_file_cut_between_chunks_says_it_is_unfinished(damaged: Damaged, tmp_path: Path,
                                                               capsys: pytest.CaptureFixture[str]) -> None:
    third = chunks_of(damaged.original)[2]
    crash = tmp_path / "run.mcap.active"
    crash.write_bytes(damaged.original.read_bytes()[:third.chunk_start_offset])
    assert main(["info", str(crash)]) == 0
    assert capsys.readouterr().err == (f"trundle info: {crash} is damaged: it stops at byte {third.chunk_start_offset} "
                                       "without its summary (an unfinished recording) (messages unknown, seconds of "
                                       "log unknown)\n")


def test_a_garbled_header_loses_every_chunk_and_the_summary_counts_them(damaged: Damaged, tmp_path: Path,
                                                                        capsys: pytest.CaptureFixture[str]) -> None:
    chunks = chunks_of(damaged.original)
    contents = [chunk_messages(damaged.original, c) for c in chunks]
    seconds = sum(max(x.log_time for x in inside) - min(x.log_time for x in inside) for inside in contents) * 1e-9
    data = bytearray(damaged.original.read_bytes())
    data[8:24] = b"\xff" * 16   # the Header record's opcode and length, right after the magic
    bad = tmp_path / "header.mcap"
    bad.write_bytes(bytes(data))
    assert main(["info", str(bad), "--json"]) == 1   # nothing readable: exit 1, as before
    line = (f"{bad} is damaged: skipped {len(chunks)} unreadable chunks after byte 8 of {len(data)} "
            f"({damaged.total} messages, {seconds:.2f} s of log)")
    out, err = capsys.readouterr()
    assert err == f"trundle info: {line}\n"
    entry = json.loads(out)["log_damage"]
    assert (entry["torn_after_byte"], entry["chunks_after_tear"], entry["messages_lost"], entry["said"]) == (
        8, len(chunks), damaged.total, line)


def test_slam_says_it_and_its_report_records_it(damaged: Damaged, tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["slam", str(damaged.bad), "-o", str(tmp_path / "bad")]) == 0
    said(capsys, "slam", damaged)
    report = json.loads((tmp_path / "bad" / "report.json").read_text())
    recorded(report["log_damage"], damaged)
    assert report["scans"] == damaged.per_topic["/scan"] - damaged.lost["/scan"]
    assert main(["slam", str(damaged.original), "-o", str(tmp_path / "intact")]) == 0
    silent(capsys)
    report = json.loads((tmp_path / "intact" / "report.json").read_text())
    assert report["log_damage"] is None and report["scans"] == damaged.per_topic["/scan"]
    assert main(["slam", str(damaged.bad), "--estimator", "ekf", "-o", str(tmp_path / "ekf")]) == 0
    said(capsys, "slam", damaged)
    recorded(json.loads((tmp_path / "ekf" / "report.json").read_text())["log_damage"], damaged)


def test_localize_says_it_and_its_report_records_it(damaged: Damaged, tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["slam", str(damaged.original), "-o", str(tmp_path / "map")]) == 0
    capsys.readouterr()
    assert main(["localize", str(damaged.bad), "--map", str(tmp_path / "map"), "--json"]) == 0
    report = json.loads(said(capsys, "localize", damaged))
    recorded(report["log_damage"], damaged)
    assert report["scans"] == damaged.per_topic["/scan"] - damaged.lost["/scan"]
    assert main(["localize", str(damaged.original), "--map", str(tmp_path / "map"), "--json"]) == 0
    assert json.loads(silent(capsys))["log_damage"] is None


def test_replay_export_and_recover_say_it_and_do_their_job(damaged: Damaged, tmp_path: Path,
                                                           capsys: pytest.CaptureFixture[str]) -> None:
    kept = damaged.total - sum(damaged.lost.values())
    assert main(["replay", str(damaged.bad), "--rate", "0", "-o", str(tmp_path / "replayed.mcap")]) == 0
    assert f"replayed {kept} messages" in said(capsys, "replay", damaged)
    replayed = LogReader(tmp_path / "replayed.mcap").info()
    assert replayed.damage is None and replayed.message_count == kept
    recorded(read_metadata(replayed.metadata).fields["log_damage"], damaged)  # in the output, as in a report
    assert main(["export", str(damaged.bad), "--topic", "/odom", "-o", str(tmp_path / "odom.csv")]) == 0
    said(capsys, "export", damaged)
    with open(tmp_path / "odom.csv") as f:
        assert len(list(csv.DictReader(f))) == damaged.per_topic["/odom"] - damaged.lost["/odom"]
    assert main(["recover", str(damaged.bad), str(tmp_path / "fixed.mcap")]) == 0
    assert f"recovered {kept} messages" in said(capsys, "recover", damaged)
    assert main(["info", str(tmp_path / "fixed.mcap")]) == 0
    silent(capsys)
    for argv in (["replay", str(damaged.original), "--rate", "0", "-o", str(tmp_path / "intact.mcap")],
                 ["export", str(damaged.original), "--topic", "/odom", "-o", str(tmp_path / "all.csv")],
                 ["recover", str(damaged.original), str(tmp_path / "copy.mcap")]):
        assert main(argv) == 0
        silent(capsys)
    intact = LogReader(tmp_path / "intact.mcap").info().metadata["trundle"]["log_damage"]
    assert json.loads(intact) is None  # null, as a report's log_damage of an intact log


def test_characterize_says_it_and_its_report_records_it(damaged: Damaged, tmp_path: Path,
                                                        capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["characterize", str(damaged.bad), "--topic", "/scan", "-o", str(tmp_path / "bad")]) == 0
    said(capsys, "characterize", damaged)
    recorded(json.loads((tmp_path / "bad" / "report.json").read_text())["log_damage"], damaged)
    assert main(["characterize", str(damaged.original), "--topic", "/scan", "-o", str(tmp_path / "intact")]) == 0
    silent(capsys)
    assert json.loads((tmp_path / "intact" / "report.json").read_text())["log_damage"] is None


def test_inject_faults_says_it_and_writes_an_intact_copy(damaged: Damaged, tmp_path: Path,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "faulty.mcap"
    assert main(["inject-faults", str(damaged.bad), "--scale", "0.02", "-o", str(out), "--json"]) == 0
    report = json.loads(said(capsys, "inject-faults", damaged))
    recorded(report["log_damage"], damaged)
    assert report["topics"]["/odom"]["messages"] == damaged.per_topic["/odom"] - damaged.lost["/odom"]
    assert LogReader(out).info().damage is None
    assert main(["inject-faults", str(damaged.original), "--scale", "0.02", "-o", str(tmp_path / "f2.mcap"),
                 "--json"]) == 0
    assert json.loads(silent(capsys))["log_damage"] is None


def test_perceive_says_it_and_its_summary_records_it(damaged: Damaged, tmp_path: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["--pipeline", "features", "--no-images", "--json"]
    assert main(["perceive", str(damaged.bad), "-o", str(tmp_path / "bad.mcap"), *argv]) == 0
    summary = json.loads(said(capsys, "perceive", damaged))
    recorded(summary["log_damage"], damaged)
    assert summary["frames"] == damaged.per_topic[IMAGE_TOPIC] - damaged.lost[IMAGE_TOPIC]
    assert main(["perceive", str(damaged.original), "-o", str(tmp_path / "intact.mcap"), *argv]) == 0
    assert json.loads(silent(capsys))["log_damage"] is None


def test_fleet_rows_results_reports_and_summary_record_it(damaged: Damaged, tmp_path: Path) -> None:
    rows = []
    for log in (damaged.bad, damaged.original):
        row = process_log(Task("slam", str(log), log.stem, str(tmp_path), {}, options_key("slam", {})))
        assert row["status"] == "ok", row["error"]
        rows.append(row)
    assert rows[0]["log_damage"] == damaged.line and rows[1]["log_damage"] is None
    assert not any(name.startswith(("log_damage.", "report.log_damage")) for row in rows for name in row)
    recorded(json.loads((tmp_path / "bad" / "report.json").read_text())["log_damage"], damaged)
    assert json.loads((tmp_path / "drive" / "report.json").read_text())["log_damage"] is None
    page = markdown("slam", rows, {}, None)
    assert f"| {damaged.bad} | ok | {damaged.line} |" in page.splitlines()
    damaged_section = page.split("## Damaged logs")[1].split("\n## ")[0]
    assert str(damaged.original) not in damaged_section
    with open(write_csv(rows, tmp_path / "results.csv")) as f:
        assert [row["log_damage"] for row in csv.DictReader(f)] == [damaged.line, ""]


def test_the_daemon_says_what_it_could_not_salvage_of_a_crash_file(damaged: Damaged, tmp_path: Path,
                                                                   capsys: pytest.CaptureFixture[str]) -> None:
    crash = tmp_path / "logs" / "run.mcap.active"
    crash.parent.mkdir()
    shutil.copyfile(damaged.bad, crash)
    with Running(config(tmp_path)) as run:
        wait_for(lambda: run.daemon.logger is not None)
    err = capsys.readouterr().err
    said = [x for x in err.splitlines() if x.startswith("trundle daemon: recovered")]
    lost = sum(damaged.lost.values())
    assert len(said) == 1 and f"from {crash.name} into " in said[0], said
    assert re.search(rf"; skipped 1 corrupt chunks \({lost} messages, [0-9.]+ s of log\)", said[0]), said
    assert LogReader(tmp_path / "logs" / "run.mcap").info().message_count == damaged.total - sum(damaged.lost.values())


@pytest.fixture(scope="module")
def small_log(tmp_path_factory: pytest.TempPathFactory) -> tuple[bytes, int]:
    """A small log of 4 KiB chunks (its bytes) and its message count."""
    path = tmp_path_factory.mktemp("small") / "small.mcap"
    with Logger(path, chunk_size=4096, salvage=False) as logger:
        for i in range(120):
            ranges = np.random.default_rng(i).uniform(0.5, 9.0, 101)
            logger.write("/scan", m.LaserScan(i, "laser", -1, 1, 0.02, 0, 0, 0.1, 10, ranges), i * 10**8)
            if i % 3 == 0:
                logger.write("/odom", m.Odometry(i, "odom", "base_link", 0.1 * i, 0, 0), i * 10**8)
    return path.read_bytes(), 160


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(where=st.floats(0.0, 1.0), length=st.integers(1, OVERWRITTEN), seed=st.integers(0, 2**32 - 1))
@example(where=0.5233134980768993, length=1, seed=0)   # a record length overwritten: the pass jumps 8 chunks
@example(where=0.9669126075006913, length=1, seed=0)   # a chunk's offset in the summary overwritten
@example(where=0.9933824141435648, length=1, seed=1)   # ... to one beyond what a file can have
def test_any_overwrite_is_read_and_its_damage_adds_up(small_log: tuple[bytes, int], tmp_path: Path, where: float,
                                                      length: int, seed: int) -> None:
    data, count = bytearray(small_log[0]), small_log[1]
    at = int(where * (len(data) - 1))
    data[at:at + length] = np.random.default_rng(seed).bytes(len(data[at:at + length]))
    path = tmp_path / "overwritten.mcap"
    path.write_bytes(bytes(data))
    try:
        reader = LogReader(path)
        info = reader.info()
        read = sum(1 for _ in reader.raw_messages())
    except DataError:   # the magic bytes were hit: refused in one line, not read
        assert at < 8
        return
    damage = reader.last_damage
    assert damage == info.damage
    assert read == info.message_count
    if damage is None:
        assert read == count
        return
    assert "\n" not in damage.line()
    assert damage.seconds is None or damage.seconds >= 0.0
    if damage.messages is not None:
        assert read + damage.messages == count


def test_a_record_length_that_jumps_over_intact_chunks_counts_them_as_lost(damaged: Damaged, tmp_path: Path,
                                                                           capsys: pytest.CaptureFixture[str]) -> None:
    """An overwritten length makes a linear reader skip the chunks behind it: the summary still lists them."""
    chunks = chunks_of(damaged.original)
    garbled = min(chunks[1].message_index_offsets.values())   # chunk 1's first MessageIndex record
    assert garbled == chunks[1].chunk_start_offset + chunks[1].chunk_length
    jumped = [chunk_messages(damaged.original, c) for c in chunks[2:4]]
    assert chunks[3].message_start_time >= chunks[2].message_end_time   # the spans add up without overlap
    seconds = sum(c.message_end_time - c.message_start_time for c in chunks[2:4]) * 1e-9
    data = bytearray(damaged.original.read_bytes())
    data[garbled + 1:garbled + 9] = (chunks[4].chunk_start_offset - garbled - 9).to_bytes(8, "little")
    bad = tmp_path / "jump.mcap"
    bad.write_bytes(bytes(data))
    lost = sum(len(inside) for inside in jumped)
    assert main(["info", str(bad), "--json"]) == 0
    line = (f"{bad} is damaged: skipped 2 unreadable chunks after byte {garbled} of {len(data)} "
            f"({lost} messages, {seconds:.2f} s of log)")
    out, err = capsys.readouterr()
    assert err == f"trundle info: {line}\n"
    assert json.loads(out)["messages"] == damaged.total - lost
    assert sum(1 for _ in LogReader(bad).raw_messages()) == damaged.total - lost


def test_a_chunk_whose_opcode_was_overwritten_is_counted_as_lost(damaged: Damaged, tmp_path: Path,
                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    """A reader skips a record of an unknown opcode (0x80 and up are private records): here that is a chunk."""
    chunk = chunks_of(damaged.original)[2]
    lost = len(chunk_messages(damaged.original, chunk))
    data = bytearray(damaged.original.read_bytes())
    data[chunk.chunk_start_offset] = 0x80
    bad = tmp_path / "opcode.mcap"
    bad.write_bytes(bytes(data))
    assert main(["info", str(bad)]) == 0
    seconds = (chunk.message_end_time - chunk.message_start_time) * 1e-9
    assert capsys.readouterr().err == (
        f"trundle info: {bad} is damaged: skipped 1 unreadable chunk after byte {chunk.chunk_start_offset} of "
        f"{len(data)} ({lost} messages, {seconds:.2f} s of log)\n")
    assert sum(1 for _ in LogReader(bad).raw_messages()) == damaged.total - lost
