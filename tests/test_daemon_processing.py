"""The daemon's online processing, fed by a scripted robot: SLAM on /scan + /odom and ArUco
markers on the camera images, with their output checked against the simulator's ground truth."""

from __future__ import annotations

import math
import threading
import time

import cv2
import numpy as np
import pytest

from trundle.drivers.camera import OPTICAL_ROTATION
from trundle.drivers.lifecycle import Driver
from trundle.fusion.geometry import compose, inverse
from trundle.fusion.slam.config import SlamConfig
from trundle.logs import messages as m
from trundle.logs.reader import LogReader
from trundle.tools.config.robot import FramesConfig, ProcessingConfig, parse_config
from trundle.tools.daemon.processing import Processing
from trundle.tools.daemon.service import Daemon
from trundle.tools.sim.camera_render import optical_rotation
from trundle.tools.sim.robot import RobotSim
from trundle.tools.sim.world import load_world

START_S = 14.0  # heading east towards marker 3 on the east wall


class SimRobotDriver(Driver):
    """Publishes, in real time from ``START_S`` of a noise-free run: scans at 20 Hz, exact odometry
    (the odom frame is the pose at the first message) and camera frames with calibration at 5 Hz."""

    def __init__(self, sim: RobotSim, sink) -> None:
        super().__init__("robot", sink)
        self.sim = sim
        self.wall0 = 0
        self.next_image = 0.0
        self.info = sim.camera.camera_info(0, "camera_optical")

    def sim_time(self, stamp_ns: int) -> float:
        return START_S + (stamp_ns - self.wall0) / 1e9

    def open(self) -> None:
        self.wall0 = time.time_ns()
        self.origin = self.sim.pose_at(START_S)
        mount, camera = self.sim.model.laser, self.sim.model.camera
        self.publish("/tf_static", m.TFMessage((
            m.TransformStamped.planar(0, "base_link", "laser", mount.x, mount.y, mount.yaw),
            m.TransformStamped.planar(0, "base_link", "camera", camera.x, camera.y, camera.yaw, z=camera.z),
            m.TransformStamped(0, "camera", "camera_optical", (0.0, 0.0, 0.0), OPTICAL_ROTATION))))
        self.publish("/camera/camera_info", self.info)

    def read_once(self) -> None:
        time.sleep(0.05)
        now = time.time_ns()
        t = self.sim_time(now)
        x, y, theta = compose(inverse(self.origin), self.sim.pose_at(t))
        self.publish("/odom", m.Odometry(now, "odom", "base_link", float(x), float(y), float(theta)))
        model = self.sim.model.laser_model
        self.publish("/scan", m.LaserScan(now, "laser", model.angle_min, model.angle_max, model.angle_increment, 0.0,
                                          model.scan_time, model.range_min, model.range_max, self.sim.ranges_at(t)))
        if t >= self.next_image:
            self.next_image = t + 0.2
            ok, jpeg = cv2.imencode(".jpg", self.sim.frame_at(t), (cv2.IMWRITE_JPEG_QUALITY, 90))
            self.publish(
                "/camera/image_raw/compressed", m.CompressedImage(now, "camera_optical", "jpeg", jpeg.tobytes())
            )

    def close(self) -> None:
        pass


@pytest.fixture(scope="module")
def sim():
    return RobotSim(load_world(), noise=False)


