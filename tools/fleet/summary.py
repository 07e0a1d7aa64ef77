"""The fleet summary over the rows: ``summary.md`` (counts, failed logs, damaged logs, checks that
failed, figures per robot) and ``summary.png`` (the headline figures of each log over the log's start
time, one series per robot: e.g. a laser whose noise drifts up, SLAM runs whose residual jumps).

Headline figures are the numeric columns the job's report has, those matching the job's
preferred names first (:data:`PREFERRED`, substrings so a renamed or added figure still
matches), then others that vary between logs, at most :data:`PANELS`. A boolean figure that is
false for some logs (a consistency check, a completeness flag) is listed as a failed check; a figure
that says ``not checked`` for some logs (the map self-check of a short or stationary log: nothing to
compare) as a check not made, neither passed nor failed.
"""

from __future__ import annotations

import statistics
from collections.abc import Mapping, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from trundle.fusion.mapping.map_check import NOT_CHECKED
from trundle.logs.outputs import save_figure, write_text
from trundle.tools.fleet.rows import COLUMNS, columns

PREFERRED = {
    "slam": ("consisten", "real_time_factor", "loop_closures", "scan_to_map_residual_m.mean", "path_length_m"),
    "characterize": ("noise", "bias", "precision", "accuracy", "rate"),
    "localize": ("converged", "false_alarms", "match_score_tracking.mean", "real_time_factor"),
    "perceive": ("detections_per_frame.mean", "frames", "corrupt_messages"),
    "info": ("duration_s", "messages", "corrupt_chunks", "size_bytes"),
}
PANELS = 6
SKIP_PREFIXES = ("config.", "class.", "report.")
STAMP_SUFFIX = "_ns"            # an absolute time (start_ns, end_ns), not a figure to plot or take a median of
DESCRIPTIVE = (".latched",)     # booleans that describe a log (a latched topic), not checks that can fail
EARLIEST = datetime(2000, 1, 1, tzinfo=UTC)   # a log "starting" before this has no wall-clock stamps (an import)
LISTED = 20   # at most this many logs named per table


