"""`trundle emulate lrf|can|camera`: run a device emulator (pty, TCP port, slcan pty or video)."""

from __future__ import annotations

import argparse
import importlib

# family -> module defining add_arguments(parser) and run(args) -> int
EMULATORS = {
    "lrf": ("trundle.tools.emulators.emulate_lrf", "laser range finder (SCIP 2.0 or RPLIDAR) on a pty or TCP port"),
    "can": ("trundle.tools.emulators.emulate_can", "SLCAN adapter on a pty with emulated wheel-encoder nodes"),
    "camera": ("trundle.tools.emulators.emulate_camera", "camera stream from a synthetic scene or a video file"),
}


def register(p: argparse.ArgumentParser) -> None:
    families = p.add_subparsers(dest="family", metavar="DEVICE")
    families.required = True
    for family, (module_name, help_text) in EMULATORS.items():
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError as error:
            if error.name != module_name:
                raise
            continue
        q = families.add_parser(family, help=help_text)
        module.add_arguments(q)
        q.set_defaults(func=module.run)
