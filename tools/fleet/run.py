"""A fleet run: every log through one job on Ray, rows as they finish, results when done or stopped.

Ctrl-C (or SIGTERM) cancels the tasks not yet finished; their rows are ``cancelled`` and every
result already installed stays complete and readable (see :mod:`trundle.tools.fleet.task`).
"""

from __future__ import annotations

import fcntl
import os
import shutil
import signal
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from trundle.logs.errors import UserError
from trundle.logs.outputs import is_output_failure, output_error, writing_folder
from trundle.logs.reader import LogReader
from trundle.tools.fleet.cluster import Cluster
from trundle.tools.fleet.inputs import expand, folder_names, local_copy
from trundle.tools.fleet.jobs import options_key
from trundle.tools.fleet.results import write_csv, write_parquet, write_run
from trundle.tools.fleet.rows import STATUSES
from trundle.tools.fleet.summary import write_summary
from trundle.tools.fleet.task import STATE, Task, robot_name
from trundle.tools.jobs.progress import NoProgress, ProgressFactory

POLL_S = 0.5          # how often the progress is redrawn while no task finishes
CANCEL_WAIT_S = 10.0  # after Ctrl-C, how long the cancelled tasks are given to stop


@dataclass
class FleetRun:
    """The outcome: one row per log (in input order), the seconds from the first task submitted
    to the last finished (``elapsed_s``), from the call to its end (``wall_s``: with Ray's start and
    the results' writing), and Ray's start alone (``ray_start_s``), the cluster's CPUs, and whether
    the run was interrupted."""

    job: str
    options: dict[str, Any]
    rows: list[dict[str, Any]] = field(default_factory=list)
    elapsed_s: float = 0.0
    wall_s: float = 0.0
    ray_start_s: float = 0.0
    cpus: float = 0.0
    interrupted: bool = False
    files: list[Path] = field(default_factory=list)

    def count(self, status: str) -> int:
        return sum(r["status"] == status for r in self.rows)


@contextmanager
def _lock(output: Path) -> Iterator[None]:
    """Hold OUT/.fleet/lock for the run, so two runs never write one output folder. The lock holds
    the run's pid, written at once: a full disk is said before Ray starts. A run that fails takes
    back what it added to OUT (:func:`trundle.logs.outputs.writing_folder`)."""
    with writing_folder(output, empty=False):
        state = output / STATE
        try:
            state.mkdir(exist_ok=True)
            lock = open(state / "lock", "a")  # noqa: SIM115  held by the with below; not emptied: another run's
        except OSError as error:
            if is_output_failure(error):
                raise output_error(error, state) from None
            raise
        with lock as f:
            try:
                fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                raise UserError(f"another trundle fleet is writing to {output}") from None
            try:
                os.ftruncate(f.fileno(), 0)
                os.write(f.fileno(), f"{os.getpid()}\n".encode())
            except OSError as error:
                if is_output_failure(error):
                    raise output_error(error, state / "lock") from None
                raise
            yield


@contextmanager
def _sigterm_interrupts() -> Iterator[None]:
    """SIGTERM (a stopped Kubernetes job, a killed session) ends the run as Ctrl-C does."""
    def interrupt(signum: int, frame: object) -> None:
        raise KeyboardInterrupt
    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def sessions_in_order(sources: Sequence[str], names: Sequence[str]) -> list[int | None]:
    """For ``trundle fleet slam --continue MAPDIR``: each log's predecessor (the index of the log of the same
    robot just before it in time; None: the robot's first, which continues MAPDIR). Reads each log's
    robot (:func:`trundle.tools.fleet.task.robot_name`) and first message time."""
    keys = []
    for source in sources:
        with local_copy(source) as path, LogReader(path) as reader:
            info = reader.info()
            keys.append((robot_name(info.metadata), info.start_ns or 0))
    previous: list[int | None] = [None] * len(sources)
    last: dict[str, int] = {}
    for i in sorted(range(len(sources)), key=lambda k: (keys[k][0], keys[k][1], names[k])):
        previous[i] = last.get(keys[i][0])
        last[keys[i][0]] = i
    return previous


