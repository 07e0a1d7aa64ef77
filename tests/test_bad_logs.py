"""Damaged or foreign files: one clear line or the intact part salvaged, never a traceback."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from trundle.logs import messages as m
from trundle.logs.reader import LogReader
from trundle.logs.writer import Logger
from trundle.tools.cli.main import main


def make_log(path: Path, n: int = 200, **kwargs) -> None:
    with Logger(path, chunk_size=4096, **kwargs) as logger:
        for i in range(n):
            logger.write("/scan", m.LaserScan(i, "laser", -1, 1, 0.01, 0, 0, 0, 10, np.full(201, i % 10)), i)


def one_line_error(capsys: pytest.CaptureFixture[str], *words: str) -> None:
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1, err
    assert "Traceback" not in err
    for w in words:
        assert w in err


@pytest.mark.parametrize("command", ["info", "recover", "replay"])
def test_not_mcap_and_empty_and_missing(tmp_path: Path, capsys: pytest.CaptureFixture[str], command: str) -> None:
    text = tmp_path / "notes.txt"
    text.write_text("hello, not a log\n")
    empty = tmp_path / "empty.mcap"
    empty.touch()
    assert main([command, str(text)]) == 2
    one_line_error(capsys, "not an MCAP file")
    assert main([command, str(empty)]) == 2
    one_line_error(capsys, "is empty")
    assert main([command, str(tmp_path / "missing.mcap")]) == 2
    one_line_error(capsys, "no such MCAP log")


def test_file_cut_mid_record_is_salvaged(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "run.mcap"
    make_log(path, compression="none")
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2 + 7])
    msgs = list(LogReader(cut).messages())
    assert 0 < len(msgs) < 200
    assert [x.log_time_ns for x in msgs] == list(range(len(msgs)))  # intact prefix, in order
    assert main(["info", str(cut)]) == 0
    assert "INCOMPLETE" in capsys.readouterr().out
    fixed = tmp_path / "fixed.mcap"
    assert main(["recover", str(cut), str(fixed)]) == 0
    assert f"recovered {len(msgs)} messages" in capsys.readouterr().out
    assert LogReader(fixed).info().complete


@pytest.mark.parametrize("compression", ["none", "zstd"])
def test_corrupt_chunk_is_skipped_and_counted(tmp_path: Path, compression: str) -> None:
    path = tmp_path / "run.mcap"
    make_log(path, compression=compression)
    whole = LogReader(path).info()
    assert whole.chunks > 4
    with open(path, "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    target = chunks[len(chunks) // 2]
    data = bytearray(path.read_bytes())
    middle = target.chunk_start_offset + target.chunk_length // 2
    for i in range(middle, middle + 40):  # scribble inside one chunk's payload
        data[i] ^= 0x5A
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    info = LogReader(bad).info()
    assert info.corrupt_chunks == 1 and not info.complete
    got = [x.log_time_ns for x in LogReader(bad).messages()]
    assert 100 < len(got) < 200 and got == sorted(got)
    assert set(got) < set(range(200))


def test_unknown_schema_is_listed_but_not_decoded(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "foreign.mcap"
    with open(path, "wb") as f:
        w = Writer(f, compression=CompressionType.NONE)
        w.start(profile="ros2", library="other")
        sid = w.register_schema("acme_msgs/msg/Widget", "ros2msg", b"int32 x\n")
        cid = w.register_channel("/widget", "cdr", sid)
        for i in range(3):
            w.add_message(cid, i, b"\x00\x01\x00\x00" + i.to_bytes(4, "little"), i)
        w.finish()
    info = LogReader(path).info()
    assert info.topics["/widget"].ros_type == "acme_msgs/msg/Widget" and info.topics["/widget"].count == 3
    assert list(LogReader(path).messages()) == []
    assert len(list(LogReader(path).raw_messages())) == 3
    assert main(["export", str(path), "--topic", "/widget"]) == 2
    one_line_error(capsys, "/widget")


def test_recover_with_nothing_readable_fails_clearly(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "stub.mcap"
    path.write_bytes(b"\x89MCAP0\r\n\x01\x05")
    assert main(["recover", str(path), str(tmp_path / "out.mcap")]) == 2
    one_line_error(capsys, "nothing could be recovered")
