"""`trundle export` as a user meets it: nested messages flattened to columns in CSV (no Python
repr), NaN as null in NDJSON, and a wrong --topic answered with the log's topics."""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path

import numpy as np
import pytest

from trundle.logs import messages as m
from trundle.logs.writer import Logger
from trundle.tools.cli.main import main


@pytest.fixture()
def log(tmp_path: Path) -> Path:
    path = tmp_path / "run.mcap"
    with Logger(path, salvage=False) as logger:
        logger.write("/diagnostics", m.DiagnosticArray(1, (m.DiagnosticStatus(0, "lrf", "ok", "", (("rate", "10"),)),)),
                     1)
        logger.write("/diagnostics", m.DiagnosticArray(2, (
            m.DiagnosticStatus(1, "lrf", "slow", "", (("rate", "2"), ("drops", "3"))),
            m.DiagnosticStatus(0, "can", "ok"))), 2)
        logger.write("/scan", m.LaserScan(3, "laser", -0.5, 0.5, 0.5, 0.0, 0.1, 0.1, 10.0,
                                          np.array([1.0, np.nan, np.inf]), np.zeros(0)), 3)
    return path


def test_csv_flattens_nested_messages_into_columns(log: Path, capsys) -> None:
    assert main(["export", str(log), "--topic", "/diagnostics"]) == 0
    rows = list(csv.reader(io.StringIO(capsys.readouterr().out)))
    assert rows[0] == ["log_time_ns", "stamp_ns", "status.0.level", "status.0.name", "status.0.message",
                       "status.0.hardware_id", "status.0.values.0.key", "status.0.values.0.value",
                       "status.0.values.1.key", "status.0.values.1.value", "status.1.level", "status.1.name",
                       "status.1.message", "status.1.hardware_id"]
    assert rows[1] == ["1", "1", "0", "lrf", "ok", "", "rate", "10", "", "", "", "", "", ""]
    assert rows[2] == ["2", "2", "1", "lrf", "slow", "", "rate", "2", "drops", "3", "0", "can", "ok", ""]
    assert len(rows) == 3


def test_ndjson_writes_non_finite_numbers_as_null(log: Path, capsys) -> None:
    assert main(["export", str(log), "--topic", "/scan", "--format", "ndjson"]) == 0
    line = capsys.readouterr().out.strip()
    assert json.loads(line)["ranges"] == [1.0, None, None]
    assert "NaN" not in line and "Infinity" not in line and '"nan"' not in line


def test_a_wrong_topic_lists_the_topics(log: Path, capsys) -> None:
    assert main(["export", str(log), "--topic", "/odom"]) == 2
    assert capsys.readouterr().err == f"trundle export: {log} has no topic /odom (topics: /diagnostics, /scan)\n"