# A real daemon process doing online SLAM on 2 shared cores: seen failing under heavy load
# (SLAM fell behind its deadline) and passing on reruns; one rerun, and a report.
@pytest.mark.flaky(reruns=1)
def test_online_slam_and_markers_follow_the_ground_truth(tmp_path, sim):
    config = parse_config({
        "robot": {"name": "proc"}, "lrf": {"url": "scip2:///dev/sim-robot"},
        "logger": {"folder": str(tmp_path / "logs")}, "status": {"socket": str(tmp_path / "s.sock")},
        "disk": {"min_free_mb": 1.0},
        "processing": {"slam": True, "markers": True, "map_period_s": 1.0, "markers_hz": 5.0,
                       "marker_size_m": 0.25}}, "test")
    drivers = []

    def make(family, url, sink, options):
        drivers.append(SimRobotDriver(sim, sink))
        return drivers[0]

    daemon = Daemon(config, make_driver=make)
    thread = threading.Thread(target=daemon.run, kwargs={"install_signals": False})
    thread.start()
    try:
        deadline = time.monotonic() + 90
        while not (drivers and drivers[0].wall0 and drivers[0].sim_time(time.time_ns()) > START_S + 4.0
                   and daemon.status()["processing"]["slam"]["scans"] >= 10):  # SLAM may run below scan rate
            assert time.monotonic() < deadline
            time.sleep(0.1)
        processing = daemon.status()["processing"]
    finally:
        daemon.stop()
        thread.join(30)
    driver = drivers[0]
    assert processing["errors"] == 0 and processing["slam"]["scans"] >= 10, processing
    assert processing["markers"].get("3", 0) >= 1

    log, = (tmp_path / "logs").glob("*.mcap")
    with LogReader(log) as reader:
        poses = [x.msg for x in reader.messages(topics=["/slam/pose"])]
        maps = [x.msg for x in reader.messages(topics=["/map"])]
        tf = [x.msg for x in reader.messages(topics=["/tf"])]
        markers = [x.msg for x in reader.messages(topics=["/camera/markers"])]
        marker_poses = [x.msg for x in reader.messages(topics=["/camera/marker_poses"])]
        landmarks = [x.msg for x in reader.messages(topics=["/landmarks"])]
    # the motion SLAM estimates since its first pose is the true motion
    assert len(poses) >= 10 and maps and all(t.transforms[0].child_frame_id == "odom" for t in tf)
    first = np.array([poses[0].x, poses[0].y, poses[0].theta])
    first_truth = sim.pose_at(driver.sim_time(poses[0].stamp_ns))
    for pose in poses:
        moved = compose(inverse(first), np.array([pose.x, pose.y, pose.theta]))
        truth = compose(inverse(first_truth), sim.pose_at(driver.sim_time(pose.stamp_ns)))
        assert math.hypot(moved[0] - truth[0], moved[1] - truth[1]) < 0.05
    assert math.hypot(truth[0], truth[1]) > 2.0
    free, occupied = (maps[-1].data >= 0) & (maps[-1].data < 20), maps[-1].data > 80
    assert occupied.sum() > 100 and free.sum() > 10 * occupied.sum() and maps[-1].resolution == pytest.approx(0.05)

    # each marker seen has its pose put it where the world file says
    assert 3 in {marker.id for marker in markers}
    for msg in marker_poses:
        transform = msg.transforms[0]
        world_marker = sim.world.marker(int(transform.child_frame_id.removeprefix("aruco_")))
        camera = sim.camera_pose_at(driver.sim_time(transform.stamp_ns))
        where = optical_rotation(camera.yaw) @ transform.translation + np.array([camera.x, camera.y, camera.z])
        distance = float(np.linalg.norm(transform.translation))
        if distance > 6.0:  # a 0.25 m marker is under 22 px there: detected, but its pose is rough
            continue
        error = np.linalg.norm(where - [world_marker.x, world_marker.y, world_marker.z])
        # MJPEG-over-HTTP frames are stamped on arrival (no capture clock): on a loaded machine the
        # stamp lags the render by up to ~0.1 s, i.e. ~0.1 m of robot motion at the route's speed.
        assert error < 0.02 + 0.02 * distance + 0.1, (transform.child_frame_id, distance, error)

    # the same markers as landmark observations in base_link: placed by the true robot pose, each is where
    # the world file has it, within three of its own standard deviations (plus the arrival-stamp lag)
    assert processing["landmark_messages"] >= 1 and landmarks and all(s.frame_id == "base_link" for s in landmarks)
    for sighting in landmarks:
        robot = sim.pose_at(driver.sim_time(sighting.stamp_ns))
        for o in sighting.landmarks:
            world_marker = sim.world.marker(int(o.id))
            if o.range > 6.0:
                continue
            where = compose(robot, np.array([o.translation[0], o.translation[1], 0.0]))[:2]
            error = float(np.hypot(where[0] - world_marker.x, where[1] - world_marker.y))
            sigma = math.sqrt(np.linalg.eigvalsh(o.position_covariance()).max())
            assert o.oriented and error < 3 * sigma + 0.1, (o.id, o.range, error, sigma)


class RecordingSlam:
    """Stands in for the SLAM estimator: records the stamps of the scans it is given."""

    def __init__(self) -> None:
        self.config = SlamConfig()
        self.landmark_constraints = None
        self.wheels = None
        self.stamps: list[int] = []
        self.topics: list[str] = []

    def process(self, topic: str, msg: m.Message) -> None:
        self.topics.append(topic)
        if isinstance(msg, m.LaserScan):
            self.stamps.append(msg.stamp_ns)


def test_scans_handed_over_together_are_all_processed_and_only_stale_ones_skipped() -> None:
    """Behind real time, the scans waiting more than max_scan_lag_s older than the newest are skipped; two
    scans a driver hands over at once (one scan period apart) are both processed."""
    slam = RecordingSlam()
    processing = Processing(ProcessingConfig(slam=True, max_scan_lag_s=0.2), FramesConfig(), lambda topic, msg: None,
                            slam)  # type: ignore[arg-type]
    stamps_ms = [0, 25, 1000, 1025, 1050, 1199, 1200, 1225, 1250, 1275, 1300, 1400]
    for stamp in stamps_ms:   # one batch: all waiting when the thread wakes
        processing.put("/scan", m.LaserScan(stamp * 1_000_000, "laser", -1.0, 1.0, 0.5, 0.0, 0.025, 0.1, 30.0,
                                            np.ones(5, np.float32)))
    processing.thread.start()
    processing.stop()
    kept = [stamp for stamp in stamps_ms if stamp >= 1200]   # the newest is 1400 ms
    assert slam.stamps == [stamp * 1_000_000 for stamp in kept]
    assert processing.skipped_scans == len(stamps_ms) - len(kept) and processing.errors == 0


def test_odometry_and_transforms_wait_for_the_next_scan_in_order() -> None:
    """Odometry and /tf (hundreds a second) do not wake the processing thread; a scan does, and the
    thread then handles everything queued in arrival order, the state before the scan that reads it."""
    slam = RecordingSlam()
    processing = Processing(ProcessingConfig(slam=True), FramesConfig(), lambda topic, msg: None,
                            slam)  # type: ignore[arg-type]
    odom = m.Odometry(1_000_000, "odom", "base_link", 0.1, 0.0, 0.0, 0.0, 0.0, 0.0, np.zeros((3, 3)), np.zeros((3, 3)))
    tf = m.TFMessage((m.TransformStamped.planar(1_000_000, "odom", "base_link", 0.1, 0.0, 0.0),))
    processing.put("/odom", odom)
    processing.put("/tf", tf)
    assert not processing.wake.is_set() and len(processing.queue) == 2
    processing.put("/scan", m.LaserScan(2_000_000, "laser", -1.0, 1.0, 0.5, 0.0, 0.025, 0.1, 30.0,
                                        np.ones(5, np.float32)))
    assert processing.wake.is_set()
    processing.put("/odom", odom)
    processing.thread.start()
    processing.stop()
    assert slam.topics == ["/odom", "/tf", "/scan", "/odom"]
    assert processing.skipped_scans == 0 and processing.dropped == 0 and processing.errors == 0
