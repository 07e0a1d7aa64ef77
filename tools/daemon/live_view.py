"""Live view: a Foxglove WebSocket server (``foxglove-sdk``, the optional extra ``trundle[live]``)
streaming the same topics the daemon logs, as ROS 2 messages (``ros2msg`` schemas, CDR), so
Foxglove or Lichtblick shows the robot live exactly as they show its logs.

Each topic becomes a channel on first use; a message is encoded only while a client subscribes.
Latched topics (``/tf_static``, camera info) are sent again every ``repeat_latched`` call so a
client that connects later still gets them. Bound to 127.0.0.1 unless configured otherwise.

The minimum client: the SDK's server speaks the Foxglove WebSocket protocol under the subprotocol
name ``foxglove.sdk.v1`` and refuses (HTTP 400) a client that offers only the older name
``foxglove.websocket.v1`` (the protocol is the same; the SDK has no setting to accept the old
name). Current Foxglove (web and desktop) offers the new name; Lichtblick does from the release
after 1.21 (lichtblick-suite/lichtblick#819); a tool built on ``@foxglove/ws-protocol`` connects
once it offers ``foxglove.sdk.v1`` (it may offer both). ``tests/test_daemon_live.py`` checks this.
"""

from __future__ import annotations

from typing import Any

from trundle.logs import messages as m
from trundle.logs import ros2
from trundle.logs.errors import UserError
from trundle.logs.writer import is_latched


class LiveView:
    """A Sink (``view(topic, msg, log_time_ns)``) that streams to Foxglove clients."""

    def __init__(self, host: str = "127.0.0.1", port: int = 8765, name: str = "trundle") -> None:
        try:
            import foxglove
        except ImportError:
            raise UserError(
                "the live view needs the optional extra: pip install 'trundle[live]' (foxglove-sdk)"
            ) from None
        self._foxglove = foxglove
        self.context = foxglove.Context()
        try:
            self.server = foxglove.start_server(name=name, host=host, port=port, context=self.context)
        except Exception as error:  # the SDK raises its own error types for a busy or bad address
            raise UserError(f"cannot serve the live view on {host}:{port}: {error}") from None
        self.channels: dict[str, Any] = {}
        self.latched: dict[str, tuple[m.Message, int]] = {}
        self.sent = 0

    @property
    def port(self) -> int:
        return int(self.server.port)

    def __call__(self, topic: str, msg: m.Message, log_time_ns: int) -> None:
        if is_latched(topic):
            self.latched[topic] = (msg, log_time_ns)
        channel = self.channels.get(topic)
        if channel is None:
            try:
                ros_type = ros2.ros_type(type(msg))
            except ros2.UnsupportedType:
                return
            schema = self._foxglove.Schema(name=ros_type, encoding="ros2msg", data=ros2.schema_text(ros_type).encode())
            channel = self.channels[topic] = self._foxglove.Channel(topic, schema=schema, message_encoding="cdr",
                                                                    context=self.context)
        if channel.has_sinks():
            channel.log(ros2.encode(msg)[1], log_time=log_time_ns)
            self.sent += 1

    def repeat_latched(self) -> None:
        """Send the latched messages again (for clients that connected since)."""
        for topic, (msg, log_time_ns) in list(self.latched.items()):
            self(topic, msg, log_time_ns)

    def close(self) -> None:
        self.server.stop()
