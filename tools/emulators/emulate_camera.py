"""`trundle emulate camera`: an MJPEG-over-HTTP camera serving a synthetic scene or a video
file / image folder, for the demo and for trying `trundle record --camera http://...`."""

from __future__ import annotations

import argparse
import time

from trundle.logs.errors import UserError
from trundle.tools.config.arguments import non_negative_int, number_in, percent, positive, tcp_port
from trundle.tools.emulators.camera_emulator import CameraEmulator


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--source", metavar="PATH",
                        help="video file or image folder to serve (default: a synthetic moving scene)")
    parser.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    parser.add_argument("--port", type=tcp_port, default=8090, help="TCP port (default 8090; 0 picks a free one)")
    parser.add_argument(
        "--fps", type=number_in(0.0, 240.0, low_open=True), help="frame rate in Hz (default: the file's, or 30)"
    )
    parser.add_argument(
        "--width", type=number_in(16, 8192, whole=True), default=640, help="synthetic scene width in pixels"
    )
    parser.add_argument(
        "--height", type=number_in(16, 8192, whole=True), default=480, help="synthetic scene height in pixels"
    )
    parser.add_argument("--quality", type=percent, default=85, help="JPEG quality 1-100 for encoded frames")
    parser.add_argument("--corrupt-every", type=non_negative_int, default=0, metavar="N",
                        help="send every N-th frame truncated, as a flaky USB link does (0: never)")
    parser.add_argument("--duration", type=positive, help="stop after this many seconds (default: until Ctrl-C)")


def run(args: argparse.Namespace) -> int:
    emulator = CameraEmulator(source=args.source, fps=args.fps, width=args.width, height=args.height,
                              quality=args.quality, host=args.host, port=args.port, corrupt_every=args.corrupt_every)
    with emulator:
        print(f"camera emulator serving {emulator.url} at {emulator.fps:g} fps", flush=True)
        print(f"  record it with: trundle record --camera {emulator.url} -o run.mcap", flush=True)
        deadline = None if args.duration is None else time.monotonic() + args.duration
        try:
            while deadline is None or time.monotonic() < deadline:
                time.sleep(0.1 if deadline is None else max(0.0, min(0.1, deadline - time.monotonic())))
                if emulator.error is not None:
                    raise UserError(f"emulator stopped: {emulator.error}")
        except KeyboardInterrupt:
            pass
        print(f"served {emulator.frames_made} frames", flush=True)
    return 0
