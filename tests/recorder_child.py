"""A recorder process for crash tests: 40 Hz laser scans + 100 Hz joint states into a Logger.

Usage: python recorder_child.py OUT.mcap [--fsize-limit BYTES]
Prints "ready" once logging has started; runs until killed (or until the logger fails); SIGTERM
closes the log normally (renamed to OUT.mcap).
"""

from __future__ import annotations

import resource
import signal
import sys
import time

import numpy as np

from trundle.logs import messages as m
from trundle.logs.writer import Logger


def main() -> int:
    out = sys.argv[1]
    if "--fsize-limit" in sys.argv:
        limit = int(sys.argv[sys.argv.index("--fsize-limit") + 1])
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    rng = np.random.default_rng(0)
    logger = Logger(out, compression="zstd", flush_period_s=0.5)
    stop: list[int] = []
    signal.signal(signal.SIGTERM, lambda signum, frame: stop.append(signum))
    print("ready", flush=True)
    start = time.monotonic()
    tick = 0
    deadline = time.monotonic() + 120  # never outlive a crashed test run
    while logger.error is None and not stop and time.monotonic() < deadline:
        now = time.time_ns()
        if tick % 5 == 0:  # 40 Hz of the 200 Hz loop
            logger.write("/scan", m.LaserScan(now, "laser", -2.35, 2.35, 0.00436, 2.5e-5, 0.025, 0.02, 30.0,
                                              rng.uniform(0.1, 30, 1081), rng.uniform(0, 5000, 1081)), now)
        if tick % 2 == 0:
            logger.write("/wheels", m.JointState(now, "base_link", ("left", "right"), [tick * 0.01, tick * 0.011],
                                                 [1.0, 1.1]), now)
        tick += 1
        time.sleep(max(0.0, start + tick * 0.005 - time.monotonic()))
    try:
        logger.close()
    except Exception as error:  # the test reads this line
        print(f"logger stopped: {error}", file=sys.stderr, flush=True)
        return 3
    return 0


if __name__ == "__main__":
    sys.exit(main())
