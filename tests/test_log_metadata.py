"""The log's own description, written and read by one module: structured values round-trip, the
formats trundle 0.1 wrote (a robot's plain name, ``family=url`` device words) still read, and the
wheel model reaches slam from every kind of log (daemon, recorder, importer)."""

from __future__ import annotations

import json
from pathlib import Path

from hypothesis import given
from hypothesis import strategies as st

from trundle.logs.metadata import LogMetadata, decode, encode, read_metadata
from trundle.logs.reader import LogInfo, LogReader, TopicInfo
from trundle.tools.jobs.config import laser_pose, make_odometry

DEMO_LOG = Path(__file__).resolve().parent / "data" / "demo_short" / "demo.mcap"
WHEELS = {"/wheels": TopicInfo("sensor_msgs/msg/JointState")}


def test_structured_values_round_trip_as_json_objects():
    record = encode({"command": "record", "robot": {"name": "r2", "wheel_radius_m": 0.1, "track_m": 0.5},
                     "devices": {"can": {"family": "can", "url": "slcan:///dev/ttyACM0", "track_m": 0.4}},
                     "malformed_lines": 3, "source": "/data/run.clf"})
    assert all(isinstance(v, str) for v in record.values())
    assert json.loads(record["robot"]) == {"name": "r2", "wheel_radius_m": 0.1, "track_m": 0.5}
    meta = decode(record)
    assert meta.command == "record" and meta.robot_name == "r2"
    assert meta.wheel_model() == {"wheel_radius_m": 0.1, "track_m": 0.5}  # the robot's before a device's
    assert meta.devices["can"]["url"] == "slcan:///dev/ttyACM0"
    assert meta.fields["source"] == "/data/run.clf" and meta.fields["malformed_lines"] == "3"
    assert encode({"robot": "r2"})["robot"] == '{"name": "r2"}'


def test_what_trundle_0_1_wrote_still_reads():
    daemon = decode({"command": "daemon", "robot": "trundle-demo",
                     "devices": json.dumps({"can": {"family": "can", "wheel_radius_m": 0.1, "track_m": 0.5}})})
    assert daemon.robot_name == "trundle-demo" and daemon.wheel_model() == {"wheel_radius_m": 0.1, "track_m": 0.5}
    record = decode({"command": "record", "devices": "lrf=scip2:///dev/ttyACM0 can=slcan:///dev/ttyACM1@1000000"})
    assert record.devices == {"lrf": {"family": "lrf", "url": "scip2:///dev/ttyACM0"},
                              "can": {"family": "can", "url": "slcan:///dev/ttyACM1@1000000"}}
    assert record.robot == {} and record.wheel_model() is None and record.laser_mount() is None
    assert decode({"robot": "{broken", "devices": "[1, 2]"}) == LogMetadata(robot={"name": "{broken"})


@given(st.dictionaries(st.text(max_size=8), st.text(max_size=30), max_size=6))
def test_any_record_decodes_without_an_error(record):
    meta = decode(record)
    meta.wheel_model()
    meta.laser_mount()


def test_the_wheel_model_reaches_slam_from_every_kind_of_log():
    daemon_log = LogReader(DEMO_LOG).info()  # written by trundle 0.1's daemon: robot is a plain name
    assert read_metadata(daemon_log.metadata).robot_name == "trundle-demo"
    assert make_odometry(daemon_log, None).track_m == 0.5
    recorder = LogInfo(Path("r.mcap"), 0, topics=dict(WHEELS), metadata={"trundle": encode({
        "command": "record", "devices": {"can": {"family": "can", "url": "slcan:///x", "wheel_radius_m": 0.08,
                                                 "track_m": 0.35, "wheels": ["l", "r"]}}})})
    odometry = make_odometry(recorder, None)
    assert (odometry.track_m, odometry.left, odometry.right) == (0.35, "l", "r")
    imported = LogInfo(Path("i.mcap"), 0, topics=dict(WHEELS), metadata={"trundle": encode({
        "command": "import breezyslam", "robot": {"wheel_radius_m": 0.077, "track_m": 0.33, "laser_x_m": 0.145}})})
    assert make_odometry(imported, None).track_m == 0.33
    assert laser_pose(imported, None) == (0.145, 0.0, 0.0)
    assert laser_pose(imported, {"laser": {"x_m": 0.3}}) == (0.3, 0.0, 0.0)
