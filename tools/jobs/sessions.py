"""The session bundle: what ``trundle slam`` leaves in its output folder to be continued
(``trundle slam LOG --continue MAPDIR``), written and read (and checked) here alone.

The bundle is the folder ``session/`` of a slam output, readable without trundle (format
``trundle-session``, :data:`VERSION`):

- ``session.json``: ``format``, ``version``, the sessions (log, keyframes, scans, first and last stamp),
  the laser (beams, ``angle_min``/``angle_max``/``angle_increment`` rad, ``range_min``/``range_max`` m, its
  mount in base_link ``x, y, yaw``), the nodes the optimisation keeps fixed (``fixed``);
- ``config.json``: the ``[slam]`` options the map was made with (:class:`trundle.fusion.slam.config.SlamConfig`);
- ``keyframes.mcap``: every keyframe's scan as logged (``sensor_msgs/msg/LaserScan`` on
  :data:`~trundle.logs.topics.SESSION_SCAN_TOPIC`) and its optimised map pose
  (``geometry_msgs/msg/PoseWithCovarianceStamped`` on :data:`~trundle.logs.topics.SESSION_POSE_TOPIC`), in node order;
- ``nodes.csv``: ``node,session,t_ns,x,y,theta,mount_x,mount_y,mount_yaw`` (m, rad; map frame);
- ``edges.csv``: ``i,j,dx,dy,dtheta,i_xx,i_xy,i_xt,i_yy,i_yt,i_tt``: node ``j``'s pose in node ``i``'s frame and
  the upper triangle of its information matrix (odometry, loop closures, cross-session closures);
- ``scans.csv``: ``t_ns,session,node,dx,dy,dtheta``: every scan's pose relative to its keyframe (the trajectory);
- ``submaps.csv``: ``submap,anchor_node,node``: which keyframes make each submap (every session's keyframes in
  order, a new submap every ``submaps.scans_per_submap``, each keyframe in two);
- ``landmarks.csv`` (when landmarks were mapped): ``id,x,y,c_xx,c_xy,c_yy,sightings,yaw``;
- ``sightings.csv`` (when landmarks were mapped): ``node,landmark,stamp_s,here_x,here_y,here_theta,vx,vy,wz,x,y,
  c_xx,c_xy,c_yy,yaw,yaw_variance``: each sighting tied to its keyframe (the robot at the sighting in the
  keyframe's frame, its velocity, what was seen in the robot frame with its covariance, a marker's yaw and
  its variance, 0 for a point), so the next session optimises the landmarks with it.
"""

from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from trundle.fusion.slam.config import SlamConfig
from trundle.fusion.slam.landmark_grid_slam import Sighting
from trundle.fusion.slam.landmark_slam import LandmarkMap
from trundle.fusion.slam.sessions import SessionGraph, keyframe_points, submap_members
from trundle.logs import messages as m
from trundle.logs.errors import DataError, UserError
from trundle.logs.importers import write_log
from trundle.logs.outputs import write_json, writing_file
from trundle.logs.reader import LogReader
from trundle.logs.topics import SESSION_POSE_TOPIC, SESSION_SCAN_TOPIC

BUNDLE = "session"
FORMAT = "trundle-session"
VERSION = 1

NODES_HEADER = ["node", "session", "t_ns", "x", "y", "theta", "mount_x", "mount_y", "mount_yaw"]
EDGES_HEADER = ["i", "j", "dx", "dy", "dtheta", "i_xx", "i_xy", "i_xt", "i_yy", "i_yt", "i_tt"]
SCANS_HEADER = ["t_ns", "session", "node", "dx", "dy", "dtheta"]
SUBMAPS_HEADER = ["submap", "anchor_node", "node"]
LANDMARKS_HEADER = ["id", "x", "y", "c_xx", "c_xy", "c_yy", "sightings", "yaw"]
SIGHTINGS_HEADER = ["node", "landmark", "stamp_s", "here_x", "here_y", "here_theta", "vx", "vy", "wz", "x", "y",
                    "c_xx", "c_xy", "c_yy", "yaw", "yaw_variance"]
