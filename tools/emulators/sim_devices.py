"""The world simulator driving the real device emulators: the whole robot's hardware, emulated.

``SimDevices(robot_sim, folder)`` starts, on one shared clock:

- a Hokuyo SCIP 2.0 laser (``trundle.tools.emulators.scip2_emulator``) on a pty at ``folder/lrf``, its
  ranges cast in the world from the robot's laser pose when each scan passes the rear;
- an SLCAN adapter (``trundle.tools.emulators.slcan_emulator``) on a pty at ``folder/can`` with ODrive
  CAN Simple axes turning as the robot's wheels do (motor = wheel, one axis per wheel; four
  wheels = a skid-steer with front and rear axes on each side);
- an MJPEG-over-HTTP camera (``trundle.tools.emulators.camera_emulator``) serving rendered frames.

Simulation time is ``(host wall-clock ns - t0_ns) / 1e9`` with ``t0_ns`` taken at ``start()``,
so a message stamped ``stamp_ns`` is compared with ``sim.pose_at(sim_time(stamp_ns))``.
``daemon_config`` writes the matching ``[lrf]``, ``[can]`` and ``[camera]`` tables.
"""

from __future__ import annotations

import collections
import math
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from trundle.tools.emulators import scip2_emulator
from trundle.tools.emulators.camera_emulator import CameraEmulator
from trundle.tools.emulators.can_nodes import CanNodeRunner, WheelMotion, odrive_nodes
from trundle.tools.emulators.device_server import DeviceServer
from trundle.tools.emulators.faults import FaultPlan
from trundle.tools.emulators.slcan_emulator import SlcanEmulator
from trundle.tools.sim.camera_render import CameraRenderer
from trundle.tools.sim.robot import RobotSim
from trundle.tools.sim.world import LaserModel


def laser_model_for(model: scip2_emulator.ScipModel, base: LaserModel) -> LaserModel:
    """``base``'s error model with the beam layout, range limits and sweep of an emulated SCIP model
    (one step of ``ARES`` per ``60 / SCAN`` seconds: the head turns at its rpm)."""
    angles = model.angles
    p = model.params
    period = 60.0 / p.rpm
    return LaserModel(beams=angles.size, angle_min=float(angles[0]), angle_max=float(angles[-1]),
                      range_min=p.dmin / 1000.0, range_max=p.dmax / 1000.0, noise_sigma_m=base.noise_sigma_m,
                      dropout=base.dropout, max_incidence_rad=base.max_incidence_rad,
                      scan_time=period, time_increment=period / p.ares)


def first_beam_delay_s(model: scip2_emulator.ScipModel) -> float:
    """Time (s) from a SCIP scan's start (the head pointing backwards, step ``AFRT - ARES / 2``)
    to its first step ``AMIN``, as the protocol times it and the driver stamps it."""
    p = model.params
    return (p.amin - (p.afrt - p.ares / 2.0)) / p.ares * 60.0 / p.rpm


