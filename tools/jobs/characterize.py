"""The characterize job: a sensor's characteristics from one log topic -> figures, plots, report.

The topic's type says what the sensor is (LaserScan: laser; JointState: wheel encoders;
CompressedImage/Image: camera). Figures are in SI units.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

import numpy as np

from trundle.logs import messages as m
from trundle.logs.errors import UserError
from trundle.logs.reader import LogReader
from trundle.tools.jobs.sensor_figures import characterize_camera, characterize_encoders, characterize_laser
from trundle.tools.jobs.sensor_report import markdown, write_plots


def read_reference(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(t_ns, value) sorted by time from a CSV with a header naming t_ns or t_s, and value; a bad file is a UserError."""
    try:
        with open(path, newline="") as f:
            rows = list(csv.DictReader(f))
    except OSError as error:
        raise UserError(f"cannot read reference {path}: {error.strerror}") from None
    if not rows or "value" not in rows[0] or not ({"t_ns", "t_s"} & set(rows[0])):
        raise UserError(f"reference {path} needs a header with t_ns (or t_s) and value columns")
    try:
        t = np.array([int(r["t_ns"]) if "t_ns" in r else round(float(r["t_s"]) * 1e9) for r in rows], np.int64)
        v = np.array([float(r["value"]) for r in rows])
    except ValueError as error:
        raise UserError(f"reference {path}: {error}") from None
    order = np.argsort(t)
    return t[order], v[order]


def _jsonable(value: Any) -> Any:
    """``value`` with numpy scalars as Python numbers and non-finite floats as None (JSON null)."""
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, float) and not np.isfinite(value):
        return None
    if isinstance(value, np.generic):
        return _jsonable(value.item())
    return value


def characterize_log(log: str | Path, topic: str, output: Path | None = None, reference: Path | None = None,
                     beam: int | str = "all", stated_min: float | None = None, stated_max: float | None = None,
                     bits: int | None = None, min_still_s: float = 1.0) -> dict[str, Any]:
    """The characteristics of the sensor on ``topic`` of ``log``; with ``output``, also written there
    (folder, created) as ``report.md``, ``report.json`` and PNG plots.

    ``reference`` is a CSV of true values over time (see :func:`read_reference`) that laser
    ``beam`` (an index or ``"all"``) is compared with; ``stated_min`` / ``stated_max`` the device's
    stated limits (default: from the messages); ``bits`` its A/D bits; ``min_still_s`` the
    shortest standing-still stretch used (s). Returns the figures (JSON-able; what report.json holds).
    """
    reader = LogReader(log)
    info = reader.info()
    if topic not in info.topics:
        raise UserError(f"topic {topic} is not in {log} (topics: {', '.join(sorted(info.topics))})")
    msgs = [x.msg for x in reader.messages([topic])]
    if len(msgs) < 3:
        raise UserError(f"topic {topic} has {len(msgs)} decodable messages; at least 3 are needed")
    truth = read_reference(reference) if reference else None
    first = msgs[0]
    if isinstance(first, m.LaserScan):
        figures, plots = characterize_laser(msgs, reader, truth, stated_min, stated_max, bits,  # type: ignore[arg-type]
                                            min_still_s, beam)
    elif isinstance(first, m.JointState):
        figures, plots = characterize_encoders(msgs)  # type: ignore[arg-type]
    elif isinstance(first, (m.CompressedImage, m.Image)):
        figures, plots = characterize_camera(np.array([x.stamp_ns for x in msgs], np.int64))
    else:
        raise UserError(f"{topic} carries {info.topics[topic].ros_type}: not a laser, encoder or camera topic")
    figures = _jsonable(figures)
    if output:
        output.mkdir(parents=True, exist_ok=True)
        names = write_plots(output, plots)
        (output / "report.json").write_text(json.dumps(figures, indent=2))
        (output / "report.md").write_text(markdown(figures, topic, names))
    return figures
