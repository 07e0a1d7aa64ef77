"""World simulator speed: camera frames and laser scans of the default office.

1. Camera render (640x480 and 1280x720) against encoding the same frame as JPEG (what the camera
   emulator does with every frame anyway) and against one bare ``cv2.remap`` of the frame (the
   floor of any remap-based renderer). Goal: 640x480 fast enough for 30 fps (< 33 ms).
2. A 1081-beam laser scan (all beams x all segments at once) against casting the same beams
   one at a time (the per-beam loop vectorisation replaces). Goal: 40 Hz in well under 10 % of a core.

Run: python tools/bench/bench_world.py
"""

from __future__ import annotations

from functools import partial

import cv2
import numpy as np

from trundle.tools.bench import report
from trundle.tools.sim.camera_render import CameraPose, CameraRenderer, PinholeCamera
from trundle.tools.sim.world import LaserModel, cast_rays, load_world, simulate_scan


def main() -> None:
    world = load_world()
    pose = CameraPose(10.0, 5.25, 0.45, 0.0)
    figures: dict[str, float] = {}
    for width, height in ((640, 480), (1280, 720)):
        renderer = CameraRenderer(world, PinholeCamera().scaled(width, height))
        rng = np.random.default_rng(0)
        frame = renderer.render(pose, rng)
        maps = np.random.default_rng(1).random((2, height, width), dtype=np.float32) * [[[width - 1]], [[height - 1]]]
        maps = maps.astype(np.float32)
        render = report.best_of(partial(renderer.render, pose, rng), repeat=5, number=10)
        encode = partial(cv2.imencode, ".jpg", frame, (cv2.IMWRITE_JPEG_QUALITY, 85))
        jpeg = report.best_of(encode, repeat=5, number=10)
        remap = report.best_of(partial(cv2.remap, frame, maps[0], maps[1], cv2.INTER_LINEAR), repeat=5, number=10)
        key = f"render_{width}x{height}"
        figures[f"{key}_ms"] = render * 1e3
        figures[f"{key}_fps"] = 1.0 / render
        figures[f"{key}_vs_jpeg_encode_ratio"] = render / jpeg
        figures[f"{key}_vs_one_remap_ratio"] = render / remap
    model = LaserModel()
    laser = (10.2, 5.25, 0.0)
    scan = report.best_of(lambda: simulate_scan(world, laser, model, np.random.default_rng(0)), repeat=5, number=20)
    angles = laser[2] + model.angles()
    per_beam = report.best_of(
        lambda: [cast_rays(world.segments, laser[:2], angles[i : i + 1]) for i in range(angles.size)],
        repeat=3,
        number=1,
    )
    figures["scan_1081_beams_ms"] = scan * 1e3
    figures["scan_cpu_percent_at_40hz"] = 100.0 * 40.0 * scan
    figures["scan_per_beam_loop_vs_vectorised_ratio"] = per_beam / scan
    figures["segments"] = int(world.segments.shape[0])
    report.write("world", figures)


if __name__ == "__main__":
    main()