class SimDevices:
    """Emulated laser, wheel encoders and camera fed by one ``RobotSim`` (see the module doc).

    Parameters
    ----------
    sim : the simulated run (world, robot, ground truth).
    folder : where the pty links go (``lrf``, ``can``).
    lrf_model : SCIP model name (``utm-30lx``: 40 Hz, 1081 beams; ``urg-04lx``: 10 Hz, 682 beams).
    wheels : 2 (left, right) or 4 (left front, right front, left rear, right rear) encoder axes.
    camera_fps, camera_size : the camera stream; intrinsics are ``sim.camera`` scaled to the size.
    lrf_faults : a fault plan for the laser (checksum errors, stalls, unplugs, ...).
    camera_clip : serve this MJPEG clip (packets byte for byte, looped) instead of rendering live;
        for benchmarks, where the emulator's own rendering would compete with the daemon.
    """

    def __init__(self, sim: RobotSim, folder: str | Path, *, lrf_model: str = "utm-30lx", wheels: int = 2,
                 camera_fps: float = 30.0, camera_size: tuple[int, int] = (640, 480), camera_quality: int = 85,
                 lrf_faults: FaultPlan | None = None, odrive_ids: tuple[int, ...] | None = None,
                 camera_clip: str | Path | None = None) -> None:
        if wheels not in (2, 4):
            raise ValueError("wheels must be 2 or 4")
        self.sim = sim
        self.folder = Path(folder)
        self.t0_ns = time.time_ns()
        self.wheels = wheels
        self.odrive_ids = odrive_ids or tuple(range(wheels))
        self.scip_model = scip2_emulator.MODELS[lrf_model]
        self.laser_model = laser_model_for(self.scip_model, sim.model.laser_model)
        self.camera = sim.camera.scaled(*camera_size)
        self.renderer = sim.renderer if self.camera == sim.camera else CameraRenderer(sim.world, self.camera)
        self._lrf_faults = lrf_faults
        self._camera_fps, self._camera_quality, self._camera_clip = camera_fps, camera_quality, camera_clip
        self.lrf: DeviceServer | None = None
        self.lrf_device: scip2_emulator.ScipDevice | None = None
        self.can_adapter: SlcanEmulator | None = None
        self.can_nodes: CanNodeRunner | None = None
        self.camera_emulator: CameraEmulator | None = None
        self.activity: dict[str, collections.deque[int]] = {
            k: collections.deque(maxlen=1 << 20) for k in ("lrf", "can", "camera")
        }

    # ------------------------------------------------------------------ clock
    def sim_time(self, wall_ns: int) -> float:
        """Simulation time (s) of a host wall-clock time (ns)."""
        return (wall_ns - self.t0_ns) / 1e9

    def now(self) -> float:
        return self.sim_time(time.time_ns())

    # ------------------------------------------------------------------ sensors on the shared clock
    def _ranges_at(self, rear_s: float) -> np.ndarray:
        self.activity["lrf"].append(time.time_ns())  # when the emulator emits the scan (its thread ran)
        return self.sim.ranges_at(rear_s - self.t0_ns / 1e9 + first_beam_delay_s(self.scip_model), self.laser_model)

    def first_beam_ns(self, rear_ns: int) -> int:
        """Host time (ns) of the first beam of the scan the laser emulator began at ``rear_ns``."""
        return rear_ns + int(round(first_beam_delay_s(self.scip_model) * 1e9))

    def _motor_turns_per_s(self, _runner_t: float) -> np.ndarray:
        now = time.time_ns()
        self.activity["can"].append(now)
        left, right = self.sim.wheel_speeds_at(self.sim_time(now)) / (2.0 * math.pi)
        return np.array([left, right] * (self.wheels // 2))

    def _frame_at(self, _emulator_t: float) -> np.ndarray:
        now = time.time_ns()
        self.activity["camera"].append(now)
        return self.sim.frame_at(self.sim_time(now), self.renderer)

    def produced(self, name: str) -> np.ndarray:
        """Wall-clock times (ns) at which emulator ``name`` (lrf, can, camera) produced data: scans
        emitted, encoder ticks, rendered frames; to tell a daemon's gap from a starved emulator."""
        return np.array(self.activity[name], np.int64)

    # ------------------------------------------------------------------ life cycle
    def start(self) -> SimDevices:
        """Start every emulator; simulation time 0 is now."""
        self.folder.mkdir(parents=True, exist_ok=True)
        (self.folder / "camera.yaml").write_text(self.camera.calibration_yaml())
        self.t0_ns = time.time_ns()
        self.lrf_device = scip2_emulator.ScipDevice(self.scip_model, self._ranges_at, self._lrf_faults or FaultPlan(),
                                                    time.time_ns())
        self.lrf = DeviceServer(self.lrf_device, link_path=self.folder / "lrf").start()
        self.can_adapter = SlcanEmulator(str(self.folder / "can")).start()
        self.can_nodes = CanNodeRunner(self.can_adapter.bus, odrive_nodes(self.odrive_ids),
                                       WheelMotion(self._motor_turns_per_s, self.wheels), tick_s=0.002,
                                       adapter=self.can_adapter).start()
        self.camera_emulator = CameraEmulator(self._frame_at, source=self._camera_clip, fps=self._camera_fps,
                                              width=self.camera.width, height=self.camera.height,
                                              quality=self._camera_quality).start()
        return self

    def stop(self) -> None:
        if self.camera_emulator is not None:
            self.camera_emulator.close()
        if self.can_nodes is not None:
            self.can_nodes.stop()
        if self.can_adapter is not None:
            self.can_adapter.close()
        if self.lrf is not None:
            self.lrf.stop()

    # ------------------------------------------------------------------ faults (for soak tests)
    def unplug_lrf(self, away_s: float) -> None:
        """Pull the laser's cable for ``away_s`` seconds; it comes back rebooted (clock reset)."""
        assert self.lrf is not None and self.lrf_device is not None
        with self.lrf.lock:
            self.lrf_device.link_request = ("unplug", away_s)

    def unplug_can(self, away_s: float) -> None:
        """Pull the SLCAN adapter for ``away_s`` seconds (a fresh, closed adapter comes back)."""
        assert self.can_adapter is not None
        self.can_adapter.unplug()
        timer = threading.Timer(away_s, self.can_adapter.replug)
        timer.daemon = True
        timer.start()

    def stall_camera(self, seconds: float) -> None:
        """The camera sends nothing for ``seconds`` while its connection stays open."""
        assert self.camera_emulator is not None
        self.camera_emulator.stall(seconds)

    def __enter__(self) -> SimDevices:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ------------------------------------------------------------------ configuration
    @property
    def urls(self) -> dict[str, str]:
        assert self.camera_emulator is not None, "start() first"
        return {"lrf": f"scip2://{self.folder / 'lrf'}", "can": f"slcan://{self.folder / 'can'}@1000000",
                "camera": self.camera_emulator.url}

    def device_tables(self) -> dict[str, dict[str, Any]]:
        """``[lrf]``, ``[can]`` and ``[camera]`` tables for a daemon (or record) config."""
        model = self.sim.model
        laser, camera = model.laser, model.camera
        names = ["left", "right"] if self.wheels == 2 else ["left_front", "right_front", "left_rear", "right_rear"]
        return {
            "lrf": {"url": self.urls["lrf"], "frame_id": "laser", "parent_frame": "base_link",
                    "x": laser.x, "y": laser.y, "z": laser.z, "yaw": laser.yaw},
            "can": {"url": self.urls["can"], "encoders": "odrive:" + ",".join(map(str, self.odrive_ids)),
                    "wheels": names, "wheel_radius_m": model.wheel_radius_m, "track_m": model.track_m,
                    "odometry_wheels": names[:2]},
            "camera": {"url": self.urls["camera"], "transform": [camera.x, camera.y, camera.z, 0.0, 0.0, camera.yaw],
                       "calibration": str(self.folder / "camera.yaml")},
        }
