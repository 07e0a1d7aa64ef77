"""Every command's numeric and path options fed bad values: each ends with one line on stderr and a
non-zero exit code, never a traceback, a hang or a silently accepted value.

The options are read from the parsers themselves, so a new numeric option without a checked
type, or a new path option missing from ``PATH_OPTIONS``, fails here.
"""

from __future__ import annotations

import argparse
import signal
from pathlib import Path

import cv2
import numpy as np
import pytest

from trundle.fusion.mapping.map_io import save_map
from trundle.logs import messages as m
from trundle.tools.cli.main import COMMANDS, build_parser, main

DEMO_LOG = Path(__file__).resolve().parent / "data" / "demo_short" / "demo.mcap"
SKIP = (argparse._HelpAction, argparse._VersionAction)


def actions() -> list[tuple[tuple[str, ...], argparse.Action]]:
    """(command path, action) for every argument of every command, sub-commands included."""
    found = []

    def walk(parser: argparse.ArgumentParser, path: tuple[str, ...]) -> None:
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, sub in action.choices.items():
                    walk(sub, path + (name,))
            elif not isinstance(action, SKIP):
                found.append((path, action))

    for command in COMMANDS:
        parser = build_parser([command])
        sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices[command]
        walk(sub, (command,))
    return found


def name(action: argparse.Action) -> str:
    return action.option_strings[-1] if action.option_strings else action.dest


# ---------------------------------------------------------------------------------------- numbers

NUMERIC = [(path, a) for path, a in actions() if a.type in (int, float) or hasattr(a.type, "bounds")]


def test_every_numeric_option_has_a_checked_type():
    plain = [f"{' '.join(path)} {name(a)}" for path, a in NUMERIC if a.type in (int, float)]
    assert not plain, f"numeric options that accept nan, inf or any sign: {plain}"


def bad_numbers(action: argparse.Action) -> list[str]:
    low, high, low_open, whole = action.type.bounds
    values = ["nan", "inf", "-inf", "abc", "1e999", ""]
    if whole:
        values.append("1.5")
    if low is not None:
        values.append(repr(low) if low_open else repr(low - 1 if whole else low - 0.001))
    if high is not None:
        values.append(repr(high + 1 if whole else high + 0.001))
    return values


@pytest.mark.parametrize("path, action", NUMERIC, ids=[f"{' '.join(p)} {name(a)}" for p, a in NUMERIC])
def test_bad_numbers_are_one_line_errors(path, action, capfd):
    for value in bad_numbers(action):
        argv = [*path, f"{action.option_strings[0]}={value}"]
        assert main(argv) == 2, (argv, capfd.readouterr())
        err = capfd.readouterr().err
        assert err.count("\n") == 1 and "Traceback" not in err and name(action) in err, (argv, err)


# ------------------------------------------------------------------------------------------ paths

@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """Good inputs for every command, so each run fails only on the one bad path it is given."""
    root = tmp_path_factory.mktemp("fuzz")
    image = root / "image.png"
    cv2.imwrite(str(image), np.random.default_rng(0).integers(0, 255, (64, 64, 3), np.uint8))
    grid = m.OccupancyGrid(0, "map", 0.05, 0.0, 0.0, 0.0, np.zeros((20, 20), np.int8))
    (root / "map").mkdir()
    save_map(grid, root / "map" / "map")
    (root / "trajectory.csv").write_text("t_ns,x,y,theta\n1,0,0,0\n2,1,0,0\n3,2,0,0\n")
    (root / "carmen.log").write_text("ODOM 0 0 0 0 0 0 1.0 host 1.0\nODOM 1 0 0 0 0 0 2.0 host 2.0\n")
    (root / "exp.dat").write_text(" ".join(["1000", "0", "0", "0"] + ["0"] * 20 + ["100"] * 683) + "\n")
    (root / "robot.toml").write_text("")
    mrclam = root / "mrclam"  # one robot of a UTIAS MRCLAM folder: a metre straight ahead, one landmark seen
    mrclam.mkdir()
    (mrclam / "Barcodes.dat").write_text("# Subject # Barcode #\n1 5\n6 18\n")
    (mrclam / "Landmark_Groundtruth.dat").write_text("# Subject # x y sx sy\n6 2.0 0.0 0.001 0.001\n")
    (mrclam / "Robot1_Odometry.dat").write_text("# Time [s] v w\n100.0 1.0 0.0\n101.0 0.0 0.0\n")
    (mrclam / "Robot1_Measurement.dat").write_text("# Time [s] Subject # range bearing\n100.5 18 1.5 0.0\n")
    (mrclam / "Robot1_Groundtruth.dat").write_text("# Time x y theta\n100.0 0 0 0\n101.0 1 0 0\n")
    (root / "binary.bin").write_bytes(bytes(range(256)) * 16)
    (root / "empty.txt").write_text("")
    (root / "full").mkdir()
    (root / "dir").mkdir()
    (root / "full" / "result.txt").write_text("an earlier result")
    (root / "existing.mcap").write_text("an earlier result")
    return root


