"""Reader of the iSAM / GTSAM 2-D text graph (the Victoria Park graph GTSAM ships) into a FactorGraph.

Lines, whitespace separated, one record each (metres, radians):

- ``ODOMETRY i j dx dy dtheta v1 .. v6`` (also ``EDGE2``, ``EDGE``, ``EDGE_SE2``): pose j in the
  frame of pose i. The six numbers are read as GTSAM's ``load2D`` reads them by default: when they
  have the pattern ``v1 0 0 v4 0 v6`` they are the covariance ``diag(v1, v4, v6)`` (the Victoria
  Park file: ``0.0001 0 0 4e-06 0 4e-06``), when ``v1 0 v3 v4 0 0`` the covariance in the layout GTSAM calls ``GRAPH``
  ``[v1 v2 v5; v2 v3 v6; v5 v6 v4]``; any other pattern is refused, as GTSAM does.
- ``LANDMARK i l dx dy v1 v2 v3``: point l at ``(dx, dy)`` in the frame of pose i. GTSAM turns it
  into a bearing-range factor with ``sigma_bearing = sqrt(v1 / 10)`` rad and ``sigma_range =
  sqrt(v1)`` m (the x-y covariance taken as describing a sighting at 10 m) when ``v1 == v3``;
  otherwise (with a warning) unit sigmas. The same is done here, so chi2 values are comparable.
- ``BR i l bearing range sigma_bearing sigma_range``: a bearing-range sighting as such.
- ``VERTEX2 id x y theta`` (also ``VERTEX``, ``VERTEX_SE2``): an initial pose.

Initial values follow GTSAM: a pose first met as the end of an odometry edge is the composition
of its start with the measurement, a pose met first otherwise is the origin, a point is placed by
its first sighting. Pose and point ids may be any non-negative integers (they are renumbered in
order of appearance); the first pose stays fixed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from trundle.fusion.geometry import compose
from trundle.fusion.optimization.factor_graph import FactorGraph
from trundle.logs.errors import UserError

EDGE_TAGS = ("ODOMETRY", "EDGE2", "EDGE", "EDGE_SE2")
VERTEX_TAGS = ("VERTEX2", "VERTEX", "VERTEX_SE2")
GTSAM_LANDMARK_RANGE_M = 10.0  # load2D's assumed range of a LANDMARK line's x-y covariance


@dataclass
class IsamGraph:
    """A read graph: the factor graph, the file's pose and point ids by index, and notes on the read.

    ``nonuniform_landmarks`` counts LANDMARK lines whose covariance GTSAM (and so this reader)
    replaces by unit sigmas.
    """

    graph: FactorGraph
    pose_ids: list[int] = field(default_factory=list)
    point_ids: list[int] = field(default_factory=list)
    nonuniform_landmarks: int = 0


def edge_covariance(values: list[float]) -> np.ndarray:
    """The 3x3 covariance of an odometry line's six numbers, by GTSAM's automatic layout detection."""
    v1, v2, v3, v4, v5, v6 = values
    if v1 != 0 and v2 == 0 and v3 != 0 and v4 != 0 and v5 == 0 and v6 == 0:
        return np.array([[v1, v2, v5], [v2, v3, v6], [v5, v6, v4]])
    if v1 != 0 and v2 == 0 and v3 == 0 and v4 != 0 and v5 == 0 and v6 != 0:
        return np.array([[v1, v2, v3], [v2, v4, v5], [v3, v5, v6]])
    raise ValueError(f"unrecognised covariance layout {values} (GTSAM's load2D refuses it too)")


def landmark_sigmas(v1: float, v3: float) -> tuple[float, float] | None:
    """(sigma_range m, sigma_bearing rad) of a LANDMARK line's covariance as GTSAM's load2D sets them;
    None when the covariance is not uniform (GTSAM then uses unit sigmas)."""
    if abs(v1 - v3) >= 1e-4:
        return None
    return math.sqrt(v1), math.sqrt(v1 / GTSAM_LANDMARK_RANGE_M)


def read_isam_graph(path: str | Path) -> IsamGraph:
    """Read an iSAM/GTSAM text graph; a malformed line is a UserError naming the file and line."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"no such graph file: {path}")
    result = IsamGraph(FactorGraph())
    graph = result.graph
    poses: dict[int, int] = {}
    points: dict[int, int] = {}
    initial: dict[int, np.ndarray] = {}
    placed: list[np.ndarray] = []  # initial value of every pose added, by index

    def pose(key: int, guess: np.ndarray | None = None) -> int:
        if key not in poses:
            placed.append(initial.get(key, guess if guess is not None else np.zeros(3)))
            poses[key] = graph.add_pose(placed[-1])
            result.pose_ids.append(key)
        return poses[key]

    def point(key: int, seen_from: int, xy: np.ndarray) -> int:
        if key not in points:
            points[key] = graph.add_point(compose(placed[seen_from], np.array([*xy, 0.0]))[:2])
            result.point_ids.append(key)
        return points[key]

    with path.open("r", encoding="ascii", errors="replace") as handle:
        lines = handle.readlines()
    try:
        for tokens in (line.split() for line in lines):
            if tokens and tokens[0] in VERTEX_TAGS and len(tokens) >= 5:
                initial[int(tokens[1])] = np.array([float(t) for t in tokens[2:5]])
    except ValueError as error:
        raise UserError(f"{path}: bad vertex line ({error})") from None
    for number, line in enumerate(lines, 1):
        tokens = line.split()
        if not tokens or tokens[0].startswith("#") or tokens[0] in VERTEX_TAGS:
            continue
        try:
            tag = tokens[0]
            if tag in EDGE_TAGS and len(tokens) == 12:
                i, j = int(tokens[1]), int(tokens[2])
                z = np.array([float(t) for t in tokens[3:6]])
                covariance = edge_covariance([float(t) for t in tokens[6:12]])
                a = pose(i)
                b = pose(j, compose(placed[a], z))
                graph.add_between(a, b, z, np.linalg.inv(covariance))
            elif tag == "LANDMARK" and len(tokens) == 8:
                i, key = int(tokens[1]), int(tokens[2])
                xy = np.array([float(tokens[3]), float(tokens[4])])
                v1, _, v3 = (float(t) for t in tokens[5:8])
                sigmas = landmark_sigmas(v1, v3)
                if sigmas is None:
                    result.nonuniform_landmarks += 1
                    sigmas = (1.0, 1.0)
                a = pose(i)
                b = point(key, a, xy)
                graph.add_range_bearing(a, b, float(np.hypot(*xy)), math.atan2(xy[1], xy[0]),
                                        np.diag([sigmas[0] ** -2, sigmas[1] ** -2]))
            elif tag == "BR" and len(tokens) == 7:
                i, key = int(tokens[1]), int(tokens[2])
                bearing, range_m, sigma_bearing, sigma_range = (float(t) for t in tokens[3:7])
                a = pose(i)
                b = point(key, a, range_m * np.array([math.cos(bearing), math.sin(bearing)]))
                graph.add_range_bearing(a, b, range_m, bearing, np.diag([sigma_range ** -2, sigma_bearing ** -2]))
            else:
                raise ValueError(f"unsupported record {tag!r} with {len(tokens)} fields")
        except ValueError as error:
            raise UserError(f"{path}:{number}: not an iSAM 2-D graph line ({error})") from None
    if len(graph) == 0:
        raise UserError(f"{path}: no ODOMETRY, LANDMARK or BR lines")
    return result
