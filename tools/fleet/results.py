"""The results table of a fleet run: ``results.csv`` (and ``results.parquet`` when pyarrow is
installed) with one row per log, and ``run.json`` with the run's own figures.

Each column of the Parquet file has one type: booleans, 64-bit integers, doubles (a column
mixing integers and floats), or text (anything else).
"""

from __future__ import annotations

import csv
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from trundle import __version__
from trundle.logs.outputs import write_json, writing_file
from trundle.tools.fleet.rows import columns


def _replace(path: Path, write: Any) -> Path:
    """Write ``path`` (the run's own, replaced each run) through a temporary file, so a reader never
    sees half a table (:func:`trundle.logs.outputs.writing_file`)."""
    with writing_file(path, replace=True) as tmp:
        write(tmp)
    return path


def write_csv(rows: Sequence[Mapping[str, Any]], path: Path) -> Path:
    """``rows`` as CSV with a header of :func:`trundle.tools.fleet.rows.columns` (empty cells for
    missing values)."""
    names = columns(list(rows))

    def write(tmp: Path) -> None:
        with open(tmp, "w", newline="") as f:
            writer = csv.DictWriter(f, names, restval="")
            writer.writeheader()
            writer.writerows({k: ("" if v is None else v) for k, v in row.items()} for row in rows)
    return _replace(path, write)


def _arrow_type(values: list[Any]) -> Any:
    import pyarrow as pa

    present = [v for v in values if v is not None]
    if present and all(isinstance(v, bool) for v in present):
        return pa.bool_()
    if present and all(isinstance(v, int) and not isinstance(v, bool) for v in present):
        return pa.int64()
    if present and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in present):
        return pa.float64()
    return pa.string()


def write_parquet(rows: Sequence[Mapping[str, Any]], path: Path) -> Path | None:
    """``rows`` as a Parquet file (None, writing nothing, when pyarrow is not installed)."""
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError:
        return None
    arrays, names = [], columns(list(rows))
    for name in names:
        values = [row.get(name) for row in rows]
        kind = _arrow_type(values)
        if kind == pa.string():
            values = [None if v is None else str(v) for v in values]
        elif kind == pa.float64():
            values = [None if v is None else float(v) for v in values]
        arrays.append(pa.array(values, type=kind))
    return _replace(path, lambda tmp: pq.write_table(pa.table(arrays, names=names), tmp))


def write_run(figures: Mapping[str, Any], path: Path) -> Path:
    """The run's own figures (job, options, counts, seconds, CPUs, logs per minute) as JSON."""
    return write_json(path, {**figures, "trundle_version": __version__}, replace=True)