# command -> (its good arguments: positional dest or option string -> value, {name} filled from
# ``files``, None for a flag; the path options with the kind of path each wants: "in" (a file to
# read), "config" (a TOML file, empty is fine), "map" (a map folder or YAML), "out" (a file to
# create), "out or folder" (a file to create, or a folder to put it in), "folder" (a folder to
# create or reuse), "new folder" (a folder to create, or an empty one), "link" (a path to create),
# "socket" (a daemon's status socket), "mapdir" (a trundle slam output folder to continue)).
PATH_OPTIONS: dict[tuple[str, ...], tuple[dict[str, str | None], dict[str, str]]] = {
    ("demo",): ({"-o": "{out}", "--world": "{binary}"}, {"-o": "folder", "--world": "in"}),
    ("record",): ({"--lrf": "scip2:///dev/null", "--duration": "1", "-o": "{out}.mcap"},
                  {"--config": "config", "-o": "out"}),
    ("daemon",): ({"--check": None, "--config": "{robot}"}, {"--config": "config"}),
    ("status",): ({}, {"--socket": "socket", "--config": "config"}),
    ("info",): ({"file": "{log}"}, {"file": "in"}),
    ("recover",): ({"input": "{log}", "output": "{out}.mcap"}, {"input": "in", "output": "out or folder"}),
    ("replay",): ({"file": "{log}", "--rate": "0", "-o": "{out}.mcap"},
                  {"file": "in", "--config": "config", "-o": "out"}),
    ("export",): ({"file": "{log}", "--topic": "/odom", "-o": "{out}.csv"}, {"file": "in", "-o": "out"}),
    ("slam",): ({"log": "{log}", "-o": "{out}"},
               {"log": "in", "-o": "new folder", "--config": "config", "--continue": "mapdir"}),
    ("inject-faults",): ({"log": "{log}", "-o": "{out}.mcap", "--glitches": "1"},
                         {"log": "in", "-o": "out", "--config": "config"}),
    ("slam-eval",): ({"result": "{trajectory}", "reference": "{trajectory}"}, {"result": "in", "reference": "in"}),
    ("localize",): ({"log": "{log}", "--map": "{map}", "-o": "{out}.csv"},
                    {"log": "in", "--map": "map", "--config": "config", "-o": "out"}),
    ("perceive",): ({"file": "{log}", "--pipeline": "color", "--template": "{image}", "-o": "{out}.mcap"},
                    {"file": "in", "-o": "out", "--template": "in", "--template-mask": "in"}),
    ("match",): ({"image1": "{image}", "image2": "{image}", "--draw": "{out}.png"},
                 {"image1": "in", "image2": "in", "--draw": "out"}),
    ("import", "carmen"): ({"input": "{carmen}", "-o": "{out}.mcap"},
                           {"input": "in", "-o": "out", "--reference": "out"}),
    ("import", "breezyslam"): ({"input": "{dat}", "-o": "{out}.mcap"}, {"input": "in", "-o": "out"}),
    ("import", "mrclam"): ({"input": "{mrclam}", "--robot": "1", "-o": "{out}.mcap"},
                           {"input": "dataset", "-o": "out", "--reference": "out", "--landmarks-reference": "out"}),
    ("emulate", "lrf"): ({"--tcp": "0", "--duration": "0.1"}, {"--link": "link", "--scene": "in"}),
    ("emulate", "can"): ({"--protocol": "odrive", "--link": "{out}", "--duration": "0.1"}, {"--link": "link"}),
    ("emulate", "camera"): ({"--port": "0", "--duration": "0.1"}, {"--source": "in"}),
    ("fleet",): ({"job": "info", "logs": "{log}", "-o": "{out}"}, {"-o": "folder", "--continue": "mapdir"}),
    ("characterize",): ({"log": "{log}", "--topic": "/scan", "-o": "{out}"},
                        {"log": "in", "--reference": "in", "-o": "folder"}),
}

