"""Live view: a Foxglove WebSocket server (``foxglove-sdk``, the optional extra ``trundle[live]``)
streaming the same topics the daemon logs, as ROS 2 messages (``ros2msg`` schemas, CDR), so
Foxglove or Lichtblick shows the robot live exactly as they show its logs.

Each topic becomes a channel on first use; a message is encoded only while a client subscribes.
Latched topics (``/tf_static``, camera info) are sent again to a channel as soon as a client
subscribes to it (with the next message), and every ``repeat_latched`` call, so a client that
connects later still gets them. Bound to 127.0.0.1 unless configured otherwise. With
``log_time`` (``trundle replay``) the server advertises the time capability and ``set_time``
broadcasts the log's time, so a client plays the stream in log time.

The minimum client: the SDK's server speaks the Foxglove WebSocket protocol under the subprotocol
name ``foxglove.sdk.v1`` and refuses (HTTP 400) a client that offers only the older name
``foxglove.websocket.v1`` (the protocol is the same; the SDK has no setting to accept the old
name). Current Foxglove (web and desktop) offers the new name; Lichtblick does from the release
after 1.21 (lichtblick-suite/lichtblick#819); a tool built on ``@foxglove/ws-protocol`` connects
once it offers ``foxglove.sdk.v1`` (it may offer both). ``tests/test_daemon_live.py`` checks this.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Mapping
from typing import Any

from trundle.logs import messages as m
from trundle.logs import ros2
from trundle.logs.errors import UserError
from trundle.logs.writer import is_latched

TIME_PERIOD_NS = 50_000_000  # set_time broadcasts at most this often (in the time it is given)


class LiveView:
    """A Sink (``view(topic, msg, log_time_ns)``) that streams to Foxglove clients (from any thread)."""

    def __init__(self, host: str = "127.0.0.1", port: int = 8765, name: str = "trundle",
                 log_time: bool = False, channels: Mapping[str, str] | None = None) -> None:
        """Serve on ``host``:``port`` (0: any free port) as ``name``; ``log_time``: the server time is the
        one ``set_time`` gives; ``channels`` (topic -> ROS type): advertised before the server starts."""
        try:
            import foxglove
            from foxglove.websocket import Capability, ServerListener
        except ImportError:
            raise UserError(
                "the live view needs the optional extra: pip install 'trundle[live]' (foxglove-sdk)"
            ) from None
        self._foxglove = foxglove
        self.context = foxglove.Context()
        self.channels: dict[str, Any] = {}
        self.latched: dict[str, tuple[str, bytes, int]] = {}  # topic -> (ROS type, CDR, log time)
        self.sent = 0
        self._lock = threading.RLock()
        self._joined: set[str] = set()  # latched topics a client subscribed to since they were last sent
        self._next_time_ns: int | None = None
        for topic, ros_type in (channels or {}).items():
            self.advertise(topic, ros_type)
        try:
            self.server = foxglove.start_server(name=name, host=host, port=port, context=self.context,
                                                capabilities=[Capability.Time] if log_time else None,
                                                server_listener=_joins(ServerListener, self._joined))
        except Exception as error:  # the SDK raises its own error types for a busy or bad address
            raise UserError(f"cannot serve the live view on {host}:{port}: {error}") from None

    @property
    def port(self) -> int:
        return int(self.server.port)

    def __call__(self, topic: str, msg: m.Message, log_time_ns: int) -> None:
        try:
            ros_type = ros2.ros_type(type(msg))
        except ros2.UnsupportedType:
            return
        self.send(topic, ros_type, lambda: ros2.encode(msg)[1], log_time_ns)

    def send(self, topic: str, ros_type: str, data: bytes | Callable[[], bytes], log_time_ns: int) -> None:
        """Stream one message of ``ros_type``: its CDR bytes, or a callable giving them (called only
        while a client subscribes, or for a latched topic)."""
        with self._lock:
            if is_latched(topic):
                encoded = data() if callable(data) else data
                self.latched[topic] = (ros_type, encoded, log_time_ns)
                data = encoded
            self._log(topic, ros_type, data, log_time_ns)
            if self._joined:
                for joined in [t for t in list(self._joined) if t in self.latched and t != topic]:
                    self._joined.discard(joined)
                    self._log(joined, *self.latched[joined])

    def advertise(self, topic: str, ros_type: str) -> Any:
        """The channel of ``topic`` (made on first use). When the topics are known (a replay), give them as
        ``channels``: a client that subscribes at once to a channel advertised while it is connected can
        be told "unknown channel" (foxglove-sdk 0.30.3) and then gets nothing on it."""
        with self._lock:
            channel = self.channels.get(topic)
            if channel is None:
                schema = self._foxglove.Schema(name=ros_type, encoding="ros2msg",
                                               data=ros2.schema_text(ros_type).encode())
                channel = self.channels[topic] = self._foxglove.Channel(topic, schema=schema, message_encoding="cdr",
                                                                        context=self.context)
            return channel

    def _log(self, topic: str, ros_type: str, data: bytes | Callable[[], bytes], log_time_ns: int) -> None:
        channel = self.advertise(topic, ros_type)
        if channel.has_sinks():
            channel.log(data() if callable(data) else data, log_time=log_time_ns)
            self.sent += 1

    def set_time(self, log_time_ns: int) -> None:
        """Tell the clients the server's time is ``log_time_ns`` (at most every ``TIME_PERIOD_NS`` of it)."""
        if self._next_time_ns is None or not 0 <= self._next_time_ns - log_time_ns <= TIME_PERIOD_NS:
            self._next_time_ns = log_time_ns + TIME_PERIOD_NS
            self.server.broadcast_time(log_time_ns)

    def repeat_latched(self) -> None:
        """Send the latched messages again (for clients that connected since)."""
        with self._lock:
            for topic, (ros_type, data, log_time_ns) in list(self.latched.items()):
                self._log(topic, ros_type, data, log_time_ns)

    def close(self) -> None:
        self.server.stop()


def _joins(base: type, joined: set[str]) -> Any:
    """A server listener (a ``base``, the SDK's ServerListener) that notes in ``joined`` the latched
    topics a client subscribes to, to be sent again."""

    class Joins(base):
        def on_subscribe(self, client: Any, channel: Any) -> None:
            if is_latched(channel.topic):
                joined.add(channel.topic)

    return Joins()
