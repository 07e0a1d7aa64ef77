"""Live view: a Foxglove WebSocket client (the `websockets` package speaking the Foxglove
protocol v1) sees the daemon's topics with their ROS 2 schemas and receives CDR messages that
decode to what the drivers sent."""

from __future__ import annotations

import json
import socket
import struct
import time

from websockets.sync import client as websockets_client

from tests.test_daemon import Running, config, wait_for
from trundle.logs import messages as m
from trundle.logs import ros2


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def test_foxglove_client_receives_logged_topics(tmp_path):
    port = free_port()
    with Running(config(tmp_path, live={"enabled": True, "port": port})) as run:
        wait_for(lambda: run.drivers["lrf"].counters["scans"] > 5)
        with websockets_client.connect(
            f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1", "foxglove.websocket.v1"], open_timeout=10
        ) as ws:
            channels: dict[str, dict] = {}
            deadline = time.monotonic() + 10
            while not {"/scan", "/tf_static"} <= set(channels):
                assert time.monotonic() < deadline, channels
                message = ws.recv(timeout=5)
                if isinstance(message, str) and json.loads(message)["op"] == "advertise":
                    channels.update({c["topic"]: c for c in json.loads(message)["channels"]})
            scan = channels["/scan"]
            assert scan["encoding"] == "cdr" and scan["schemaName"] == "sensor_msgs/msg/LaserScan"
            assert scan["schemaEncoding"] == "ros2msg" and scan["schema"] == ros2.schema_text(
                "sensor_msgs/msg/LaserScan"
            )
            ws.send(
                json.dumps(
                    {
                        "op": "subscribe",
                        "subscriptions": [
                            {"id": 7, "channelId": scan["id"]},
                            {"id": 8, "channelId": channels["/tf_static"]["id"]},
                        ],
                    }
                )
            )
            got: dict[int, m.Message] = {}
            while len(got) < 2:
                assert time.monotonic() < deadline + 10
                message = ws.recv(timeout=5)
                if isinstance(message, bytes) and message[0] == 0x01:
                    subscription, stamp = struct.unpack_from("<IQ", message, 1)
                    ros_type = "sensor_msgs/msg/LaserScan" if subscription == 7 else "tf2_msgs/msg/TFMessage"
                    got[subscription] = ros2.decode(ros_type, message[13:])
        status = run.daemon.status()
    assert isinstance(got[7], m.LaserScan) and got[7].frame_id == "laser" and got[7].ranges.size == 5
    assert {t.child_frame_id for t in got[8].transforms} == {"laser", "camera"}  # latched, merged
    assert status["live"]["sent"] >= 2 and status["live"]["errors"] == 0


def test_the_minimum_client_offers_the_sdk_subprotocol(tmp_path):
    """What a client needs (documented in tools/daemon/live_view.py and README): the Foxglove SDK
    server speaks the Foxglove WebSocket protocol under the subprotocol name ``foxglove.sdk.v1``
    only; a client offering just the older name ``foxglove.websocket.v1`` (older Foxglove and
    Lichtblick, tools on @foxglove/ws-protocol) is refused with HTTP 400. If an SDK release
    accepts the old name, this test fails and the documentation should say so."""
    from websockets.exceptions import InvalidStatus

    port = free_port()
    with Running(config(tmp_path, live={"enabled": True, "port": port})):
        with websockets_client.connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"],
                                       open_timeout=10) as ws:
            assert ws.subprotocol == "foxglove.sdk.v1"
            assert json.loads(ws.recv(timeout=5))["op"] == "serverInfo"
        try:
            websockets_client.connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.websocket.v1"],
                                      open_timeout=10).close()
        except InvalidStatus as refused:
            assert refused.response.status_code == 400
        else:
            raise AssertionError("the SDK now accepts foxglove.websocket.v1: update the live view's documentation")
