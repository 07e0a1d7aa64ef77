"""Serve an emulated device on a pty behind a stable symlink, or on a TCP port, from a thread.

The device object is pure (bytes and times in, bytes out); this module is its cable: it
feeds the host's bytes to ``device.receive``, sends what ``device.poll`` has due, and acts on
``device.link_request`` (pull the cable for a while, as an unplug or a reboot does). Output
the host is not reading is held in a bounded backlog (a device's USB FIFO) and the oldest
bytes are dropped beyond it.
"""

from __future__ import annotations

import fcntl
import os
import select
import socket
import termios
import threading
import time
from pathlib import Path
from typing import Protocol

from trundle.tools.emulators.pty_link import PtyLink


class Device(Protocol):
    """What a server needs from an emulated device (times are host wall-clock nanoseconds)."""

    link_request: tuple[str, float] | None  # ("unplug", seconds offline), taken by the server

    def receive(self, data: bytes, now_ns: int) -> bytes: ...

    def poll(self, now_ns: int) -> bytes: ...

    def next_event_ns(self) -> int | None: ...

    def power_on(self, now_ns: int) -> None: ...


def _unread(fd: int) -> int:
    """Bytes waiting to be read on ``fd`` (a pty master or a socket); 0 if it cannot be asked."""
    try:
        return int.from_bytes(fcntl.ioctl(fd, termios.FIONREAD, b"\0\0\0\0"), "little")
    except OSError:
        return 0


class _Pty:
    def __init__(self, link_path: Path) -> None:
        self.link = PtyLink(link_path)

    def fds(self) -> list[int]:
        return [self.link.fileno()] if self.link.plugged else []

    def read(self, ready: list[int]) -> bytes:
        return self.link.read(65536, 0.0) if ready else b""

    def write(self, data: bytes) -> int:
        try:
            return os.write(self.link.fileno(), data)
        except (BlockingIOError, InterruptedError):
            return 0
        except OSError:
            return len(data)  # nobody on the other side: the bytes are gone

    def unplug(self) -> None:
        self.link.unplug()

    def replug(self) -> None:
        self.link.replug()

    def close(self) -> None:
        self.link.close()


class _Tcp:
    def __init__(self, host: str, port: int) -> None:
        self.host, self.port = host, port
        self.listener: socket.socket | None = None
        self.client: socket.socket | None = None
        self.replug()

    def replug(self) -> None:
        listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        listener.bind((self.host, self.port))
        listener.listen(2)
        listener.setblocking(False)
        self.port = listener.getsockname()[1]
        self.listener = listener

    def fds(self) -> list[int]:
        return [s.fileno() for s in (self.listener, self.client) if s is not None]

    def read(self, ready: list[int]) -> bytes:
        if self.listener is not None and self.listener.fileno() in ready:
            try:
                client, _ = self.listener.accept()
            except OSError:
                client = None
            if client is not None:
                self._drop_client()
                client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                client.setblocking(False)
                self.client = client
        if self.client is None or self.client.fileno() not in ready:
            return b""
        try:
            data = self.client.recv(65536)
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError:
            data = b""
        if not data:
            self._drop_client()
        return data

    def write(self, data: bytes) -> int:
        if self.client is None:
            return len(data)
        try:
            return self.client.send(data)
        except (BlockingIOError, InterruptedError):
            return 0
        except OSError:
            self._drop_client()
            return len(data)

    def _drop_client(self) -> None:
        if self.client is not None:
            self.client.close()
            self.client = None

    def unplug(self) -> None:
        self._drop_client()
        if self.listener is not None:
            self.listener.close()
            self.listener = None

    def close(self) -> None:
        self.unplug()


class DeviceServer:
    """Runs ``device`` on a pty (``link_path``) or a TCP port (``tcp_port``, 0 = any free port).

    ``unplugs`` counts cable pulls, ``replugged_ns`` holds when the cable came back,
    ``last_input_ns`` when the host last sent something, ``dropped_bytes`` what overflowed the
    ``backlog`` while nobody read.
    """

    def __init__(self, device: Device, *, link_path: str | os.PathLike[str] | None = None,
                 tcp_port: int | None = None, host: str = "127.0.0.1", backlog: int = 1 << 16) -> None:
        if (link_path is None) == (tcp_port is None):
            raise ValueError("give exactly one of link_path and tcp_port")
        self.device = device
        self.transport: _Pty | _Tcp = _Pty(Path(link_path)) if link_path is not None else _Tcp(host, tcp_port or 0)
        self.backlog_limit = backlog
        self.unplugs = 0
        self.last_input_ns = 0
        self.replugged_ns: list[int] = []
        self.dropped_bytes = 0
        self._out = bytearray()
        self._offline_until = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.lock = threading.Lock()  # held while the device is being driven

    def unread(self) -> int:
        """Bytes the host sent that the device has not read yet (on the pty or the TCP client)."""
        fds = self.transport.fds()
        if isinstance(self.transport, _Tcp):
            fds = [self.transport.client.fileno()] if self.transport.client is not None else []
        return sum(_unread(fd) for fd in fds)

    @property
    def port(self) -> int:
        return self.transport.port if isinstance(self.transport, _Tcp) else 0

    @property
    def link_path(self) -> Path | None:
        return self.transport.link.link_path if isinstance(self.transport, _Pty) else None

    def start(self) -> DeviceServer:
        self._thread = threading.Thread(target=self.run, name="device-server", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5.0)
        self.transport.close()

    def __enter__(self) -> DeviceServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def run(self) -> None:
        while not self._stop.is_set():
            now = time.time_ns()
            if self._offline_until:
                if now < self._offline_until:
                    self._stop.wait(min(0.01, (self._offline_until - now) / 1e9))
                    continue
                self._offline_until = 0
                self.transport.replug()
                with self.lock:
                    self.device.power_on(time.time_ns())
                self.replugged_ns.append(time.time_ns())
            self._step(now)

    def _step(self, now: int) -> None:
        due = self.device.next_event_ns()
        wait = 0.02 if due is None else min(max((due - now) / 1e9, 0.0), 0.02)
        if self._out:
            wait = min(wait, 0.005)
        try:
            ready, _, _ = select.select(self.transport.fds(), [], [], wait)
        except (OSError, ValueError):
            ready = []
        data = self.transport.read(ready)
        now = time.time_ns()
        if data:
            self.last_input_ns = now
        with self.lock:
            out = (self.device.receive(data, now) if data else b"") + self.device.poll(now)
            request, self.device.link_request = self.device.link_request, None
        self._send(out)
        if request is not None:
            self.unplugs += 1
            self.transport.unplug()
            self._out.clear()
            self._offline_until = time.time_ns() + int(request[1] * 1e9)

    def _send(self, data: bytes) -> None:
        self._out += data
        if len(self._out) > self.backlog_limit:
            extra = len(self._out) - self.backlog_limit
            self.dropped_bytes += extra
            del self._out[:extra]
        while self._out:
            n = self.transport.write(bytes(self._out))
            if n <= 0:
                break
            del self._out[:n]
