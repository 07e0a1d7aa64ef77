"""The daemon's status socket: a UNIX stream socket answering ``status`` with one JSON line.

``StatusServer`` serves whatever its provider function returns (the daemon passes its ``status``
method); ``query_status`` is the client ``trundle status`` uses and ``format_status`` the text it
prints. Only the standard library: asking for the status stays quick.
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import socketserver
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any, cast

from trundle.logs.errors import UserError

STATUS_TIMEOUT_S = 2.0
StatusProvider = Callable[[], dict[str, Any]]  # the current status, JSON-able


class _Handler(socketserver.StreamRequestHandler):
    """One connection: read a request line (``status``, the default), write one JSON line."""

    timeout = STATUS_TIMEOUT_S

    def handle(self) -> None:
        try:
            request = self.rfile.readline(256).decode(errors="replace").strip() or "status"
        except OSError:
            return
        if request == "status":
            reply = cast(_Server, self.server).provider()
        else:
            reply = {"error": f"unknown request {request!r} (send 'status')"}
        with contextlib.suppress(OSError):
            self.wfile.write(json.dumps(reply, default=str).encode() + b"\n")


class _Server(socketserver.ThreadingMixIn, socketserver.UnixStreamServer):
    daemon_threads = True

    def __init__(self, path: str, provider: StatusProvider) -> None:
        super().__init__(path, _Handler)
        self.provider = provider


class StatusServer:
    """The socket at ``path`` (mode 0660), answering with ``provider()``. Refuses a socket another
    daemon answers on; replaces a stale one left by a killed daemon."""

    def __init__(self, path: Path, provider: StatusProvider) -> None:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as error:
            raise UserError(f"cannot create {path.parent} for the status socket: {error.strerror or error}") from None
        if path.exists() or path.is_symlink():
            try:
                query_status(path, timeout_s=0.5)
            except UserError:
                path.unlink(missing_ok=True)  # a stale socket left by a killed daemon
            else:
                raise UserError(f"another trundle daemon is answering at {path}")
        try:
            self._server = _Server(os.fspath(path), provider)
        except OSError as error:
            raise UserError(f"cannot open the status socket {path}: {error.strerror or error}") from None
        os.chmod(path, 0o660)
        self.path = path

    def start(self) -> None:
        """Answer requests on a thread of their own."""
        threading.Thread(target=self._server.serve_forever, kwargs={"poll_interval": 0.2}, name="status",
                         daemon=True).start()

    def close(self) -> None:
        """Stop answering and remove the socket."""
        self._server.shutdown()
        self._server.server_close()
        with contextlib.suppress(FileNotFoundError):
            self.path.unlink()


def query_status(path: str | os.PathLike[str], timeout_s: float = STATUS_TIMEOUT_S) -> dict[str, Any]:
    """Ask the daemon at socket ``path`` for its status, waiting up to ``timeout_s`` (s); a UserError
    when nobody answers."""
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
            sock.settimeout(timeout_s)
            sock.connect(os.fspath(path))
            sock.sendall(b"status\n")
            chunks = []
            while chunk := sock.recv(65536):
                chunks.append(chunk)
    except (FileNotFoundError, ConnectionRefusedError):
        raise UserError(f"no trundle daemon is answering at {path} (is it running? see --socket)") from None
    except OSError as error:
        raise UserError(f"cannot ask the daemon at {path}: {error.strerror or error}") from None
    try:
        return json.loads(b"".join(chunks))
    except json.JSONDecodeError:
        raise UserError(f"the daemon at {path} sent an unreadable answer") from None


def format_status(status: dict[str, Any]) -> str:
    """The human-readable form of a status answer (what ``trundle status`` prints)."""
    d = status["daemon"]
    lines = [f"trundle daemon ({d['robot']}): {d['state']}, pid {d['pid']}, up {_duration(d['uptime_s'])}"]
    lines.append("devices:")
    for dev in status["devices"]:
        rates = ", ".join(f"{t} {r:.1f} Hz" for t, r in dev["rates_hz"].items()) or "no messages"
        lines.append(f"  {dev['name']:<10} {dev['family']:<6} {dev['state']:<10} {rates}")
        lines.append(f"  {'':<10} errors {dev['errors']}, reconnects {dev['reconnects']}, crashes {dev['crashes']}"
                     + (f"; last error: {dev['last_error']}" if dev["last_error"] else "")
                     + (f"; last crash: {dev['last_crash']}" if dev["last_crash"] else ""))
    log = status["logger"]
    if log["recording"]:
        lines.append(f"logger: recording {log['file']} ({_size(log['size_bytes'])}), written {log['written']}, "
                     f"dropped {log['dropped']}, queue {log['queue']}")
    else:
        lines.append(f"logger: not recording ({log['paused'] or 'disabled'}), written {log['written']}, "
                     f"dropped {log['dropped']}")
    disk = status.get("disk", {})
    if "error" in disk:
        lines.append(f"disk: {disk['folder']}: {disk['error']}")
    elif disk:
        lines.append(
            f"disk: {_size(disk['free_bytes'])} free in {disk['folder']} (floor {_size(disk['min_free_bytes'])}, "
            f"{disk['action']}; {disk['deleted_count']} logs deleted)"
        )
    for name, odo in status.get("odometry", {}).items():
        lines.append(f"odometry ({name}): {'STALE, ' if odo['stale'] else ''}{odo['distance_m']:.1f} m travelled, "
                     f"{odo['gaps']} gaps")
    if "live" in status:
        lines.append(
            f"live view: {status['live']['url']} (open it in Foxglove), {status['live']['sent']} messages sent"
        )
    if "processing" in status:
        p = status["processing"]
        lines.append(f"processing: queue {p['queue']}, dropped {p['dropped']}, errors {p['errors']}"
                     + (f"; last error: {p['last_error']}" if p.get("last_error") else ""))
        if "slam" in p:
            s = p["slam"]
            lines.append(f"  slam: {s['scans']} scans, {s['keyframes']} keyframes, {s['matched']} matched, "
                         f"{s['loop_closures']} loop closures")
        if "markers" in p:
            seen = ", ".join(f"id {k} {v} times" for k, v in p["markers"].items()) or "none yet"
            lines.append(f"  markers seen: {seen}; {p.get('landmark_messages', 0)} landmark messages")
    return "\n".join(lines)


def _size(n: float) -> str:
    """A byte count in decimal units (kB = 1000 B)."""
    for unit in ("B", "kB", "MB", "GB", "TB"):
        if abs(n) < 1000 or unit == "TB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000.0
    return f"{n:.1f} TB"


def _duration(seconds: float) -> str:
    """An uptime (s) as h:mm:ss."""
    seconds = int(seconds)
    return f"{seconds // 3600:d}:{seconds // 60 % 60:02d}:{seconds % 60:02d}"
