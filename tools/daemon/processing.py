"""Online processing off the drivers' threads: SLAM on the scans and odometry, ArUco markers on
the camera images.

The daemon offers every message to ``wants``; the chosen ones go through a bounded queue to one
processing thread (a full queue drops and counts), and the results (``/slam/pose``, map -> odom
on ``/tf``, ``/map``, ``.../markers``, ``.../marker_poses``, and the markers as landmark
observations in the robot frame on ``/landmarks`` once ``/tf_static`` places the camera) go back
through ``publish``. With both SLAM and markers on, the markers are landmarks of the SLAM's pose
graph. SLAM and the marker detector (both bring SciPy) are imported only when configured.
"""

from __future__ import annotations

import collections
import threading
import time
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from trundle.drivers.lifecycle import wall_ns
from trundle.logs import messages as m
from trundle.logs.frames import FrameTree
from trundle.logs.topics import LANDMARK_TOPIC, MAP_TOPIC, SLAM_POSE_TOPIC, TF_STATIC_TOPIC, TF_TOPIC

if TYPE_CHECKING:
    from trundle.fusion.slam.grid_slam import Slam
    from trundle.perception.markers import MarkerDetector
    from trundle.tools.config.robot import FramesConfig, ProcessingConfig

Publish = Callable[[str, m.Message], None]  # (topic, message): log a result as the daemon's own