def run_fleet(job: str, patterns: Sequence[str], output: Path, options: Mapping[str, Any], *,
              address: str | None = None, retries: int = 3, num_cpus: int | None = None,
              cpus_per_log: float = 1.0, force: bool = False, progress: ProgressFactory = NoProgress,
              on_row: Callable[[dict[str, Any], FleetRun], None] | None = None,
              say: Callable[[str], None] = lambda text: None, continue_from: Path | None = None) -> FleetRun:
    """Run ``job`` with ``options`` on every log ``patterns`` name, outputs in ``output``/<name>/.

    ``continue_from`` (the slam job only): each robot's logs are sessions mapped in time order, its first
    continuing the map of ``continue_from``, each next one the output of the one before (a task starts
    once its predecessor's has finished; a failed one fails the rest of its robot's chain).

    ``address``/``num_cpus``: see :class:`trundle.tools.fleet.cluster.Cluster`; ``retries``: how
    often a task lost with its worker is run again; ``force`` recomputes complete results;
    ``progress`` shows done/failed/running/remaining; ``on_row`` is called with each finished row;
    ``say`` is told when Ray starts and is ready (seconds of silence otherwise).
    """
    called = time.perf_counter()
    output = output.resolve()
    sources = expand(patterns, exclude=output)
    names = folder_names(sources)
    key = options_key(job, options)
    run = FleetRun(job, dict(options))
    rows: list[dict[str, Any] | None] = [None] * len(sources)
    with _lock(output), _sigterm_interrupts():
        shutil.rmtree(output / STATE / "work", ignore_errors=True)
        cluster = Cluster(address, num_cpus, say)
        run.ray_start_s = time.perf_counter() - called
        say(f"Ray ready in {run.ray_start_s:.1f} s")
        try:
            started = time.perf_counter()
            refs = _submit(cluster, job, sources, names, output, options, key, force, retries, cpus_per_log,
                           continue_from)
            bar = progress("fleet", len(sources))
            pending = list(refs)
            try:
                while pending:
                    finished, pending = cluster.wait(pending, POLL_S)
                    for ref in finished:
                        i = refs[ref]
                        result = cluster.result(ref, retries)
                        row = result if isinstance(result, dict) else \
                            {"log": sources[i], "name": names[i], "status": "failed", "error": result}
                        rows[i] = row
                        run.rows = [r for r in rows if r is not None]
                        if on_row is not None:
                            on_row(row, run)
                    total, busy = cluster.cpus()
                    run.cpus = total
                    done = len(sources) - len(pending)
                    bar.update(
                        done,
                        f"{done - run.count('failed')} done, {run.count('failed')} failed, "
                        f"{min(len(pending), round(busy / cpus_per_log))} running, {len(pending)} remaining",
                    )
            except KeyboardInterrupt:
                run.interrupted = True
                left = [ref for ref, i in refs.items() if rows[i] is None]
                cluster.cancel(left)
                try:  # tasks that finished before the cancel reached them still give their rows
                    finished, _ = cluster.wait(left, CANCEL_WAIT_S)
                except KeyboardInterrupt:
                    finished = []
                for ref in finished:
                    result = cluster.result(ref, retries)
                    rows[refs[ref]] = result if isinstance(result, dict) else None
                for i in (refs[ref] for ref in left if rows[refs[ref]] is None):
                    rows[i] = {
                        "log": sources[i],
                        "name": names[i],
                        "status": "cancelled",
                        "error": "interrupted before it finished",
                    }
            finally:
                bar.close()
            run.elapsed_s = time.perf_counter() - started
        finally:
            cluster.close()
            shutil.rmtree(output / STATE / "work", ignore_errors=True)
        run.rows = [r for r in rows if r is not None]
        run.wall_s = time.perf_counter() - called   # before the results are written, so run.json holds it
        run.files = write_results(run, output)
    return run


def _submit(cluster: Cluster, job: str, sources: Sequence[str], names: Sequence[str], output: Path,
            options: Mapping[str, Any], key: str, force: bool, retries: int, cpus_per_log: float,
            continue_from: Path | None) -> dict[Any, int]:
    """Every log's task submitted: reference -> index (chained per robot with ``continue_from``, see
    :func:`run_fleet`)."""
    if continue_from is None:
        return {cluster.submit(Task(job, s, n, str(output), dict(options), key, force), retries, cpus_per_log): i
                for i, (s, n) in enumerate(zip(sources, names, strict=True))}
    previous = sessions_in_order(sources, names)
    submitted: dict[int, Any] = {}
    pending = list(range(len(sources)))
    while pending:  # a log after its predecessor
        for i in [k for k in pending if previous[k] is None or previous[k] in submitted]:
            before = previous[i]
            mapdir = continue_from.resolve() if before is None else output / names[before]
            chained = {**options, "continue_from": str(mapdir)}
            task = Task(job, sources[i], names[i], str(output), chained, options_key(job, chained), force)
            submitted[i] = cluster.submit(task, retries, cpus_per_log, None if before is None else submitted[before])
            pending.remove(i)
    return {ref: i for i, ref in submitted.items()}


def figures(run: FleetRun) -> dict[str, Any]:
    """The run's own figures (what ``run.json`` holds)."""
    finished = len(run.rows) - run.count("cancelled")
    return {"job": run.job, "options": run.options, "logs": len(run.rows),
            **{status: run.count(status) for status in STATUSES}, "interrupted": run.interrupted,
            "elapsed_s": run.elapsed_s, "wall_s": run.wall_s, "ray_start_s": run.ray_start_s, "cpus": run.cpus,
            "logs_per_minute": 60.0 * finished / run.elapsed_s if run.elapsed_s > 0 else 0.0,
            "job_cpu_seconds": sum(r.get("cpu_seconds") or 0.0 for r in run.rows if r["status"] == "ok")}


def write_results(run: FleetRun, output: Path) -> list[Path]:
    """results.csv, results.parquet (with pyarrow), run.json, summary.md and summary.png in ``output``."""
    written = [write_csv(run.rows, output / "results.csv")]
    written += [p for p in [write_parquet(run.rows, output / "results.parquet")] if p is not None]
    written.append(write_run(figures(run), output / "run.json"))
    return written + write_summary(run.job, run.rows, figures(run), output)
