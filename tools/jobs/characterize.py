"""The characterize job: a sensor's characteristics from one log topic -> figures, plots, report.

The topic's type says what the sensor is (LaserScan: laser; JointState: wheel encoders;
CompressedImage/Image: camera). Figures are in SI units.
"""

from __future__ import annotations

import csv
import io
from pathlib import Path
from typing import Any, cast

import numpy as np

from trundle.logs import messages as m
from trundle.logs.errors import UserError
from trundle.logs.outputs import plain, write_json, write_text, writing_folder
from trundle.logs.paths import output_folder, read_text
from trundle.logs.reader import LogReader, damage_dict
from trundle.tools.jobs.sensor_figures import characterize_camera, characterize_encoders, characterize_laser
from trundle.tools.jobs.sensor_report import markdown, write_plots

Characterized = m.LaserScan | m.JointState | m.CompressedImage | m.Image  # the sensors characterize knows


def read_reference(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(t_ns, value) sorted by time from a CSV with a header naming t_ns or t_s, and value.

    A bad file is a UserError."""
    rows = list(csv.DictReader(io.StringIO(read_text(path, "reference CSV"))))
    if not rows or "value" not in rows[0] or not ({"t_ns", "t_s"} & set(rows[0])):
        raise UserError(f"reference {path} needs a header with t_ns (or t_s) and value columns")
    try:
        t = np.array([int(r["t_ns"]) if "t_ns" in r else round(float(r["t_s"]) * 1e9) for r in rows], np.int64)
        v = np.array([float(r["value"]) for r in rows])
    except (TypeError, ValueError, OverflowError):
        row = next((i for i, r in enumerate(rows, 2) if None in r.values() or "" in r.values()), None)
        where = f" (line {row} is short)" if row else ""
        raise UserError(f"reference {path}: every row needs a time and a number{where}") from None
    order = np.argsort(t)
    return t[order], v[order]


def constant_reference(stamps_ns: np.ndarray, value: float) -> tuple[np.ndarray, np.ndarray]:
    """A reference that is ``value`` at every one of ``stamps_ns`` (a target at a known, fixed distance)."""
    return np.asarray(stamps_ns, np.int64), np.full(len(stamps_ns), float(value))


def characterize_log(log: str | Path, topic: str, output: Path | None = None, reference: Path | float | None = None,
                     beam: int | str = "all", stated_min: float | None = None, stated_max: float | None = None,
                     bits: int | None = None, min_still_s: float = 1.0) -> dict[str, Any]:
    """The characteristics of the sensor on ``topic`` of ``log``; with ``output``, also written there
    (folder, created) as ``report.md``, ``report.json`` and PNG plots.

    ``reference`` is the true value that laser ``beam`` (an index or ``"all"``) is compared with:
    a CSV of values over time (see :func:`read_reference`) or one number (m, held throughout);
    ``stated_min`` / ``stated_max`` the device's stated limits (default: from the messages);
    ``bits`` its A/D bits; ``min_still_s`` the shortest standing-still stretch used (s). Returns
    the figures (JSON-able; what report.json holds) and ``log_damage``: what the log's damage
    skipped (None when intact).
    """
    reader = LogReader(log)
    if output:
        output_folder(output, empty=False, create=False)  # checked before the work
    info = reader.info()
    if topic not in info.topics:
        raise UserError(f"topic {topic} is not in {log} (topics: {', '.join(sorted(info.topics))})")
    # a topic carries one message type, the first one's; other types are refused below
    msgs = cast(list[Characterized], [x.msg for x in reader.messages([topic])])
    damage = damage_dict(reader.last_damage)
    if len(msgs) < 3:
        raise UserError(f"topic {topic} has {len(msgs)} decodable messages; at least 3 are needed")
    truth: tuple[np.ndarray, np.ndarray] | None
    if isinstance(reference, (int, float)):
        truth = constant_reference(np.array([x.stamp_ns for x in msgs], np.int64), reference)
    else:
        truth = read_reference(reference) if reference else None
    first = msgs[0]
    if isinstance(first, m.LaserScan):
        figures, plots = characterize_laser(cast(list[m.LaserScan], msgs), reader, truth, stated_min, stated_max,
                                            bits, min_still_s, beam)
    elif isinstance(first, m.JointState):
        figures, plots = characterize_encoders(cast(list[m.JointState], msgs))
    elif isinstance(first, (m.CompressedImage, m.Image)):
        figures, plots = characterize_camera(np.array([x.stamp_ns for x in msgs], np.int64))
    else:
        raise UserError(f"{topic} carries {info.topics[topic].ros_type}: not a laser, encoder or camera topic")
    figures = {**plain(figures), "log_damage": damage}
    if output:
        with writing_folder(output, empty=False):  # every file or, on any failure, none
            names = write_plots(output, plots)
            write_json(output / "report.json", figures)
            write_text(output / "report.md", markdown(figures, topic, names))
    return figures