class Processing:
    """Online processing on its own thread, fed through a bounded queue (drops counted); results
    go to ``publish``. ``slam`` is the ``[slam]`` table, ``frames`` names map and odom."""

    def __init__(self, config: ProcessingConfig, slam: Mapping[str, Any], frames: FramesConfig,
                 publish: Publish) -> None:
        self.config, self.frames, self.publish = config, frames, publish
        self.queue: collections.deque[tuple[str, m.Message] | None] = collections.deque()
        self.wake = threading.Event()
        self.dropped = 0
        self.skipped_scans = 0
        self.errors = 0
        self.last_error = ""
        self.markers_seen: collections.Counter[int] = collections.Counter()
        self.landmarks_published = 0
        self._next_marker_t = 0.0
        self._next_map_t = 0.0
        self._camera_info: dict[str, m.CameraInfo] = {}
        self.slam: Slam | None = None
        self.detector: MarkerDetector | None = None
        self.static_frames: FrameTree | None = None
        if config.slam:
            from trundle.fusion.slam.config import SlamConfig
            from trundle.fusion.slam.estimators import EstimatorInputs, make_estimator
            from trundle.fusion.slam.grid_slam import Slam
            estimator = make_estimator("grid-landmarks" if config.markers else "grid",
                                       EstimatorInputs(SlamConfig.from_mapping(slam)))
            assert isinstance(estimator, Slam)
            self.slam = estimator
        self.scan_topic = self.slam.config.scan.topic if self.slam is not None else ""
        if config.markers:
            from trundle.perception.markers import MarkerDetector
            self.detector = MarkerDetector(config.aruco_dictionary)
            self.static_frames = FrameTree()
        self.thread = threading.Thread(target=self._run, name="processing", daemon=True)

    @property
    def active(self) -> bool:
        """True when anything is configured (else the daemon leaves the thread unstarted)."""
        return self.slam is not None or self.detector is not None

    def wants(self, topic: str, msg: m.Message) -> bool:
        """Whether to ``put`` this message; images are rate-limited to ``markers_hz`` here, camera
        info is kept for the marker poses."""
        if self.static_frames is not None and topic == TF_STATIC_TOPIC:
            self.static_frames.add(topic, msg)  # where the camera is on the robot, for the markers' landmark poses
        if self.slam is not None and (topic in (self.scan_topic, TF_STATIC_TOPIC) or isinstance(msg, m.Odometry)):
            return True
        if self.detector is not None:
            if isinstance(msg, m.CameraInfo):
                self._camera_info[msg.frame_id] = msg
            elif isinstance(msg, m.CompressedImage | m.Image):
                now = time.monotonic()
                if now >= self._next_marker_t:  # rate-limit before queueing: images are large
                    self._next_marker_t = now + 1.0 / max(self.config.markers_hz, 1e-3)
                    return True
        return False

    def put(self, topic: str, msg: m.Message) -> None:
        """Queue a message for the processing thread (dropped and counted when the queue is full)."""
        if len(self.queue) >= self.config.queue_size:
            self.dropped += 1
            return
        self.queue.append((topic, msg))
        self.wake.set()

    def stop(self) -> None:
        """Finish what is queued and end the thread (waits up to 10 s)."""
        self.queue.append(None)
        self.wake.set()
        self.thread.join(10.0)

    def _run(self) -> None:
        while True:
            self.wake.wait(0.5)
            self.wake.clear()
            batch = [self.queue.popleft() for _ in range(len(self.queue))]
            # behind real time: of the scans waiting, SLAM takes the newest (odometry is all used)
            scans = [i for i, item in enumerate(batch) if item is not None and isinstance(item[1], m.LaserScan)]
            self.skipped_scans += max(len(scans) - 1, 0)
            stale = set(scans[:-1])
            for i, item in enumerate(batch):
                if item is None:
                    return
                if i in stale:
                    continue
                try:
                    self._handle(*item)
                except Exception as error:  # noqa: BLE001 -- keep processing the next message
                    self.errors += 1
                    self.last_error = f"{type(error).__name__}: {error}"

    def _handle(self, topic: str, msg: m.Message) -> None:
        frames = self.frames
        if isinstance(msg, m.CompressedImage | m.Image):
            self._detect_markers(topic, msg)
            return
        assert self.slam is not None
        result = self.slam.process(topic, msg)
        if result is None:
            return
        now = wall_ns()
        x, y, theta = (float(v) for v in result.pose_map)
        self.publish(SLAM_POSE_TOPIC, m.Pose2D(result.stamp_ns, frames.map, x, y, theta))
        mx, my, mt = (float(v) for v in self.slam.map_to_odom)
        self.publish(TF_TOPIC, m.TFMessage((m.TransformStamped.planar(result.stamp_ns, frames.map, frames.odom,
                                                                   mx, my, mt),)))
        if time.monotonic() >= self._next_map_t:
            self._next_map_t = time.monotonic() + self.config.map_period_s
            self.publish(MAP_TOPIC, self.slam.build_map().to_message(now, frames.map))

    def _detect_markers(self, topic: str, msg: m.CompressedImage | m.Image) -> None:
        from trundle.perception.landmarks import marker_observation  # loaded with the detector
        from trundle.perception.markers import marker_pose
        if isinstance(msg, m.CompressedImage):
            image = cv2.imdecode(np.frombuffer(msg.data, np.uint8), cv2.IMREAD_GRAYSCALE)
        else:
            image = msg.to_array()
        if image is None:
            return
        assert self.detector is not None and self.static_frames is not None
        info = self._camera_info.get(msg.frame_id)
        base = topic.rsplit("/image_raw", 1)[0]
        camera_in_base = self.static_frames.try_transform(self.frames.base, msg.frame_id)
        observations = []
        for marker in self.detector.detect(image):
            self.markers_seen[marker.id] += 1
            self.publish(f"{base}/markers", m.ImageMarker(
                msg.stamp_ns, msg.frame_id, "aruco", marker.id, m.POLYGON, marker.centre,
                points=marker.corners))
            if info is not None and info.k[0, 0] > 0:  # calibrated
                pose = marker_pose(marker, info, self.config.marker_size_m)
                self.publish(f"{base}/marker_poses", m.TFMessage((m.TransformStamped(
                    msg.stamp_ns, msg.frame_id, f"aruco_{marker.id}", pose.translation, pose.quaternion()),)))
                landmark = None if camera_in_base is None else marker_observation(
                    marker, pose, info, self.config.marker_size_m, camera_in_base)
                if landmark is not None:
                    observations.append(landmark)
        if observations:
            landmarks = m.LandmarkList(msg.stamp_ns, self.frames.base, tuple(observations))
            self.publish(LANDMARK_TOPIC, landmarks)
            self.landmarks_published += 1
            if self.slam is not None:
                self.slam.process(LANDMARK_TOPIC, landmarks)

    def diagnostics(self, robot: str) -> m.DiagnosticStatus:
        """The ``robot/processing`` entry of ``/diagnostics``: ERROR once a message failed to process
        (SLAM or marker detection raised), with the last error; OK otherwise."""
        values = (("errors", str(self.errors)), ("dropped", str(self.dropped)),
                  ("skipped_scans", str(self.skipped_scans)))
        if self.errors:
            return m.DiagnosticStatus(m.ERROR, f"{robot}/processing",
                                      f"{self.errors} message(s) failed to process: {self.last_error}", "", values)
        return m.DiagnosticStatus(m.OK, f"{robot}/processing", "ok", "", values)

    def status(self) -> dict[str, Any]:
        """The ``processing`` entry of the status answer: queue, drops, errors, SLAM and marker counts."""
        out: dict[str, Any] = {"queue": len(self.queue), "dropped": self.dropped, "skipped_scans": self.skipped_scans,
                               "errors": self.errors, "last_error": self.last_error}
        if self.slam is not None:
            s = self.slam.stats
            out["slam"] = {"scans": s.scans, "keyframes": s.keyframes, "matched": s.matched,
                           "loop_closures": s.loop_closures}
        if self.detector is not None:
            out["markers"] = {str(k): v for k, v in sorted(self.markers_seen.items())}
            out["landmark_messages"] = self.landmarks_published
        return out