_UPPER = ([0, 0, 0, 1, 1, 2], [0, 1, 2, 1, 2, 2])


def laser_description(scan: m.LaserScan, mount: np.ndarray) -> dict[str, Any]:
    """The laser of a session: beams, angles (rad), ranges (m) and its mount (base_link, m and rad)."""
    return {"frame_id": scan.frame_id, "beams": int(scan.ranges.size), "angle_min": float(scan.angle_min),
            "angle_max": float(scan.angle_max), "angle_increment": float(scan.angle_increment),
            "range_min": float(scan.range_min), "range_max": float(scan.range_max),
            "mount": [float(v) for v in mount]}


def _rows(path: Path, header: list[str], rows: list[list[Any]]) -> None:
    with writing_file(path) as tmp, open(tmp, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(header)
        writer.writerows(rows)


def _f(value: float) -> str:
    return repr(float(value))


def write_bundle(output: Path, graph: SessionGraph, config: SlamConfig, logs: list[str]) -> Path:
    """Write ``output/session/`` for ``graph`` (made with ``config``; ``logs``: each session's log) inside the
    caller's :func:`trundle.logs.outputs.writing_folder`; returns the bundle's folder."""
    folder = output / BUNDLE
    folder.mkdir()
    sessions = []
    for session, log in enumerate(logs):
        scans = graph.scan_stamps[graph.scan_session == session]
        sessions.append({"log": log, "keyframes": int(np.sum(graph.session == session)), "scans": int(scans.size),
                         "start_ns": int(scans.min()) if scans.size else None,
                         "end_ns": int(scans.max()) if scans.size else None})
    write_json(folder / "session.json", {
        "format": FORMAT, "version": VERSION, "sessions": sessions,
        "laser": laser_description(graph.scans[0], graph.mounts[0]), "fixed": sorted(int(k) for k in graph.fixed),
        "keyframes": len(graph), "edges": int(len(graph.edges[0])), "scans": int(graph.scan_stamps.size)})
    write_json(folder / "config.json", config.model_dump())
    items: list[tuple[str, m.Message, int]] = []
    for scan, stamp, pose in zip(graph.scans, graph.stamps, graph.poses, strict=True):
        items.append((SESSION_SCAN_TOPIC, scan, int(stamp)))
        x, y, theta = (float(v) for v in pose)
        items.append((SESSION_POSE_TOPIC, m.Pose2D(int(stamp), "map", x, y, theta), int(stamp)))
    with writing_file(folder / "keyframes.mcap") as tmp:
        write_log(items, tmp, metadata={"command": "slam", "source": "session bundle"})
    _rows(folder / "nodes.csv", NODES_HEADER,
          [[k, int(s), int(t), *map(_f, p), *map(_f, mt)]
           for k, (s, t, p, mt) in enumerate(zip(graph.session, graph.stamps, graph.poses, graph.mounts, strict=True))])
    ij, z, info = graph.edges
    _rows(folder / "edges.csv", EDGES_HEADER,
          [[int(a), int(b), *map(_f, zz), *map(_f, ii[_UPPER])] for (a, b), zz, ii in zip(ij, z, info, strict=True)])
    _rows(folder / "scans.csv", SCANS_HEADER,
          [[int(t), int(s), int(n), *map(_f, o)] for t, s, n, o in
           zip(graph.scan_stamps, graph.scan_session, graph.scan_nodes, graph.scan_offsets, strict=True)])
    _rows(folder / "submaps.csv", SUBMAPS_HEADER,
          [[k, nodes[0], n] for k, nodes in enumerate(submap_members(graph, config)) for n in nodes])
    if graph.sightings:
        _rows(folder / "sightings.csv", SIGHTINGS_HEADER,
              [[v.node, v.landmark, _f(v.stamp_s), *map(_f, v.here), *map(_f, v.velocity), *map(_f, v.position),
                _f(v.position_covariance[0, 0]), _f(v.position_covariance[0, 1]), _f(v.position_covariance[1, 1]),
                _f(v.yaw), _f(v.yaw_variance)] for v in graph.sightings])
    landmarks = graph.landmarks
    if landmarks is not None:
        _rows(folder / "landmarks.csv", LANDMARKS_HEADER,
              [[name, _f(p[0]), _f(p[1]), _f(c[0, 0]), _f(c[0, 1]), _f(c[1, 1]), int(n), _f(y)] for name, p, c, n, y in
               zip(landmarks.ids, landmarks.positions, landmarks.covariances, landmarks.sightings, landmarks.yaw,
                   strict=True)])
    return folder


def _table(path: Path, header: list[str], damaged: str) -> list[list[str]]:
    """The rows of a bundle CSV under ``header``; anything else is the damaged-bundle line."""
    try:
        rows = list(csv.reader(io.StringIO(path.read_text("utf-8"), newline="")))
    except (OSError, UnicodeDecodeError) as error:
        raise DataError(f"{damaged}: {path.name} cannot be read ({error.__class__.__name__})") from None
    if not rows or rows[0] != header:
        raise DataError(f"{damaged}: {path.name} is not a {','.join(header)} table")
    body = [r for r in rows[1:] if r]
    if any(len(r) != len(header) for r in body):
        raise DataError(f"{damaged}: {path.name} has rows of the wrong length")
    return body


def _numbers(rows: list[list[str]], columns: slice, path: str, damaged: str) -> np.ndarray:
    try:
        values = np.array([[float(v) for v in r[columns]] for r in rows], np.float64)
    except ValueError:
        raise DataError(f"{damaged}: {path} holds a value that is not a number") from None
    if not np.all(np.isfinite(values)):
        raise DataError(f"{damaged}: {path} holds a value that is not finite")
    return values


def _json(path: Path, damaged: str) -> dict[str, Any]:
    try:
        value = json.loads(path.read_text("utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as error:
        raise DataError(f"{damaged}: {path.name} cannot be read ({error.__class__.__name__})") from None
    if not isinstance(value, dict):
        raise DataError(f"{damaged}: {path.name} is not a JSON object")
    return value


def read_bundle(mapdir: Path) -> tuple[SessionGraph, SlamConfig, dict[str, Any]]:
    """The session graph, config and ``session.json`` of the slam output ``mapdir``. A folder that is no
    slam output, one from a trundle before session bundles or of another bundle version, and a damaged
    bundle are one line each (UserError / DataError)."""
    if not mapdir.is_dir():
        what = "not a folder" if mapdir.exists() else "no such folder"
        raise UserError(f"--continue {mapdir}: {what} (give the output folder of a trundle slam run)")
    folder = mapdir / BUNDLE
    if not (folder / "session.json").is_file():
        if (mapdir / "map.yaml").is_file() or (mapdir / "report.json").is_file():
            raise UserError(f"--continue {mapdir}: no session bundle ({BUNDLE}/session.json): the map was made by "
                            "an older trundle; map its log again with this one to continue it")
        raise UserError(f"--continue {mapdir}: not the output folder of trundle slam (no {BUNDLE}/session.json)")
    damaged = f"--continue {mapdir}: damaged session bundle"
    meta = _json(folder / "session.json", damaged)
    if meta.get("format") != FORMAT:
        raise DataError(f"{damaged}: session.json is not a {FORMAT} file")
    if meta.get("version") != VERSION:
        raise UserError(f"--continue {mapdir}: session bundle version {meta.get('version')!r}, this trundle reads "
                        f"version {VERSION}: map its log again with this trundle")
    try:
        config = SlamConfig.from_mapping(_json(folder / "config.json", damaged))
    except UserError as error:
        raise DataError(f"{damaged}: config.json: {error}") from None
    nodes = _numbers(_table(folder / "nodes.csv", NODES_HEADER, damaged), slice(0, 9), "nodes.csv", damaged)
    count = len(nodes)
    if count == 0 or not np.array_equal(nodes[:, 0], np.arange(count)) or meta.get("keyframes") != count:
        raise DataError(f"{damaged}: nodes.csv does not list keyframes 0 .. {meta.get('keyframes')} in order")
    edges = _numbers(_table(folder / "edges.csv", EDGES_HEADER, damaged), slice(0, 11), "edges.csv", damaged)
    edges = edges.reshape(-1, 11)
    ij = edges[:, :2].astype(np.int64)
    if len(edges) != meta.get("edges") or (ij.size and (ij.min() < 0 or ij.max() >= count)):
        raise DataError(f"{damaged}: edges.csv names keyframes it does not hold or lost edges")
    info = np.zeros((len(edges), 3, 3))
    info[:, _UPPER[0], _UPPER[1]] = edges[:, 5:]
    info[:, _UPPER[1], _UPPER[0]] = edges[:, 5:]
    if len(info) and np.any(np.linalg.eigvalsh(info)[:, 0] <= 0):
        raise DataError(f"{damaged}: edges.csv holds an information matrix that is not positive definite")
    scans_rows = _numbers(_table(folder / "scans.csv", SCANS_HEADER, damaged), slice(0, 6), "scans.csv", damaged)
    scans_rows = scans_rows.reshape(-1, 6)
    scan_nodes = scans_rows[:, 2].astype(np.int64)
    outside = scan_nodes.size and (scan_nodes.min() < 0 or scan_nodes.max() >= count)
    if len(scans_rows) != meta.get("scans") or outside:
        raise DataError(f"{damaged}: scans.csv names keyframes it does not hold or lost scans")
    taken: list[m.LaserScan] = []
    try:
        for item in LogReader(folder / "keyframes.mcap").messages(topics=[SESSION_SCAN_TOPIC]):
            if isinstance(item.msg, m.LaserScan):
                taken.append(item.msg)
    except (UserError, DataError, OSError) as error:
        raise DataError(f"{damaged}: keyframes.mcap cannot be read ({error})") from None
    if len(taken) != count:
        raise DataError(f"{damaged}: keyframes.mcap holds {len(taken)} scans for {count} keyframes")
    mounts = nodes[:, 6:9]
    points, free = zip(*(keyframe_points(s, mt, config) for s, mt in zip(taken, mounts, strict=True)), strict=True)
    landmarks = None
    if (folder / "landmarks.csv").is_file():
        rows = _table(folder / "landmarks.csv", LANDMARKS_HEADER, damaged)
        values = _numbers(rows, slice(1, 7), "landmarks.csv", damaged).reshape(-1, 6)
        try:  # a point landmark has no yaw (nan)
            yaw = np.array([float(r[7]) for r in rows], np.float64)
        except ValueError:
            raise DataError(f"{damaged}: landmarks.csv holds a yaw that is not a number") from None
        covariances = np.stack([values[:, 2], values[:, 3], values[:, 3], values[:, 4]], axis=1).reshape(-1, 2, 2)
        landmarks = LandmarkMap([r[0] for r in rows], values[:, :2], covariances, values[:, 5].astype(np.int64), yaw)
    sightings = []
    if (folder / "sightings.csv").is_file():
        rows = _table(folder / "sightings.csv", SIGHTINGS_HEADER, damaged)
        values = _numbers([[r[0], *r[2:]] for r in rows], slice(0, 15), "sightings.csv", damaged).reshape(-1, 15)
        if values.size and (values[:, 0].min() < 0 or values[:, 0].max() >= count):
            raise DataError(f"{damaged}: sightings.csv names keyframes it does not hold")
        for row, v in zip(rows, values, strict=True):
            covariance = np.array([[v[10], v[11]], [v[11], v[12]]])
            sightings.append(Sighting(int(v[0]), row[1], float(v[1]), v[2:5].copy(), v[5:8].copy(), v[8:10].copy(),
                                      covariance, float(v[13]), float(v[14])))
    fixed = meta.get("fixed")
    if not isinstance(fixed, list) or any(not isinstance(k, int) or not 0 <= k < count for k in fixed):
        raise DataError(f"{damaged}: session.json's fixed nodes are not keyframes")
    sessions = nodes[:, 1].astype(np.int64)
    if not isinstance(meta.get("sessions"), list) or len(meta["sessions"]) != int(sessions.max()) + 1:
        raise DataError(f"{damaged}: session.json lists {len(meta.get('sessions') or [])} sessions, nodes.csv "
                        f"{int(sessions.max()) + 1}")
    graph = SessionGraph(sessions, nodes[:, 2].astype(np.int64), nodes[:, 3:6], taken, mounts, list(points),
                         list(free), (ij.reshape(-1, 2), edges[:, 2:5].reshape(-1, 3), info),
                         scans_rows[:, 0].astype(np.int64), scans_rows[:, 1].astype(np.int64), scan_nodes,
                         scans_rows[:, 3:6], landmarks, set(fixed), sightings=sightings)
    members: dict[str, list[int]] = {}
    for row in _table(folder / "submaps.csv", SUBMAPS_HEADER, damaged):
        members.setdefault(row[0], []).append(int(row[2]) if row[2].isdigit() else -1)
    if list(members.values()) != submap_members(graph, config):
        raise DataError(f"{damaged}: submaps.csv does not hold the submaps its keyframes make")
    return graph, config, meta


def _differences(there: Any, here: Any, prefix: str = "") -> list[str]:
    """The dotted keys whose values differ between two config dumps, with both values."""
    if isinstance(there, dict) and isinstance(here, dict):
        out = []
        for key in sorted(set(there) | set(here)):
            out += _differences(there.get(key), here.get(key), f"{prefix}{key}.")
        return out
    if isinstance(there, list | tuple) and isinstance(here, list | tuple) and len(there) == len(here):
        same = all(not _differences(a, b) for a, b in zip(there, here, strict=True))
        return [] if same else [f"{prefix[:-1]} {list(there)} there, {list(here)} here"]
    if isinstance(there, float) and isinstance(here, float) and math.isclose(there, here, rel_tol=1e-9):
        return []
    return [] if there == here else [f"{prefix[:-1]} {there!r} there, {here!r} here"]


def check_config(mapdir: Path, there: SlamConfig, here: SlamConfig) -> None:
    """A map continues only with the ``[slam]`` options it was made with (but ``sessions``): one line naming
    the first option that differs."""
    differences = [d for d in _differences(there.model_dump(), here.model_dump()) if not d.startswith("sessions.")]
    if differences:
        more = f" (and {len(differences) - 1} more)" if len(differences) > 1 else ""
        raise UserError(f"--continue {mapdir}: the map was made with another [slam] config: {differences[0]}{more}")


def check_laser(mapdir: Path, meta: dict[str, Any], scan: m.LaserScan, mount: np.ndarray,
                allow_new_area: bool = False) -> str | None:
    """A map continues only with the laser it was made with: beams, field of view, range limits and mount
    (1 mm, 1 mrad); else one line saying both. With ``allow_new_area`` (the log may be of somewhere else)
    that line is returned for the report instead (None: the same laser)."""
    there = meta.get("laser")
    here = laser_description(scan, mount)
    if not isinstance(there, dict):
        raise DataError(f"--continue {mapdir}: damaged session bundle: session.json has no laser")
    same = (there.get("beams") == here["beams"]
            and all(math.isclose(float(there.get(k, math.nan)), here[k], abs_tol=1e-4)
                    for k in ("angle_min", "angle_max", "angle_increment"))
            and all(math.isclose(float(there.get(k, math.nan)), here[k], rel_tol=1e-4, abs_tol=1e-3)
                    for k in ("range_min", "range_max"))
            and np.allclose(np.asarray(there.get("mount", [math.nan] * 3), np.float64), here["mount"], atol=1e-3))

    def said(d: dict[str, Any]) -> str:
        fov = math.degrees(float(d.get("angle_max", math.nan)) - float(d.get("angle_min", math.nan)))
        x, y, yaw = d.get("mount", [math.nan] * 3)
        return (f"{d.get('beams')} beams over {fov:.1f} deg to {float(d.get('range_max', math.nan)):.1f} m at "
                f"({x:.3f} m, {y:.3f} m, {math.degrees(yaw):.1f} deg)")

    if same:
        return None
    line = f"the map was made with another laser: {said(there)} there, {said(here)} here"
    if not allow_new_area:
        raise UserError(f"--continue {mapdir}: {line} (--allow-new-area adds the log as a part of its own)")
    return line
