"""The demo's output scored against the simulated world: the SLAM trajectory and wheel odometry
against the ground truth (ATE, RPE), the SLAM map against the world's walls, and ArUco marker
detections and poses against the markers the simulator had in view and their known poses.
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from trundle.fusion.evaluation.trajectory_errors import (
    AbsoluteError,
    RelativeError,
    Trajectory,
    absolute_trajectory_error,
    poses_at,
    relative_pose_error,
)
from trundle.fusion.geometry import compose, transform_points
from trundle.fusion.mapping.map_io import OCCUPIED_THRESH
from trundle.logs import messages as m
from trundle.logs.errors import UserError
from trundle.logs.frames import BASE_FRAME, FrameTree, planar
from trundle.logs.reader import LogReader
from trundle.logs.topics import CAMERA_INFO_TOPIC, IMAGE_TOPIC
from trundle.perception.images import decode_image, to_gray
from trundle.perception.markers import MarkerDetector, marker_pose
from trundle.tools.jobs.progress import NoProgress, ProgressFactory
from trundle.tools.sim.camera_render import CameraPose, CameraRenderer, PinholeCamera, optical_rotation
from trundle.tools.sim.robot import Mount
from trundle.tools.sim.world import World

# ---------------------------------------------------------------------------------- trajectory


@dataclass(frozen=True)
class TrajectoryScore:
    """A SLAM run's trajectories against the ground truth (one pose per scan): the ATE of the SLAM
    estimate (its alignment places the map in the world) and of wheel odometry alone, and the
    SLAM estimate's RPE over about a second of scans (None: the run has no more scans than that)."""

    ate: AbsoluteError
    odometry_ate: AbsoluteError
    rpe: RelativeError | None


def score_trajectory(estimate: Trajectory, odometry: Trajectory, truth: Trajectory) -> TrajectoryScore:
    """Trajectory errors of the SLAM ``estimate`` and the wheel ``odometry`` against ``truth``."""
    ate = absolute_trajectory_error(estimate, truth)
    odometry_ate = absolute_trajectory_error(odometry, truth)
    scan_period = float(np.median(np.diff(truth.stamps_ns))) if len(truth) > 1 else 0.0   # ns
    rpe_step = max(1, int(round(1e9 / scan_period))) if scan_period > 0 else 1             # scans in a second
    rpe = relative_pose_error(estimate, truth, step=rpe_step) if len(truth) > rpe_step else None
    return TrajectoryScore(ate, odometry_ate, rpe)


def path_length(poses: np.ndarray) -> float:
    """Length (m) of the polyline through the poses' positions."""
    return float(np.hypot(*np.diff(np.asarray(poses)[:, :2], axis=0).T).sum()) if len(poses) > 1 else 0.0


# ---------------------------------------------------------------------------------- map


