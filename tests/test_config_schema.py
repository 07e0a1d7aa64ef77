"""The one config schema: each bad value of robot.toml is refused in one line naming the key, the
value and what was expected, with exit code 2, by every command that reads the file; random
tables never give a traceback nor a value other than the one given."""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from trundle.drivers.camera_config import CameraConfig, parse_camera_url
from trundle.drivers.lrf import driver_from_url as laser_from_url
from trundle.drivers.rplidar_driver import RplidarConfig
from trundle.drivers.scip2_driver import ScipConfig
from trundle.drivers.wheels import CanOptions
from trundle.fusion.odometry.diff_drive import WheelModel
from trundle.fusion.slam.landmark_slam import LandmarkOptions
from trundle.logs.errors import ConfigError, UserError
from trundle.logs.schema import Schema, parse
from trundle.tools.config.robot import LoggerConfig, ProcessingConfig, parse_config
from trundle.tools.config.toml_text import format_config

TESTS = Path(__file__).resolve().parent
LOG = TESTS / "data" / "demo_short" / "demo.mcap"
LASER = {"url": "scip2:///dev/null"}

# (tables of robot.toml, the line every command says after "<file>: ")
BAD = {
    "integer refuses 25.7": ({"logger": {"chunk_size_kb": 25.7}},
                             "logger.chunk_size_kb = 25.7: expected a whole number"),
    "number refuses a string": ({"odometry": {"wheel_radius_m": "0.1", "track_m": 0.5}},
                                "odometry.wheel_radius_m = '0.1': expected a number"),
    "timeout below its range": ({"lrf": {**LASER, "timeout_s": -1}}, "lrf.timeout_s = -1: expected a number > 0"),
    "nan": ({"lrf": {**LASER, "x": math.nan}}, "lrf.x = nan: expected a finite number"),
    "frame id is a string": ({"lrf": {**LASER, "frame_id": 5}}, "lrf.frame_id = 5: expected a string"),
    "slam integer refuses 25.7": ({"slam": {"submaps": {"scans_per_submap": 25.7}}},
                                  "slam.submaps.scans_per_submap = 25.7: expected a whole number"),
    "slam number refuses a string": ({"slam": {"submaps": {"resolution": "0.05"}}},
                                     "slam.submaps.resolution = '0.05': expected a number"),
    "slam float inside its range": ({"slam": {"submaps": {"resolution": 1e300}}},
                                    "slam.submaps.resolution = 1e+300: expected a number <= 1"),
    "unknown key named with the known": ({"live": {"adress": "0.0.0.0"}},
                                         "unknown key live.adress (known in [live]: enabled, host, port)"),
}


def commands(config: Path, tmp: Path) -> dict[str, list[str]]:
    """Every command that reads a robot config, given ``config``."""
    return {
        "daemon --check": ["daemon", "--config", str(config), "--check"],
        "daemon": ["daemon", "--config", str(config)],
        "record": ["record", "--config", str(config), "--duration", "1", "-o", str(tmp / "r.mcap")],
        "slam": ["slam", str(LOG), "-o", str(tmp / "slam"), "--config", str(config)],
        "localize": ["localize", str(LOG), "--map", str(tmp), "--config", str(config)],
        "fleet": ["fleet", "slam", str(LOG), "-o", str(tmp / "fleet"), "--job-options", f"config={config}"],
    }


CASES = [(bad, command) for bad in BAD for command in commands(Path("x"), Path("y"))]


@pytest.mark.parametrize("bad, command", CASES, ids=[f"{b}-{c}" for b, c in CASES])
def test_each_bad_value_is_one_line_and_exit_2_in_each_command(bad: str, command: str, tmp_path: Path) -> None:
    tables, line = BAD[bad]
    document: dict[str, Any] = {"logger": {"folder": str(tmp_path / "logs")}, "lrf": dict(LASER)}
    for name, table in tables.items():
        document[name] = {**document.get(name, {}), **table}
    config = tmp_path / "robot.toml"
    config.write_text(format_config(document))
    argv = commands(config, tmp_path)[command]
    done = subprocess.run([sys.executable, "-m", "trundle.tools.cli", *argv], capture_output=True, text=True,
                          timeout=120, env={**os.environ, "RAY_ADDRESS": ""})
    where = "slam option config" if command == "fleet" else str(config)
    assert done.returncode == 2, done.stderr
    assert done.stderr.count("\n") == 1 and done.stderr.endswith(f"{where}: {line}\n"), done.stderr
    assert not (tmp_path / "logs").exists() and not (tmp_path / "slam").exists()


# ------------------------------------------------------------------------- random tables

keys = st.text(alphabet="abcdefghijklmnopqrstuvwxyz_", min_size=1, max_size=12)
scalars = st.one_of(st.booleans(), st.integers(-2**63, 2**63 - 1), st.floats(allow_nan=False), st.text(max_size=6),
                    st.floats(-100, 100), st.integers(-5, 100))
toml_values = st.recursive(scalars, lambda inner: st.one_of(st.lists(inner, max_size=4),
                                                           st.dictionaries(keys, inner, max_size=3)), max_leaves=8)


