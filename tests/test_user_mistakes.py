"""Every traceback, accepted number and misleading message the user's-journey review found
(issue 13), each as the command that showed it: now one line on stderr naming the problem and a
non-zero exit code."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from trundle.fusion.mapping.map_io import save_map
from trundle.logs import messages as m
from trundle.tools.cli.main import main

DEMO_LOG = Path(__file__).resolve().parent / "data" / "demo_short" / "demo.mcap"


@pytest.fixture()
def files(tmp_path: Path) -> Path:
    (tmp_path / "file.txt").write_text("a file where a folder belongs")
    (tmp_path / "binary.bin").write_bytes(bytes(range(256)) * 8)
    (tmp_path / "short.csv").write_text("t_ns,value\n1,2.0\n2\n")
    (tmp_path / "folder").mkdir()
    (tmp_path / "map").mkdir()
    save_map(m.OccupancyGrid(0, "map", 0.05, 0.0, 0.0, 0.0, np.zeros((10, 10), np.int8)), tmp_path / "map" / "map")
    zero = tmp_path / "zero"
    zero.mkdir()
    (zero / "map.yaml").write_text((tmp_path / "map" / "map.yaml").read_text().replace("resolution: 0.05",
                                                                                       "resolution: 0"))
    (zero / "map.pgm").write_bytes((tmp_path / "map" / "map.pgm").read_bytes())
    for name, text in (("res0", "[slam.submaps]\nresolution = 0\n"), ("resneg", "[slam.submaps]\nresolution = -0.05\n"),
                       ("resnan", "[slam.submaps]\nresolution = nan\n"),
                       ("resinf", "[slam.submaps]\nresolution = inf\n"),
                       ("resfine", "[slam.submaps]\nresolution = 0.0005\n"), ("url5", "[lrf]\nurl = 5\n")):
        (tmp_path / f"{name}.toml").write_text(text)
    return tmp_path


CASES = [
    # tracebacks
    (["slam", "{log}", "-o", "{d}/file.txt"], "is a file, not a folder"),
    (["characterize", "{log}", "--topic", "/scan", "-o", "{d}/file.txt"], "is a file, not a folder"),
    (["demo", "-o", "{d}/file.txt"], "is a file, not a folder"),
    (["slam", "{log}", "-o", "{d}/o", "--config", "{d}/res0.toml"],
     "slam.submaps.resolution = 0: expected a number >= 0.001"),
    (["slam", "{log}", "-o", "{d}/o", "--config", "{d}/resneg.toml"], "slam.submaps.resolution = -0.05"),
    (["slam", "{log}", "-o", "{d}/o", "--config", "{d}/resnan.toml"], "slam.submaps.resolution = nan"),
    (["slam", "{log}", "-o", "{d}/o", "--config", "{d}/resinf.toml"], "slam.submaps.resolution = inf"),
    (["slam", "{log}", "-o", "{d}/o", "--config", "{d}/resfine.toml"],
     "slam.submaps.resolution = 0.0005: expected a number >= 0.001"),
    (["localize", "{log}", "--map", "{d}/map/map.pgm"], "is a map image: give its YAML"),
    (["localize", "{log}", "--map", "{d}/binary.bin"], "is not a map YAML (binary data)"),
    (["localize", "{log}", "--map", "{d}/zero"], "resolution = 0 must be a number in"),
    (["replay", "{log}", "--rate", "-1"], "--rate: -1 must be at least 0"),
    (["match", "{d}/map/map.png", "{d}/map/map.png", "--draw", "{d}/folder"], "is a folder"),
    (["match", "{d}/map/map.png", "{d}/map/map.png", "--draw", "{d}/out.txt"], "OpenCV writes no picture"),
    (["emulate", "lrf", "--tcp", "-1"], "--tcp: -1 must be at least 0"),
    (["emulate", "lrf", "--tcp", "70000"], "--tcp: 70000 must be at most 65535"),
    (["emulate", "camera", "--port", "70000"], "--port: 70000 must be at most 65535"),
    (["record", "--config", "{d}/url5.toml", "-o", "{d}/r.mcap"], "lrf.url = 5"),
    (["characterize", "{log}", "--topic", "/scan", "--beam", "abc"], "--beam: 'abc' is not a whole number"),
    (["characterize", "{log}", "--topic", "/scan", "--reference", "{d}/binary.bin"], "not a reference CSV (binary"),
    (["characterize", "{log}", "--topic", "/scan", "--reference", "{d}/short.csv"], "(line 3 is short)"),
    (["demo", "--world", "{d}/binary.bin", "-o", "{d}/demo"], "not a floor-plan JSON file (binary data)"),
    (["import", "carmen", "/dev/zero", "-o", "{d}/c.mcap"], "/dev/zero is not a regular file"),
    (["import", "breezyslam", "/dev/zero", "-o", "{d}/b.mcap"], "/dev/zero is not a regular file"),
    # numbers once accepted without complaint
    (
        ["record", "--lrf", "scip2:///dev/null", "--duration", "-1", "-o", "{d}/r.mcap"],
        "--duration: -1 must be above 0",
    ),
    (["record", "--lrf", "scip2:///dev/null", "--duration", "0", "-o", "{d}/r.mcap"], "--duration: 0 must be above 0"),
    (["record", "--lrf", "scip2:///dev/null", "--duration", "nan", "-o", "{d}/r.mcap"], "'nan' is not a finite number"),
    (
        ["record", "--lrf", "scip2:///dev/null", "--split-size", "-1", "-o", "{d}/r.mcap"],
        "--split-size: -1 must be above 0",
    ),
    (["replay", "{log}", "--rate", "nan"], "'nan' is not a finite number"),
    (["replay", "{log}", "--rate", "inf"], "'inf' is not a finite number"),
    (["localize", "{log}", "--map", "{d}/map", "--max-range", "-1"], "--max-range: -1 must be above 0"),
    (["slam-eval", "{d}/t.csv", "{d}/t.csv", "--tolerance-ms", "-1"], "--tolerance-ms: -1 must be at least 0"),
    (["slam-eval", "{d}/t.csv", "{d}/t.csv", "--tolerance-ms", "1e308"], "--tolerance-ms: 1e308 must be at most"),
    (["slam-eval", "{d}/t.csv", "{d}/t.csv", "--landmarks", "{log}"], "is not a landmark file (id,x,y,sx,sy)"),
    (["match", "{d}/map/map.png", "{d}/map/map.png", "--threshold", "-1"], "--threshold: -1 must be above 0"),
    (["characterize", "{log}", "--topic", "/scan", "--bits", "-3"], "--bits: -3 must be at least 1"),
    (["import", "carmen", "x.log", "-o", "{d}/c.mcap", "--max-range", "-1"], "--max-range: -1 must be above 0"),
    (["import", "carmen", "x.log", "-o", "{d}/c.mcap", "--drift-scale", "nan"], "'nan' is not a finite number"),
    (["emulate", "camera", "--fps", "0"], "--fps: 0 must be above 0"),
    (["emulate", "camera", "--fps", "-5"], "--fps: -5 must be above 0"),
    (["emulate", "camera", "--width", "0"], "--width: 0 must be at least 16"),
    (["emulate", "camera", "--quality", "500"], "--quality: 500 must be at most 100"),
    # misleading messages
    (["info", "{d}/folder"], "is a folder, not an MCAP log"),
    (["info", "/dev/zero"], "/dev/zero is not a regular file"),
    (
        ["slam", "{d}/wrongtype.mcap", "-o", "{d}/o"],
        "/scan carries sensor_msgs/msg/JointState, not sensor_msgs/msg/LaserScan",
    ),
]


@pytest.mark.parametrize("argv, said", CASES, ids=[" ".join(a)[:70] for a, _ in CASES])
def test_one_line_and_a_non_zero_exit(argv, said, files, capfd):
    if "{d}/wrongtype.mcap" in argv:
        from trundle.logs.importers import write_log

        write_log([("/scan", m.JointState(1, "base_link", ("l",), [0.0]), 1)], files / "wrongtype.mcap", metadata={})
    if "{d}/t.csv" in argv:
        (files / "t.csv").write_text("t_ns,x,y,theta\n1,0,0,0\n2,1,0,0\n")
    code = main([a.format(d=files, log=DEMO_LOG) for a in argv])
    err = capfd.readouterr().err
    assert code == 2, err
    assert err.count("\n") == 1 and "Traceback" not in err and said in err, err


def test_characterize_against_a_known_constant_distance(tmp_path, capsys):
    """`--reference 2.0`: a target at a known distance, no CSV needed."""
    assert main(["characterize", str(DEMO_LOG), "--topic", "/scan", "--beam", "540", "--reference", "2.0",
                 "--json"]) == 0
    figures = json.loads(capsys.readouterr().out)
    assert figures["sensor"] == "laser" and "accuracy" in json.dumps(figures)


def test_info_names_each_channels_own_encoding(tmp_path, capsys):
    """`info` said "cdr" for every channel, a JSON one too."""
    from mcap.writer import Writer

    path = tmp_path / "mixed.mcap"
    with open(path, "wb") as f:
        writer = Writer(f)
        writer.start("", "test")
        schema = writer.register_schema("Note", "jsonschema", b'{"type": "object"}')
        channel = writer.register_channel("/notes", "json", schema)
        writer.add_message(channel, 1, b'{"text": "hello"}', 1)
        writer.finish()
    assert main(["info", str(path)]) == 0
    (line,) = [x for x in capsys.readouterr().out.splitlines() if "Topic: /notes" in x]
    assert line.endswith("Serialization Format: json")
    assert main(["info", str(path), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["topics"]["/notes"]["encoding"] == "json"


def test_status_without_a_daemon_names_every_place_it_looked(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    monkeypatch.delenv("RUNTIME_DIRECTORY", raising=False)
    assert main(["status"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(tmp_path / "trundle" / "status.sock") in err
    assert "/run/trundle/status.sock" in err and "--config" in err
