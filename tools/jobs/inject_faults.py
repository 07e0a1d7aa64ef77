"""The inject-faults job: a copy of a log whose wheel odometry has realistic faults, for testing on real scans.

Every record is copied as it is except the odometry: ``nav_msgs/Odometry`` poses and the wheel
angles of ``sensor_msgs/JointState`` get the faults of :mod:`trundle.fusion.odometry.faults`
(heading glitches, slip, scale error, dropouts). Fault times are seconds after the first odometry
reading. The faults are stored in the output's ``faults`` metadata record (JSON), so a test or
a reader of the log knows what was done to it. The wheel model that turns a heading glitch into
wheel angles comes from the config's ``[odometry]`` table or the log (as for ``trundle slam``).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, cast

import numpy as np

from trundle.fusion.odometry.faults import OdometryFault, dropped, faulty_poses, faulty_wheels
from trundle.logs import messages as m
from trundle.logs import ros2
from trundle.logs.errors import UsageError, UserError
from trundle.logs.outputs import json_text
from trundle.logs.paths import new_file
from trundle.logs.reader import LogReader, damage_dict
from trundle.logs.recover import copy_log
from trundle.tools.jobs.config import JobConfig, make_odometry

ODOMETRY_TYPE, JOINT_STATE_TYPE = "nav_msgs/msg/Odometry", "sensor_msgs/msg/JointState"

Key = tuple[str, int, bytes]  # topic, log time, original data


def inject_faults(log: Path, output: Path, faults: list[OdometryFault],
                  config: JobConfig = None) -> dict[str, Any]:
    """Write ``output``: ``log`` with ``faults`` in its odometry. Returns a report: what the log's damage
    skipped (``log_damage``, None when intact), the faults and, per odometry topic, the messages it had,
    dropped and kept. A fault that starts outside the log's odometry is a UsageError (it would be
    reported but never injected)."""
    new_file(output, "output log")
    reader = LogReader(log)
    info = reader.info()
    topics = {name: t.ros_type for name, t in info.topics.items() if t.ros_type in (ODOMETRY_TYPE, JOINT_STATE_TYPE)}
    if not topics:
        raise UserError(f"{log} has no odometry (nav_msgs/Odometry or sensor_msgs/JointState topic)")
    raw = [r for r in reader.raw_messages(topics=topics) if r.data]
    # the two types asked for: nav_msgs/Odometry and sensor_msgs/JointState
    decoded = [(r, cast(m.Odometry | m.JointState, ros2.decode(r.ros_type, r.data))) for r in raw]
    start_ns = min(msg.stamp_ns for _, msg in decoded)
    span_s = (max(msg.stamp_ns for _, msg in decoded) - start_ns) * 1e-9
    for fault in faults:
        if not 0.0 <= fault.start_s <= span_s:
            raise UsageError(f"{fault.kind} at {fault.start_s:g} s is outside the log's odometry "
                             f"(0 to {span_s:.2f} s after its first reading): nothing would be injected")
    wheels = make_odometry(info, config) if JOINT_STATE_TYPE in topics.values() else None
    replacements: dict[Key, bytes | None] = {}
    counts: dict[str, dict[str, int]] = {}
    for topic, ros_type in sorted(topics.items()):
        items = [(r, msg) for r, msg in decoded if r.topic == topic]
        times = np.array([(msg.stamp_ns - start_ns) * 1e-9 for _, msg in items])
        new: list[m.Odometry] | list[m.JointState]
        if ros_type == ODOMETRY_TYPE:
            new = _odometry([(r, msg) for r, msg in items if isinstance(msg, m.Odometry)], times, faults)
        else:
            assert wheels is not None
            new = _joint_states([(r, msg) for r, msg in items if isinstance(msg, m.JointState)], times, faults,
                                wheels.left, wheels.right, 0.5 * (wheels.left_radius_m + wheels.right_radius_m),
                                wheels.track_m)
        lost = dropped(times, faults)
        for (r, _), msg, gone in zip(items, new, lost, strict=True):
            replacements[(topic, r.log_time_ns, r.data)] = None if gone else ros2.encode(msg)[1]
        counts[topic] = {"messages": len(items), "dropped": int(lost.sum()), "kept": len(items) - int(lost.sum())}

    def replace(topic: str, schema: str, log_time_ns: int, data: bytes) -> bytes | None:
        return replacements.get((topic, log_time_ns, bytes(data)), data)

    records = {"faults": {"faults": json_text([f.as_dict() for f in faults]), "source": str(log),
                          "start_ns": str(start_ns)}}
    copy_log(log, output, replace, records)
    return {"log": str(log), "log_damage": damage_dict(reader.last_damage), "output": str(output),
            "faults": [f.as_dict() for f in faults], "topics": counts}


def _odometry(items: list[tuple[Any, m.Odometry]], times: np.ndarray, faults: list[OdometryFault]) -> list[m.Odometry]:
    poses = np.array([[msg.x, msg.y, msg.theta] for _, msg in items])
    new = faulty_poses(times, poses, faults)
    return [
        dataclasses.replace(msg, x=float(p[0]), y=float(p[1]), theta=float(p[2]))
        for (_, msg), p in zip(items, new, strict=True)
    ]


def _joint_states(items: list[tuple[Any, m.JointState]], times: np.ndarray, faults: list[OdometryFault],
                  left: str, right: str, radius_m: float, track_m: float) -> list[m.JointState]:
    """Faulty wheel angles of the odometry's two wheels; other joints, and stale (NaN) readings, untouched."""
    out = [msg for _, msg in items]
    index = [(k, msg.name.index(left), msg.name.index(right)) for k, (_, msg) in enumerate(items)
             if left in msg.name and right in msg.name]
    if not index:
        raise UserError(f"no joint state holds both wheels {left!r} and {right!r}")
    rows = np.array([k for k, _, _ in index])
    lefts = np.array([items[k][1].position[i] for k, i, _ in index], np.float64)
    rights = np.array([items[k][1].position[j] for k, _, j in index], np.float64)
    good = np.isfinite(lefts) & np.isfinite(rights)
    new_left, new_right = lefts.copy(), rights.copy()
    new_left[good], new_right[good] = faulty_wheels(times[rows[good]], lefts[good], rights[good], faults, radius_m,
                                                    track_m)
    for (k, i, j), a, b in zip(index, new_left, new_right, strict=True):
        position = np.array(out[k].position, np.float64)
        position[i], position[j] = a, b
        out[k] = dataclasses.replace(out[k], position=position)
    return out
