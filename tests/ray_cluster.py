"""A real multi-node Ray cluster on loopback addresses, for the fleet tests.

Each node is ``ray start --block`` with its own ``--node-ip-address`` (127.0.0.2 the head,
127.0.0.3, ... the workers; not 127.0.0.1, which Ray rewrites into the machine's network
address), one CPU each. Ray binds its gRPC servers to every interface for any node address but
127.0.0.1, so the whole cluster, and every driver the tests run against it, lives in a private
network namespace whose only interface is loopback: nothing of it is reachable from, or listens
on, any other address. Nodes are stopped by pid (SIGTERM to their ``ray start``, which stops its
processes), then every process left in the namespace is killed by pid, whatever the test did.
"""

from __future__ import annotations

import contextlib
import os
import secrets
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

RAY = str(Path(sys.executable).with_name("ray"))
HEAD_IP, PORT = "127.0.0.2", 6379
STARTED = "Ray runtime started"
START_TIMEOUT_S = 90.0
# Token authentication on every node and driver, with a token of this cluster's own (Ray reads
# RAY_AUTH_TOKEN, so no token file is written to or read from ~/.ray).
ENV = {**os.environ, "RAY_USAGE_STATS_ENABLED": "0", "PYTHONUNBUFFERED": "1", "RAY_AUTH_MODE": "token",
       "RAY_AUTH_TOKEN": secrets.token_hex(32)}


class NamespaceUnavailable(RuntimeError):
    """No private network namespace can be made here (no unshare, or not allowed)."""


@dataclass
class Node:
    ip: str
    process: subprocess.Popen
    log: Path


def cmdline(pid: int) -> str:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            return f.read().replace(b"\0", b" ").decode(errors="replace").strip()
    except OSError:
        return ""


class LoopbackCluster:
    """Start with :meth:`start` (head) and :meth:`add_node` (workers); always :meth:`stop`."""

    def __init__(self) -> None:
        self.folder = Path(tempfile.mkdtemp(prefix="rayc", dir="/tmp"))   # short: Ray's socket paths
        self.nodes: list[Node] = []
        privileged = os.geteuid() == 0
        self._enter = ["nsenter", "-t"] + (["{pid}", "-n"] if privileged else
                                           ["{pid}", "-U", "-n", "--preserve-credentials"])
        unshare = ["unshare", "-n"] if privileged else ["unshare", "-U", "-r", "-n"]
        try:
            self.holder = subprocess.Popen(
                unshare + ["sh", "-c", "ip link set lo up && echo up && exec sleep infinity"],
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
            )
        except FileNotFoundError as error:
            raise NamespaceUnavailable(f"unshare not found: {error}") from None
        if self.holder.stdout.readline().strip() != "up":
            error = self.holder.stderr.read().strip()
            self.holder.wait()
            raise NamespaceUnavailable(f"cannot make a loopback-only network namespace: {error}")
        self._enter = [a.format(pid=self.holder.pid) for a in self._enter]

    @property
    def address(self) -> str:
        return f"{HEAD_IP}:{PORT}"

    def command(self, argv: list[str]) -> list[str]:
        """``argv`` run inside the cluster's network namespace."""
        return self._enter + ["--"] + argv

    def _start(self, ip: str, args: list[str]) -> Node:
        log = self.folder / f"node-{ip}.log"
        with open(log, "w") as out:
            process = subprocess.Popen(
                self.command(
                    [
                        RAY,
                        "start",
                        "--block",
                        "--node-ip-address",
                        ip,
                        "--num-cpus",
                        "1",
                        "--object-store-memory",
                        str(100 * 2**20),
                        "--disable-usage-stats",
                        *args,
                    ]
                ),
                stdout=out,
                stderr=subprocess.STDOUT,
                env=ENV,
                start_new_session=True,
            )
        node = Node(ip, process, log)
        self.nodes.append(node)
        deadline = time.monotonic() + START_TIMEOUT_S
        while STARTED not in log.read_text():
            if process.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"ray start on {ip} failed:\n{log.read_text()[-3000:]}")
            time.sleep(0.2)
        return node

    def start(self) -> None:
        """The head node at 127.0.0.2:6379."""
        self._start(HEAD_IP, ["--head", "--port", str(PORT), "--include-dashboard=false",
                              "--temp-dir", str(self.folder / "ray")])

    def add_node(self, ip: str) -> Node:
        """A worker node at ``ip`` joined to the head."""
        return self._start(ip, ["--address", self.address])

    def raylet(self, node: Node) -> int:
        """The pid of the node's raylet (a child of its ``ray start``)."""
        for _ in range(100):
            for pid in self.processes():
                if cmdline(pid).split(" ")[0].endswith("/raylet") and f"--node-ip-address={node.ip}" in cmdline(pid):
                    return pid
            time.sleep(0.1)
        raise RuntimeError(f"no raylet for {node.ip}")

    def processes(self) -> list[int]:
        """Every process in the cluster's network namespace but the namespace's holder."""
        mine = os.readlink(f"/proc/{self.holder.pid}/ns/net")
        pids = []
        for entry in os.listdir("/proc"):
            if entry.isdigit() and int(entry) != self.holder.pid:
                try:
                    if os.readlink(f"/proc/{entry}/ns/net") == mine:
                        pids.append(int(entry))
                except OSError:
                    pass
        return pids

    def listeners(self) -> list[str]:
        """The local addresses of every listening TCP socket in the namespace (``ss -ltn``)."""
        out = subprocess.run(self.command(["ss", "-Hltn"]), capture_output=True, text=True, check=True).stdout
        return [line.split()[3] for line in out.splitlines() if line.strip()]

    def stop(self) -> None:
        """Stop every node by pid, then kill whatever is left in the namespace, then the namespace."""
        for node in reversed(self.nodes):
            if node.process.poll() is None:
                node.process.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + 30.0
        for node in self.nodes:
            try:
                node.process.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                node.process.kill()
                node.process.wait()
        for pid in self.processes():
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        self.holder.kill()
        self.holder.wait()
        self.holder.stdout.close()
        self.holder.stderr.close()
        shutil.rmtree(self.folder, ignore_errors=True)
