"""`trundle demo [-o DIR]`: the whole robot on emulated hardware in a simulated world -> log, map, report.

No hardware and no arguments needed: the world simulator drives the laser, wheel-encoder and
camera emulators, the real onboard daemon records them for about a minute of robot time, and
the log is replayed through SLAM and marker detection, scored against the simulator's ground
truth. See ``tools/demo/``.
"""

from __future__ import annotations

import argparse
import signal
from pathlib import Path

from trundle.logs.errors import UserError
from trundle.tools.cli.damage import say_damage
from trundle.tools.cli.progress import Progress
from trundle.tools.config.arguments import non_negative_int, number_in, percent, positive
from trundle.tools.demo.report import ATE_LIMIT_M, markers_seen, partial_run, verdict
from trundle.tools.demo.run import LOG_NAME, DemoSettings, run_demo
from trundle.tools.sim.world import DEFAULT_WORLD


def register(p: argparse.ArgumentParser) -> None:
    """The command's options on its subparser ``p``."""
    p.description = __doc__
    p.add_argument("-o", "--output", type=Path, default=Path("trundle-demo"),
                   help="output folder (default ./trundle-demo)")
    p.add_argument(
        "--duration", type=positive, help="robot time to record, s (default: the whole route, about a minute)"
    )
    p.add_argument("--camera-fps", type=number_in(0.0, 60.0, low_open=True), default=DemoSettings.camera_fps,
                   help="camera frame rate, above 0 and at most 60 (default %(default)s)")
    p.add_argument("--camera-size", default="x".join(map(str, DemoSettings.camera_size)),
                   help="camera frame size WIDTHxHEIGHT (default %(default)s)")
    p.add_argument("--camera-quality", type=percent, default=DemoSettings.camera_quality,
                   help="JPEG quality 1-100 (default %(default)s)")
    p.add_argument("--seed", type=non_negative_int, default=0, help="seed of wheel slip and sensor noise (default 0)")
    p.add_argument("--world", type=Path, default=DEFAULT_WORLD, help="floor-plan JSON (default: the office)")
    p.set_defaults(func=run)


def camera_size(text: str) -> tuple[int, int]:
    """``WIDTHxHEIGHT`` as two positive integers."""
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise UserError(f"--camera-size must be WIDTHxHEIGHT, e.g. 640x480, not {text!r}") from None
    if not (16 <= width <= 4096 and 16 <= height <= 4096):
        raise UserError(f"--camera-size {text}: width and height must be 16-4096 pixels")
    return width, height


def _interrupted(signum: int, frame: object) -> None:
    """SIGTERM, SIGHUP (the terminal closed): end as Ctrl-C does, so the daemon is stopped and the
    partial log kept (``trundle.tools.demo.run.record``) instead of both being left behind."""
    raise KeyboardInterrupt(signal.Signals(signum).name)


def run(args: argparse.Namespace) -> int:
    """Run the demo with the options in ``args``, print its figures and checks; 0 unless a check failed
    (one not checked, with nothing to check it on, is said but does not fail)."""
    for sig in (signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, _interrupted)
    settings = DemoSettings(world=args.world, duration_s=args.duration, camera_fps=args.camera_fps,
                            camera_size=camera_size(args.camera_size), camera_quality=args.camera_quality,
                            seed=args.seed)
    out = args.output
    report = run_demo(out, settings, say=lambda text: print(text, flush=True), progress=Progress)
    say_damage(args, report["log_damage"])
    checks = report["checks"]
    print(f"\nSLAM trajectory error {report['ate_rmse_m'] * 100:.1f} cm RMSE over {report['path_length_m']:.1f} m "
          f"(limit {ATE_LIMIT_M * 100:.0f} cm; wheel odometry alone "
          f"{report['trajectory']['odometry_ate']['rmse_m'] * 100:.1f} cm), "
          f"{report['trajectory']['loop_closures']} loop closures")
    print(f"markers: {markers_seen(report)}")
    for name, ok in checks.items():
        print(f"  {verdict(ok)}  {name}")
    if partial_run(report):
        print(partial_run(report))
    if report["starved"]:
        late = report["emulator_late_ms"]
        print(f"warning: the machine was too busy for real time (load average {report['load_average'][1]:.1f}): "
              + ", ".join(f"{name} emulator up to {late[name]:.0f} ms late" for name in report["starved"])
              + "; late or bunched stamps degrade odometry and SLAM")
    print(f"\nresults in {out}/: report.md, report.json, map.png (+ map.pgm, map.yaml), trajectory.png, "
          f"camera_detections.png, {LOG_NAME}")
    print(f"open the log in Foxglove (https://app.foxglove.dev or the desktop app): Open local file -> "
          f"{(out / LOG_NAME).resolve()}")
    print(f"took {report['seconds']['total']:.0f} s")
    return 0 if all(ok is not False for ok in checks.values()) else 1