def _numeric(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def headline(job: str, rows: Sequence[Mapping[str, Any]]) -> list[str]:
    """The figure columns to plot for ``job`` (see the module doc)."""
    candidates = [c for c in columns(list(rows)) if c not in COLUMNS and not c.startswith(SKIP_PREFIXES)
                  and not c.endswith(STAMP_SUFFIX) and any(_numeric(r.get(c)) for r in rows)]
    chosen = [c for pattern in PREFERRED.get(job, ()) for c in candidates if pattern in c]
    chosen = list(dict.fromkeys(chosen))
    chosen += [c for c in candidates if c not in chosen and len({r.get(c) for r in rows if _numeric(r.get(c))}) > 1]
    return chosen[:PANELS]


def failed_checks(rows: Sequence[Mapping[str, Any]]) -> dict[str, list[str]]:
    """Boolean figure -> the logs it is false for (only figures false somewhere; not the booleans that
    describe a log, :data:`DESCRIPTIVE`)."""
    checks: dict[str, list[str]] = {}
    for name in columns(list(rows)):
        if name in COLUMNS or name.endswith(DESCRIPTIVE):
            continue
        values = [(r["log"], r.get(name)) for r in rows if isinstance(r.get(name), bool)]
        false = [log for log, v in values if v is False]
        if values and false:
            checks[name] = false
    return checks


def not_checked(rows: Sequence[Mapping[str, Any]]) -> dict[str, list[str]]:
    """Figure -> the logs it says ``not checked`` for (only figures that say it somewhere)."""
    checks: dict[str, list[str]] = {}
    for name in columns(list(rows)):
        logs = [r["log"] for r in rows if r.get(name) == NOT_CHECKED]
        if name not in COLUMNS and logs:
            checks[name] = logs
    return checks


def _when(row: Mapping[str, Any]) -> datetime | None:
    try:
        return datetime.fromisoformat(row["log_start"]) if row.get("log_start") else None
    except ValueError:
        return None


def summary_figure(job: str, rows: Sequence[Mapping[str, Any]]) -> Figure | None:
    """The figure of ``summary.png``: each headline figure over log start time, one line per robot
    (None without figures to plot).

    When a log's start is no wall-clock time (before :data:`EARLIEST`: an imported dataset's stamps
    count from 0), the figures are plotted over the logs in their order instead, named on the axis.
    """
    names = headline(job, rows)
    timed = [r for r in rows if _when(r) is not None]
    if not names or not timed:
        return None
    clock = all(when >= EARLIEST for r in timed if (when := _when(r)) is not None)
    order = {id(r): k for k, r in enumerate(timed)}

    def x(row: Mapping[str, Any]) -> Any:
        return _when(row) if clock else order[id(row)]

    robots = sorted({r.get("robot") or "unknown" for r in timed})
    fig = Figure(figsize=(9, 2.2 * len(names) + 1.0), dpi=100, layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(len(names), 1, sharex=True, squeeze=False)[:, 0]
    for ax, name in zip(axes, names, strict=True):
        for robot in robots:
            points = sorted((x(r), r[name]) for r in timed
                            if (r.get("robot") or "unknown") == robot and _numeric(r.get(name)))
            if points:
                ax.plot([p[0] for p in points], [p[1] for p in points], "o-", ms=3, lw=0.8, label=robot)
        ax.set_ylabel(name, fontsize=8)
        ax.grid(alpha=0.3)
    if clock:
        axes[0].set_title(f"trundle fleet {job}: figures per log over the log's start time (UTC)")
        axes[-1].set_xlabel("log start (UTC)")
        for label in axes[-1].get_xticklabels():
            label.set(rotation=30, horizontalalignment="right")
    else:
        axes[0].set_title(f"trundle fleet {job}: figures per log (in the order given: "
                          "some logs have no wall-clock start time)")
        axes[-1].set_xlabel("log")
        axes[-1].set_xticks(range(len(timed)), [str(r.get("name") or r["log"]) for r in timed], rotation=30,
                            horizontalalignment="right", fontsize=7)
    if len(robots) <= 12:
        axes[0].legend(fontsize=7, loc="best", title="robot", title_fontsize=7)
    return fig


def plot(job: str, rows: Sequence[Mapping[str, Any]], path: Path) -> Path | None:
    """``summary.png`` (:func:`summary_figure`; None without figures)."""
    fig = summary_figure(job, rows)
    if fig is None:
        return None
    save_figure(fig, path, dpi=100, replace=True)
    return path


def _cell(value: Any) -> str:
    if value is None:
        return "-"
    return f"{value:.4g}" if isinstance(value, float) else str(value).replace("|", "\\|")


def markdown(job: str, rows: Sequence[Mapping[str, Any]], run: Mapping[str, Any], picture: str | None) -> str:
    """The summary page for ``rows`` of a run of ``job`` (``run``: the figures of ``run.json``)."""
    counts = {s: sum(r["status"] == s for r in rows) for s in ("ok", "failed", "skipped", "cancelled")}
    lines = [f"# trundle fleet {job}: {len(rows)} logs", "",
             f"{counts['ok']} ok, {counts['failed']} failed, {counts['skipped']} skipped, {counts['cancelled']} "
             f"cancelled in {run.get('wall_s', 0.0):.1f} s (Ray's start {run.get('ray_start_s', 0.0):.1f} s; the logs "
             f"{run.get('elapsed_s', 0.0):.1f} s on {run.get('cpus', 0):g} CPUs, "
             f"{run.get('logs_per_minute', 0.0):.1f} logs per minute); job options: {run.get('options') or 'none'}.",
             ""]
    failed = [r for r in rows if r["status"] in ("failed", "cancelled")]
    if failed:
        lines += ["## Logs without a result", "", "| log | status | error |", "|---|---|---|"]
        lines += [f"| {_cell(r['log'])} | {r['status']} | {_cell(r.get('error'))} |" for r in failed[:LISTED]]
        lines += [f"| ... {len(failed) - LISTED} more in results.csv | | |"] if len(failed) > LISTED else []
        lines.append("")
    damaged = [r for r in rows if r.get("log_damage")]
    if damaged:
        lines += ["## Damaged logs (read what was intact)", "", "| log | status | what was skipped |", "|---|---|---|"]
        lines += [f"| {_cell(r['log'])} | {r['status']} | {_cell(r['log_damage'])} |" for r in damaged[:LISTED]]
        lines += [f"| ... {len(damaged) - LISTED} more in results.csv | | |"] if len(damaged) > LISTED else []
        lines.append("")
    done = [r for r in rows if r["status"] in ("ok", "skipped")]
    checks = failed_checks(done)
    if checks:
        lines += ["## Checks that failed", "", "| figure | false for | logs |", "|---|---|---|"]
        lines += [f"| {name} | {len(logs)} of {sum(isinstance(r.get(name), bool) for r in done)} | "
                  f"{_cell(', '.join(logs[:LISTED]))} |" for name, logs in checks.items()]
        lines.append("")
    unchecked = not_checked(done)
    if unchecked:
        lines += ["## Checks not made", ""]
        lines += [f"- {name}: not checked for {len(logs)} of {len(done)} logs (nothing to compare): "
                  f"{', '.join(logs[:LISTED])}" for name, logs in unchecked.items()]
        lines.append("")
    names = headline(job, done)
    if done:
        lines += ["## Per robot (medians over its logs)", "",
                  "| robot | logs | hours of log | " + " | ".join(names) + " |",
                  "|---|---|---|" + "---|" * len(names)]
        for robot in sorted({r.get("robot") or "unknown" for r in done}):
            mine = [r for r in done if (r.get("robot") or "unknown") == robot]
            hours = sum(r.get("log_duration_s") or 0.0 for r in mine) / 3600
            medians = [_cell(statistics.median(v)) if (v := [r[n] for r in mine if _numeric(r.get(n))]) else "-"
                       for n in names]
            lines.append(f"| {_cell(robot)} | {len(mine)} | {hours:.3g} | " + " | ".join(medians) + " |")
        lines.append("")
    if picture:
        lines += ["## Figures over time", "", f"![figures per log over time]({picture})", ""]
    lines.append("Every figure of every log: results.csv (one row per log); each log's outputs: <name>/.")
    return "\n".join(lines) + "\n"


def write_summary(job: str, rows: Sequence[Mapping[str, Any]], run: Mapping[str, Any], folder: Path) -> list[Path]:
    """Write ``summary.md`` (and ``summary.png`` when there are figures to plot) into ``folder``."""
    picture = plot(job, [r for r in rows if r["status"] in ("ok", "skipped")], folder / "summary.png")
    page = folder / "summary.md"
    write_text(page, markdown(job, rows, run, picture.name if picture else None), replace=True)
    return [page] + ([picture] if picture else [])
