"""Online processing off the drivers' threads: SLAM on the scans and odometry, ArUco markers on
the camera images.

The daemon offers every message to ``wants``; the chosen ones go through a bounded queue to one
processing thread (a full queue drops and counts; behind real time, SLAM skips and counts the scans
more than ``max_scan_lag_s`` older than the newest waiting), and the results (``/slam/pose``, map -> odom
on ``/tf``, ``/map``, ``.../markers``, ``.../marker_poses``, and the markers as landmark
observations in the robot frame on ``/landmarks`` once ``/tf_static`` places the camera) go back
through ``publish``. With both SLAM and markers on, the markers are landmarks of the SLAM's pose
graph. SLAM and the marker detector (both bring SciPy) are imported only when configured. The ``/map``
is built off the scans' path: every ``map_period_s`` the processing thread takes a snapshot of the
keyframes and a map thread builds and publishes it (incrementally: only new keyframes' rays are cast
unless a loop closure moved the graph), so no scan waits for a map.

``trundle replay`` runs the same class on a log's messages: on the thread at a real-time rate, or
through ``handle`` message by message at rate 0 (nothing skipped, the map built in line), with the
log's time as ``clock``.
The SLAM estimator is built by the caller through :mod:`trundle.fusion.slam.estimators` (the daemon's
by :func:`online_estimator`).
"""

from __future__ import annotations

import collections
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from trundle.logs import messages as m
from trundle.logs.frames import FrameTree
from trundle.logs.topics import LANDMARK_TOPIC, MAP_TOPIC, PATH_TOPIC, SLAM_POSE_TOPIC, TF_STATIC_TOPIC, TF_TOPIC

if TYPE_CHECKING:
    from trundle.fusion.slam.backend import MapInputs
    from trundle.fusion.slam.grid_slam import Slam
    from trundle.perception.markers import MarkerDetector
    from trundle.tools.config.robot import FramesConfig, ProcessingConfig

Publish = Callable[[str, m.Message], None]  # (topic, message): log a result as the daemon's own
INPUT_TYPES: tuple[type[m.Message], ...] = (m.LaserScan, m.TFMessage, m.Odometry, m.JointState, m.LandmarkList,
                                            m.CompressedImage, m.Image, m.CameraInfo)
"""Every message type ``wants`` may take (a replay decodes no other)."""
STATE_TYPES: tuple[type[m.Message], ...] = (m.TFMessage, m.Odometry, m.JointState)
"""The messages that only update state the next scan reads: queued without waking the processing thread."""
WAKE_PERIOD_S = 0.5  # the processing thread's longest sleep: how long queued state may wait without a scan


def online_estimator(config: ProcessingConfig, slam: Mapping[str, Any]) -> Slam | None:
    """The daemon's SLAM (None unless ``config.slam``): the registry's ``grid`` estimator, ``grid-landmarks``
    with markers on, from the ``[slam]`` table ``slam``; odometry from the ``Odometry`` messages."""
    if not config.slam:
        return None
    from trundle.fusion.slam.config import SlamConfig
    from trundle.fusion.slam.estimators import EstimatorInputs, make_estimator
    from trundle.fusion.slam.grid_slam import Slam
    estimator = make_estimator("grid-landmarks" if config.markers else "grid",
                               EstimatorInputs(SlamConfig.from_mapping(slam)))
    assert isinstance(estimator, Slam)
    return estimator


def _camera(image_topic: str) -> str:
    """The camera's namespace of one of its image topics (``/camera`` of ``/camera/image_raw/compressed``)."""
    return image_topic.rsplit("/image_raw", 1)[0]