def tables_for(model: type[Schema]) -> st.SearchStrategy[dict[str, Any]]:
    """Tables mixing the model's own keys with random ones, every value of any TOML type."""
    return st.dictionaries(st.one_of(st.sampled_from(sorted(model.model_fields)), keys), toml_values, max_size=5)


def same(given_value: Any, kept: Any) -> bool:
    """Whether ``kept`` is ``given_value`` unchanged: the same number (an int the same int), the
    same text, the same items (a TOML array may become a tuple, a path a Path)."""
    if isinstance(kept, Schema):
        return isinstance(given_value, dict) and all(same(v, getattr(kept, k)) for k, v in given_value.items())
    if isinstance(kept, (list, tuple)):
        return isinstance(given_value, (list, tuple)) and len(given_value) == len(kept) and all(
            same(a, b) for a, b in zip(given_value, kept, strict=True))
    if isinstance(kept, dict):
        return isinstance(given_value, dict) and given_value.keys() == kept.keys() and all(
            same(given_value[k], kept[k]) for k in kept)
    if isinstance(kept, Path):
        return isinstance(given_value, str) and kept == Path(given_value).expanduser()
    if isinstance(kept, bool) or isinstance(given_value, bool):
        return type(kept) is type(given_value) and kept == given_value
    if isinstance(kept, int):
        return type(given_value) is int and kept == given_value
    if isinstance(kept, float):
        return isinstance(given_value, (int, float)) and kept == given_value
    return kept == given_value


MODELS = [WheelModel, LandmarkOptions, CanOptions, LoggerConfig, ProcessingConfig]


@settings(max_examples=300, deadline=None)
@given(st.sampled_from(MODELS), st.data())
def test_random_tables_give_the_values_given_or_one_config_error(model: type[Schema], data: st.DataObject) -> None:
    table = data.draw(tables_for(model))
    try:
        checked = parse(model, table, "robot.toml: t")
    except ConfigError as error:
        assert "\n" not in str(error) and str(error).startswith("robot.toml: ")
        return
    for key, value in table.items():
        assert same(value, getattr(checked, key)), (key, value, getattr(checked, key))


@settings(max_examples=200, deadline=None)
@given(st.sampled_from(["scip2:///dev/ttyACM0", "rplidar:///dev/ttyUSB0"]),
       st.one_of(tables_for(ScipConfig), tables_for(RplidarConfig)))
def test_random_laser_tables_give_the_values_given_or_one_config_error(url: str, table: dict[str, Any]) -> None:
    table.pop("name", None)
    try:
        driver = laser_from_url(url, lambda *a: None, table)
    except ConfigError as error:
        assert "\n" not in str(error) and ("lrf." in str(error) or str(error).startswith("lrf"))
        return
    for key, value in table.items():
        if key != "url":
            assert same(value, getattr(driver.config, key)), (key, value)


@settings(max_examples=200, deadline=None)
@given(tables_for(CameraConfig))
def test_random_camera_tables_give_the_values_given_or_one_config_error(table: dict[str, Any]) -> None:
    try:
        config = parse_camera_url("v4l2:///dev/video0", table)
    except UserError as error:
        assert "\n" not in str(error)
        return
    for key, value in table.items():
        if key not in ("url", "enabled"):
            assert same(value, getattr(config, key)), (key, value)


documents = st.dictionaries(st.one_of(st.sampled_from(["robot", "frames", "logger", "disk", "processing", "status",
                                                       "supervision", "live", "slam", "landmarks", "odometry",
                                                       "laser", "transforms", "can", "camera"]), keys),
                            st.one_of(st.dictionaries(keys, toml_values, max_size=4), toml_values), max_size=4)


@settings(max_examples=200, deadline=None)
@given(documents)
def test_random_documents_give_a_config_or_one_config_error(document: dict[str, Any]) -> None:
    try:
        config = parse_config(document, "robot.toml")
    except UserError as error:
        assert "\n" not in str(error) and str(error).startswith("robot.toml: ")
        return
    for name in ("logger", "disk", "processing", "supervision", "live", "frames"):
        for key, value in document.get(name, {}).items():
            if not (name == "logger" and key == "prefix"):
                assert same(value, getattr(getattr(config, name), key)), (name, key, value)


def test_a_value_is_never_truncated() -> None:
    for table in ({"chunk_size_kb": 25.7}, {"chunk_size_kb": 25.0}, {"queue_size": True}):
        with pytest.raises(ConfigError, match="expected a whole number"):
            parse(LoggerConfig, table, "robot.toml: logger")
    assert parse(LoggerConfig, {"chunk_size_kb": 2**53}).chunk_size_kb == 2**53
    with pytest.raises(ConfigError, match=r"^robot.toml: logger.chunk_size_kb = 9007199254740993: expected a number "
                                          r"of at most 2\*\*53"):
        parse(LoggerConfig, {"chunk_size_kb": 2**53 + 1}, "robot.toml: logger")
    assert parse_config({"processing": {"markers_hz": 3}}).processing.markers_hz == 3.0