def segment_distances(points: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """Distance (m) from each point (N, 2) to the nearest of the segments (S, 4) ``x1 y1 x2 y2``."""
    a, b = segments[None, :, :2], segments[None, :, 2:]
    p = np.asarray(points, np.float64)[:, None, :]
    e = b - a
    u = np.clip(((p - a) * e).sum(-1) / np.maximum((e * e).sum(-1), 1e-18), 0.0, 1.0)
    return np.hypot(*np.moveaxis(p - (a + u[..., None] * e), -1, 0)).min(axis=1)


def map_wall_distances(grid: m.OccupancyGrid, world: World, map_to_world: np.ndarray) -> np.ndarray:
    """Distance (m) of every occupied map cell's centre to the nearest wall of ``world``, with the map
    placed in the world by ``map_to_world`` (x, y, theta)."""
    rows, cols = np.nonzero(grid.data >= OCCUPIED_THRESH * 100)
    cells = np.stack([cols + 0.5, rows + 0.5], axis=1) * grid.resolution
    map_points = transform_points(np.array([grid.origin_x, grid.origin_y, grid.origin_theta]), cells)
    return segment_distances(transform_points(map_to_world, map_points), world.segments)


# ---------------------------------------------------------------------------------- markers


@dataclass(eq=False)
class MarkerSighting:
    """One detected marker in one frame, scored against the world: ``in_view`` is whether the
    simulator had it in view (``CameraRenderer.visible_decals``: facing the camera within 60 deg,
    sides of 24 px or more, unoccluded), ``in_image`` whether it was in the image at all (any size
    or angle; a detection that is not is false); errors are of the detected pose in the camera's
    optical frame against the marker's known pose seen from the true camera."""

    stamp_ns: int
    id: int
    corners: np.ndarray
    in_view: bool
    in_image: bool
    known: bool
    distance_m: float = math.nan
    position_error_m: float = math.nan
    angle_error_deg: float = math.nan
    rvec: np.ndarray | None = None
    tvec: np.ndarray | None = None


@dataclass(eq=False)
class MarkerScore:
    """ArUco detection over a log's frames: ``in_view`` counts, per marker id, the frames in which
    the simulator had it in view; ``sightings`` are every detection; ``missed`` the (stamp, id)
    pairs in view but not detected. ``frames`` had ground truth, ``unmatched`` had none."""

    frames: int = 0
    unmatched: int = 0
    in_view: collections.Counter[int] = field(default_factory=collections.Counter)
    sightings: list[MarkerSighting] = field(default_factory=list)
    missed: list[tuple[int, int]] = field(default_factory=list)
    camera_info: m.CameraInfo | None = None
    best_stamp_ns: int | None = None

    def detected_ids(self) -> list[int]:
        """The ids detected in a frame that had them in view (sorted)."""
        return sorted({s.id for s in self.sightings if s.in_view})

    def summary(self, world: World) -> list[dict[str, Any]]:
        """Per detected id: frames detected and in view, and pose errors (m, deg) over its sightings."""
        rows = []
        for marker_id in sorted({s.id for s in self.sightings}):
            mine = [s for s in self.sightings if s.id == marker_id]
            scored = [s for s in mine if np.isfinite(s.position_error_m)]
            row: dict[str, Any] = {"id": marker_id, "frames_detected": len(mine),
                                   "frames_in_view": self.in_view[marker_id], "in_world": mine[0].known,
                                   "false_detections": sum(not s.in_image for s in mine)}
            if scored:
                pos = np.array([s.position_error_m for s in scored])
                ang = np.array([s.angle_error_deg for s in scored])
                dist = np.array([s.distance_m for s in scored])
                row.update(distance_m={"min": float(dist.min()), "max": float(dist.max())},
                           position_error_m={"median": float(np.median(pos)), "rms": float(np.sqrt(np.mean(pos ** 2))),
                                             "max": float(pos.max())},
                           angle_error_deg={"median": float(np.median(ang)), "rms": float(np.sqrt(np.mean(ang ** 2))),
                                            "max": float(ang.max())})
            if marker_id in {d.marker_id for d in world.markers}:
                d = world.marker(marker_id)
                row["world_pose"] = {"x": d.x, "y": d.y, "z": d.z, "yaw": d.yaw, "size_m": d.width}
            rows.append(row)
        return rows


def sensor_mount(log: Path, child_frame: str, parent_frame: str = BASE_FRAME) -> Mount:
    """A sensor's mount on the robot: ``child_frame`` in ``parent_frame`` by the log's ``/tf_static``."""
    with LogReader(log) as reader:
        pose = FrameTree.from_log(reader).transform(parent_frame, child_frame)
    x, y, yaw = planar(pose)
    return Mount(float(x), float(y), float(pose[2, 3]), float(yaw))


def camera_from_info(info: m.CameraInfo) -> PinholeCamera:
    """The pinhole intrinsics of a calibrated CameraInfo."""
    k = np.asarray(info.k, np.float64).reshape(3, 3)
    if k[0, 0] <= 0 or k[1, 1] <= 0:
        raise UserError(f"camera info of {info.frame_id!r} is not calibrated (K is zero): marker poses need it")
    return PinholeCamera(int(info.width), int(info.height), float(k[0, 0]), float(k[1, 1]), float(k[0, 2]),
                         float(k[1, 2]))


def camera_pose(base: np.ndarray, mount: Mount) -> CameraPose:
    """The level camera's pose in the world for a base_link pose and the camera's mount."""
    x, y, yaw = compose(np.asarray(base, np.float64), np.array([mount.x, mount.y, mount.yaw]))
    return CameraPose(float(x), float(y), mount.z, float(yaw))


def marker_truth(world: World, marker_id: int, pose: CameraPose) -> tuple[np.ndarray, np.ndarray]:
    """Rotation (3x3) and translation (m) of a world marker in the optical frame of a camera at ``pose``
    (marker frame as ``trundle.perception.markers``: x right, y up, z out of the marker)."""
    decal = world.marker(marker_id)
    camera_axes = optical_rotation(pose.yaw)                      # optical axes as columns, in the map
    right = np.array([-math.sin(decal.yaw), math.cos(decal.yaw), 0.0])
    axes = np.column_stack([right, [0.0, 0.0, 1.0], [*decal.normal, 0.0]])
    translation = (np.array([decal.x, decal.y, decal.z]) - np.array([pose.x, pose.y, pose.z])) @ camera_axes
    return camera_axes.T @ axes, translation


def score_markers(log: Path, frames: Trajectory, world: World, mount: Mount,
                  progress: ProgressFactory = NoProgress) -> MarkerScore:
    """Detect ArUco markers (ids, corners, poses) in every logged frame and score them against the
    simulator: which markers a frame had in view (from the true camera pose at that frame) and the
    known marker poses of the world file. Marker sizes are the world's. ``frames``: the true
    base_link pose at each frame's stamp; ``mount``: the camera's on the robot."""
    detector = MarkerDetector(world.aruco_dictionary)
    score = MarkerScore()
    renderer: CameraRenderer | None = None
    best: tuple[int, float] = (0, 0.0)
    with LogReader(log) as reader:
        info = reader.info()
        total = info.topics[IMAGE_TOPIC].count if IMAGE_TOPIC in info.topics else 0
        bar = progress("markers", total)
        for item in reader.messages(topics=[CAMERA_INFO_TOPIC, IMAGE_TOPIC]):
            msg = item.msg
            if isinstance(msg, m.CameraInfo):
                score.camera_info = msg
                renderer = CameraRenderer(world, camera_from_info(msg))
                continue
            if not isinstance(msg, (m.CompressedImage, m.Image)):
                continue
            base, found = poses_at(frames, np.array([msg.stamp_ns]), tolerance_ns=0)
            if renderer is None or score.camera_info is None or not found[0]:
                score.unmatched += 1
                continue
            score.frames += 1
            pose = camera_pose(base[0], mount)
            visible = {d.marker_id for d, _ in renderer.visible_decals(pose) if d.kind == "marker"}
            present = {d.marker_id for d, _ in renderer.visible_decals(pose, min_side_px=1.0, max_incidence_deg=89.9,
                                                                       border_px=0.0) if d.kind == "marker"}
            score.in_view.update(visible)
            detections = detector.detect(to_gray(decode_image(msg)))
            world_ids = {d.marker_id for d in world.markers}
            for marker in detections:
                sighting = MarkerSighting(msg.stamp_ns, marker.id, marker.corners, marker.id in visible,
                                          marker.id in present, marker.id in world_ids)
                if sighting.known:
                    estimate = marker_pose(marker, score.camera_info, world.marker(marker.id).width)
                    rotation, translation = marker_truth(world, marker.id, pose)
                    cos_angle = (np.trace(estimate.rotation.T @ rotation) - 1.0) / 2.0
                    sighting.distance_m = float(np.linalg.norm(translation))
                    sighting.position_error_m = float(np.linalg.norm(estimate.translation - translation))
                    sighting.angle_error_deg = math.degrees(math.acos(float(np.clip(cos_angle, -1.0, 1.0))))
                    sighting.rvec, sighting.tvec = estimate.rvec, estimate.translation
                score.sightings.append(sighting)
            seen = {k.id for k in detections}
            score.missed += [(msg.stamp_ns, i) for i in sorted(visible - seen)]
            shown = (len(visible & seen), sum(_perimeter(k.corners) for k in detections if k.id in visible))
            if shown > best:
                best, score.best_stamp_ns = shown, msg.stamp_ns
            bar.update(score.frames + score.unmatched, f"{len(score.sightings)} markers detected")
        bar.close()
    return score


def _perimeter(corners: np.ndarray) -> float:
    """Perimeter (px) of a detected marker's outline: the bigger, the better it shows in a picture."""
    return float(np.hypot(*(np.roll(corners, -1, axis=0) - corners).T).sum())