class Processing:
    """Online processing on its own thread, fed through a bounded queue (drops counted); results
    go to ``publish``. ``slam`` is the SLAM estimator (None: no SLAM), ``frames`` names map and odom;
    ``clock`` (ns) paces the marker detection and the map: the daemon's monotonic clock, a replay's
    log time."""

    def __init__(self, config: ProcessingConfig, frames: FramesConfig, publish: Publish,
                 slam: Slam | None = None, clock: Callable[[], int] = time.monotonic_ns) -> None:
        self.config, self.frames, self.publish, self.clock = config, frames, publish, clock
        self.queue: collections.deque[tuple[str, m.Message] | None] = collections.deque()
        self.wake = threading.Event()
        self.dropped = 0
        self.skipped_scans = 0
        self.errors = 0
        self.last_error = ""
        self._errors_lock = threading.Lock()
        self.markers_seen: collections.Counter[int] = collections.Counter()
        self.landmarks_published = 0
        self._next_marker_ns: int | None = None
        self._next_map_ns: int | None = None
        self._camera_info: dict[str, m.CameraInfo] = {}
        self.slam = slam
        self.detector: MarkerDetector | None = None
        self.static_frames: FrameTree | None = None
        self.scan_topic = slam.config.scan.topic if slam is not None else ""
        constraints = slam.landmark_constraints if slam is not None else None
        self.landmark_topic = constraints.topic if constraints is not None else ""
        if config.markers:
            from trundle.perception.markers import MarkerDetector
            self.detector = MarkerDetector(config.aruco_dictionary)
            self.static_frames = FrameTree()
        self.thread = threading.Thread(target=self._run, name="processing", daemon=True)
        # the map thread (started with the processing thread): the latest snapshot to build, None to end
        self._map_request: tuple[int, MapInputs] | None = None
        self._map_wake = threading.Event()
        self._map_stop = False
        self._map_thread = threading.Thread(target=self._map_run, name="map", daemon=True)

    @property
    def active(self) -> bool:
        """True when anything is configured (else the daemon leaves the thread unstarted)."""
        return self.slam is not None or self.detector is not None

    def outputs(self, image_topics: Iterable[str]) -> dict[str, type[m.Message]]:
        """The topics it publishes and their message types, given the camera topics it will see."""
        out: dict[str, type[m.Message]] = {}
        if self.slam is not None:
            out |= {SLAM_POSE_TOPIC: m.Pose2D, TF_TOPIC: m.TFMessage, MAP_TOPIC: m.OccupancyGrid, PATH_TOPIC: m.Path}
        if self.detector is not None:
            out[LANDMARK_TOPIC] = m.LandmarkList
            for topic in image_topics:
                base = _camera(topic)
                out |= {f"{base}/markers": m.ImageMarker, f"{base}/marker_poses": m.TFMessage}
        return out

    def wants(self, topic: str, msg: m.Message) -> bool:
        """Whether to ``put`` this message: for SLAM what its estimator reads (the scans, transforms,
        odometry, wheel states when it has a wheel model, sightings on its landmark topic); images are
        rate-limited to ``markers_hz`` here, camera info is kept for the marker poses."""
        if self.static_frames is not None and topic == TF_STATIC_TOPIC:
            self.static_frames.add(topic, msg)  # where the camera is on the robot, for the markers' landmark poses
        slam = self.slam
        if slam is not None and (topic in (self.scan_topic, TF_STATIC_TOPIC, TF_TOPIC) or isinstance(msg, m.Odometry)
                                 or (isinstance(msg, m.JointState) and slam.wheels is not None)
                                 or (isinstance(msg, m.LandmarkList) and topic == self.landmark_topic)):
            return True
        if self.detector is not None:
            if isinstance(msg, m.CameraInfo):
                self._camera_info[msg.frame_id] = msg
            elif isinstance(msg, m.CompressedImage | m.Image):
                now = self.clock()
                if self._next_marker_ns is None or now >= self._next_marker_ns:  # rate-limit before queueing
                    self._next_marker_ns = now + int(1e9 / max(self.config.markers_hz, 1e-3))
                    return True
        return False

    def put(self, topic: str, msg: m.Message) -> None:
        """Queue a message for the processing thread (dropped and counted when the queue is full). Only a
        message with work to do wakes the thread: odometry, wheel states and transforms (hundreds a second)
        only update what the next scan reads, so they wait for it in the queue (at most ``WAKE_PERIOD_S``),
        in order, and the thread wakes about once a scan instead of once a message."""
        if len(self.queue) >= self.config.queue_size:
            self.dropped += 1
            return
        self.queue.append((topic, msg))
        if not isinstance(msg, STATE_TYPES):
            self.wake.set()

    def stop(self) -> None:
        """Finish what is queued and end the threads (waits up to 10 s each; a map asked for is published)."""
        self.queue.append(None)
        self.wake.set()
        self.thread.join(10.0)
        if self._map_thread.is_alive():
            self._map_stop = True
            self._map_wake.set()
            self._map_thread.join(10.0)

    def _run(self) -> None:
        if self.slam is not None:
            self._map_thread.start()
        while True:
            self.wake.wait(WAKE_PERIOD_S)
            self.wake.clear()
            batch = [self.queue.popleft() for _ in range(len(self.queue))]
            # behind real time: SLAM skips the scans waiting more than max_scan_lag_s older than the newest
            # (odometry is all used); a driver that hands over two scans at once is not behind
            stamps = {i: item[1].stamp_ns for i, item in enumerate(batch)
                      if item is not None and isinstance(item[1], m.LaserScan)}
            newest = max(stamps.values(), default=0)
            stale = {i for i, stamp in stamps.items() if newest - stamp > self.config.max_scan_lag_s * 1e9}
            self.skipped_scans += len(stale)
            for i, item in enumerate(batch):
                if item is None:
                    return
                if i not in stale:
                    self.handle(*item)

    def handle(self, topic: str, msg: m.Message) -> None:
        """Process one wanted message now (on the caller's thread); a message that fails is counted
        in ``errors`` and processing goes on with the next."""
        try:
            self._handle(topic, msg)
        except Exception as error:  # noqa: BLE001 -- keep processing the next message
            self._failed(error)

    def _failed(self, error: Exception) -> None:
        """Count a failure (of a message, or of a map on the map thread) and keep it as the last error."""
        with self._errors_lock:
            self.errors += 1
            self.last_error = f"{type(error).__name__}: {error}"

    def finish(self) -> None:
        """End of the input (a replay's end): SLAM's final optimisation, then the final ``/map`` and the
        whole trajectory on ``/path``, stamped with the last scan's time."""
        slam = self.slam
        if slam is None or slam.stats.scans == 0:
            return
        try:
            slam.finish()
            stamps, poses = slam.trajectory()
            end_ns = int(stamps.max())
            self.publish(MAP_TOPIC, slam.build_map().to_message(end_ns, self.frames.map))
            self.publish(PATH_TOPIC, m.Path(end_ns, self.frames.map, stamps, poses))
        except Exception as error:  # noqa: BLE001 -- counted and said like any message that failed
            self._failed(error)

    def _handle(self, topic: str, msg: m.Message) -> None:
        frames = self.frames
        if isinstance(msg, m.CompressedImage | m.Image):
            self._detect_markers(topic, msg)
            return
        assert self.slam is not None
        result = self.slam.process(topic, msg)
        if result is None:
            return
        x, y, theta = (float(v) for v in result.pose_map)
        self.publish(SLAM_POSE_TOPIC, m.Pose2D(result.stamp_ns, frames.map, x, y, theta))
        mx, my, mt = (float(v) for v in self.slam.map_to_odom)
        self.publish(TF_TOPIC, m.TFMessage((m.TransformStamped.planar(result.stamp_ns, frames.map, frames.odom,
                                                                   mx, my, mt),)))
        now = self.clock()
        if self._next_map_ns is None or now >= self._next_map_ns:
            self._next_map_ns = now + int(self.config.map_period_s * 1e9)
            if self._map_thread.is_alive():   # the snapshot to the map thread (a newer one replaces it)
                self._map_request = (result.stamp_ns, self.slam.map_inputs())
                self._map_wake.set()
            else:
                self.publish(MAP_TOPIC, self.slam.build_map().to_message(result.stamp_ns, frames.map))

    def _map_run(self) -> None:
        """The map thread: build and publish each snapshot asked for, until ``stop``."""
        assert self.slam is not None
        while True:
            self._map_wake.wait()
            self._map_wake.clear()
            request, self._map_request = self._map_request, None
            if request is not None:
                stamp_ns, inputs = request
                try:
                    self.publish(MAP_TOPIC, self.slam.build_map(inputs=inputs).to_message(stamp_ns, self.frames.map))
                except Exception as error:  # noqa: BLE001 -- counted and said like any message that failed
                    self._failed(error)
            if self._map_stop and self._map_request is None:
                return

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
        base = _camera(topic)
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
