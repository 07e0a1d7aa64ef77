"""The demo's daemon as a child process that cannot outlive the demo.

``python -P -m trundle.tools.demo.daemon_process PARENT_PID ARGS...`` asks the kernel to send it
SIGTERM when its parent dies (``prctl(PR_SET_PDEATHSIG)``, which survives ``exec``), checks that
the parent is still the demo, then becomes ``python -P -m trundle.tools.cli ARGS...``: the real
``trundle daemon``. So even a demo killed by SIGKILL leaves no daemon running (SIGHUP and
SIGTERM the demo handles itself, stopping its daemon cleanly); the daemon runs in a session of
its own, so a closed terminal's SIGHUP (which means "split the log" to the daemon) never reaches it.
"""

from __future__ import annotations

import ctypes
import os
import signal
import sys

PR_SET_PDEATHSIG = 1  # <linux/prctl.h>


def command(args: list[str]) -> list[str]:
    """The command line that starts ``trundle ARGS`` as the current process's guarded child."""
    return [sys.executable, "-P", "-m", "trundle.tools.demo.daemon_process", str(os.getpid()), *args]


def main() -> None:
    parent, args = int(sys.argv[1]), sys.argv[2:]
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0) != 0:
        raise OSError(ctypes.get_errno(), "prctl(PR_SET_PDEATHSIG) failed")
    if os.getppid() != parent:  # the demo died before the guard was set
        sys.exit(1)
    os.execv(sys.executable, [sys.executable, "-P", "-m", "trundle.tools.cli", *args])


if __name__ == "__main__":
    main()
