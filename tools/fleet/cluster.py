"""The Ray side of a fleet run: connect (or start a local Ray), one task per log, wait, cancel.

Ray is imported when a run connects, never before: ``trundle --help`` stays light, and a local
Ray is told before its import to listen on 127.0.0.1 only (``RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0``:
Ray's own switch for a single-machine instance; otherwise Ray binds its gRPC servers to every
interface) and to take a token of its own (token authentication, nothing written to ~/.ray).
Usage statistics stay off unless ``RAY_USAGE_STATS_ENABLED`` says otherwise.

Each task asks for ``cpus_per_log`` CPUs; Ray retries a task whose worker or node was lost up to
``retries`` times (``max_retries``) and never retries a job's own error (the task returns a
``failed`` row instead, see :mod:`trundle.tools.fleet.task`).
"""

from __future__ import annotations

import logging
import os
import secrets
import socket
from collections.abc import Callable, Sequence
from dataclasses import asdict
from typing import Any

from trundle.logs.errors import UserError
from trundle.tools.fleet.rows import one_line
from trundle.tools.fleet.task import Task, process_log

LOCAL = "local"
CONNECT_TIMEOUT_S = 10.0


def _run_on_worker(task: dict[str, Any], *after: Any) -> dict[str, Any]:
    """The Ray task: :func:`process_log` plus the IP of the node it ran on (``after``: the rows of the tasks
    it waited for, resolved by Ray before it starts)."""
    import ray

    return {**process_log(Task(**task)), "node": ray.util.get_node_ip_address()}


def _check_reachable(address: str, timeout_s: float = CONNECT_TIMEOUT_S) -> None:
    """A UserError at once if nothing accepts TCP connections at a ``HOST:PORT`` address (Ray
    itself would retry for minutes); other address forms (``auto``, ``ray://``) are left to Ray."""
    host, sep, port = address.rpartition(":")
    if not sep or "://" in address or not port.isdigit():
        return
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s).close()
    except OSError as error:
        raise UserError(f"cannot reach the Ray cluster at {address}: {error.strerror or error} "
                        "(is `ray start --head` running there?)") from None


class Cluster:
    """A connection to a Ray cluster: ``address`` (``HOST:PORT``, ``auto``, ``ray://...``), else
    ``RAY_ADDRESS``, else a local Ray started for this run with ``num_cpus`` CPUs (default: all);
    ``say`` is told which, before the seconds Ray takes to start or connect."""

    def __init__(self, address: str | None = None, num_cpus: int | None = None,
                 say: Callable[[str], None] = lambda text: None) -> None:
        self.address = address or os.environ.get("RAY_ADDRESS") or LOCAL
        local = self.address == LOCAL
        if local:
            os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")
            if not {"RAY_AUTH_MODE", "RAY_AUTH_TOKEN"} & set(os.environ):
                os.environ.update(RAY_AUTH_MODE="token", RAY_AUTH_TOKEN=secrets.token_hex(32))
        elif num_cpus is not None:
            raise UserError("--num-cpus sizes a local Ray only; an existing cluster has the CPUs its nodes offer")
        else:
            _check_reachable(self.address)
        os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
        import ray

        self._ray = ray
        cpus = "all CPUs" if num_cpus is None else f"{num_cpus} CPU{'' if num_cpus == 1 else 's'}"
        say(f"starting a local Ray ({cpus}) ..." if local else
            f"connecting to the Ray cluster at {self.address} ...")
        try:
            ray.init(address=self.address, num_cpus=num_cpus if local else None,
                     include_dashboard=False if local else None, log_to_driver=False,
                     logging_level=logging.ERROR)
        except (ConnectionError, RuntimeError, ValueError) as error:
            raise UserError(f"cannot connect to the Ray cluster at {self.address}: {one_line(str(error))}") from None
        self._remote = ray.remote(_run_on_worker)

    def submit(self, task: Task, retries: int, cpus_per_log: float, after: Any | None = None) -> Any:
        """Start ``task`` as a Ray task (once the task of the reference ``after`` has finished, if given);
        returns its object reference."""
        options = self._remote.options(num_cpus=cpus_per_log, max_retries=retries, retry_exceptions=False,
                                       name=f"trundle-fleet {task.job} {task.name}")
        return options.remote(asdict(task)) if after is None else options.remote(asdict(task), after)

    def wait(self, refs: Sequence[Any], timeout_s: float) -> tuple[list[Any], list[Any]]:
        """(finished, unfinished) references after at most ``timeout_s`` seconds."""
        return self._ray.wait(list(refs), num_returns=len(refs), timeout=timeout_s, fetch_local=True)

    def result(self, ref: Any, retries: int) -> dict[str, Any] | str:
        """A finished task's row, or the one-line reason Ray gave up on it (e.g. its worker was
        lost ``retries + 1`` times)."""
        try:
            return self._ray.get(ref)
        except self._ray.exceptions.RayError as error:
            first = next((line for line in str(error).splitlines() if line.strip()), "")
            return one_line(f"Ray gave up after {retries + 1} attempt(s): {type(error).__name__}: {first}")

    def cancel(self, refs: Sequence[Any]) -> None:
        """Cancel the tasks of ``refs``: queued ones never start, running ones are interrupted."""
        for ref in refs:
            self._ray.cancel(ref, force=False)

    def cpus(self) -> tuple[float, float]:
        """(CPUs of the cluster, CPUs in use now), from Ray's resource view."""
        total = self._ray.cluster_resources().get("CPU", 0.0)
        return total, total - self._ray.available_resources().get("CPU", 0.0)

    def close(self) -> None:
        """Disconnect (and stop a local Ray)."""
        self._ray.shutdown()