BAD = {  # kind of path -> the wrong things to give it
    "in": ["{missing}", "{folder}", "/dev/zero", "{binary}", "{empty}"],
    "config": ["{missing}", "{folder}", "/dev/zero", "{binary}"],
    "dataset": ["{missing}", "{folder}", "/dev/zero", "{binary}"],
    "map": ["{missing}", "{folder}", "/dev/zero", "{binary}", "{map}/map.pgm"],
    "mapdir": ["{missing}", "{folder}", "/dev/zero", "{binary}", "{map}"],
    "out": ["{folder}", "{existing}"],
    "out or folder": ["{existing}"],
    "folder": ["{existing}"],
    "new folder": ["{existing}", "{full}"],
    "link": ["{existing}", "{folder}", "/dev/zero"],
    "socket": ["{missing}", "{folder}", "/dev/zero", "{existing}"],
}
PATHLIKE = {"file", "input", "output", "log", "result", "reference", "image1", "image2"}
SHARED = ["binary.bin", "carmen.log", "dir", "empty.txt", "existing.mcap", "exp.dat", "full", "image.png", "map",
          "mrclam", "robot.toml", "trajectory.csv"]


def test_every_path_option_is_fuzzed():
    covered = {(path, option) for path, (_, options) in PATH_OPTIONS.items() for option in options}
    wanted = {(path, a.option_strings[0] if a.option_strings else a.dest) for path, a in actions()
              if a.type is Path or (not a.option_strings and a.dest in PATHLIKE)
              or a.dest in ("template", "template_mask", "draw", "source", "output")}
    assert wanted <= covered, sorted(wanted - covered)


CASES = [(path, option, bad) for path, (_, options) in PATH_OPTIONS.items() for option, kind in options.items()
         for bad in BAD[kind]]


def command_line(path: tuple[str, ...], good: dict[str, str | None], option: str, value: str) -> list[str]:
    """The command with its good arguments and ``option`` (a positional's dest, or an option) set to ``value``."""
    args = {**good, option: value}
    if option == "--link":
        args.pop("--tcp", None)  # one or the other
    positional = [a.dest for p, a in actions() if p == path and not a.option_strings and a.dest in args]
    argv = [*path, *(args.pop(dest) for dest in positional)]
    for key, val in args.items():
        argv += [key] if val is None else [key, val]
    return argv  # type: ignore[return-value]


@pytest.mark.parametrize("path, option, bad", CASES, ids=[f"{' '.join(p)} {o}={b}" for p, o, b in CASES])
def test_bad_paths_are_one_line_errors(path, option, bad, files, tmp_path, capfd):
    fill = {"log": DEMO_LOG, "image": files / "image.png", "map": files / "map", "trajectory": files / "trajectory.csv",
            "carmen": files / "carmen.log", "dat": files / "exp.dat", "robot": files / "robot.toml",
            "binary": files / "binary.bin", "empty": files / "empty.txt", "full": files / "full",
            "existing": files / "existing.mcap", "folder": files / "dir", "missing": tmp_path / "missing.file",
            "out": tmp_path / "out", "mrclam": files / "mrclam"}
    good, _ = PATH_OPTIONS[path]
    argv = [a.format(**fill) for a in command_line(path, good, option, bad)]
    handlers = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    signal.signal(signal.SIGALRM, lambda *_: pytest.fail(f"{argv} did not finish in 60 s"))
    signal.alarm(60)
    try:
        code = main(argv)
    finally:
        signal.alarm(0)
        for sig, handler in handlers.items():
            signal.signal(sig, handler)
    out, err = capfd.readouterr()  # the file descriptors: OpenCV's and FFmpeg's own messages count too
    lines = [line for line in err.splitlines() if line.startswith("trundle")]
    assert code != 0, (argv, out, err)
    assert len(lines) == 1 and "Traceback" not in err and not err.replace(lines[0], "").strip(), (argv, err)
    assert (files / "existing.mcap").read_text() == "an earlier result"
    assert (files / "full" / "result.txt").read_text() == "an earlier result"
    assert sorted(p.name for p in files.iterdir()) == SHARED and not list((files / "dir").iterdir())
