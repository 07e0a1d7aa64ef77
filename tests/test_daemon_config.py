"""The robot configuration: the example parses; every mistake is one line naming the key, and
`trundle daemon --check`, the daemon itself, `record --config` and `slam --config` refuse the same."""

from __future__ import annotations

import copy
import tomllib
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from trundle.logs.errors import UserError
from trundle.tools.cli.main import main
from trundle.tools.config.robot import check_daemon_config, default_socket_path, load_config, parse_config
from trundle.tools.config.toml_text import format_config

EXAMPLE = Path(__file__).resolve().parents[1] / "tools" / "config" / "example.toml"


def example() -> dict:
    with open(EXAMPLE, "rb") as f:
        return tomllib.load(f)


def daemon_check(data: dict) -> None:
    """What the daemon (and `trundle daemon --check`) runs on a config."""
    check_daemon_config(parse_config(data, "robot.toml"))


def test_example_config_parses_with_every_section():
    config = load_config(EXAMPLE)
    assert [(d.family, d.name) for d in config.devices] == [("lrf", "lrf"), ("can", "can"), ("camera", "camera")]
    can = config.devices[1]
    assert can.url == "slcan:///dev/trundle-can@1000000" and can.options["encoders"] == "odrive:0,1"
    assert "url" not in can.options and can.options["track_m"] == 0.5
    assert config.transforms[0].child == "laser" and config.transforms[0].xyz == (0.2, 0.0, 0.3)
    assert config.logger.folder == Path("/var/lib/trundle/logs") and config.logger.prefix == "trundle"
    assert config.logger.split_size_mb == 1024.0 and config.disk.action == "delete_oldest"
    assert config.status.socket == Path("/run/trundle/status.sock")
    assert config.slam == {"submaps": {"resolution": 0.05, "scans_per_submap": 25}, "loop_closure": {"enabled": True}}
    assert not config.live.enabled and config.live.host == "127.0.0.1" and config.live.port == 8765


@pytest.mark.parametrize("edit, message", [
    (lambda d: d["logger"].update(compresion="zstd"), "unknown key logger.compresion"),
    (lambda d: d.update(loger={}), "unknown key loger"),
    (lambda d: d["disk"].update(action="panic"), "disk.action = 'panic'"),
    (lambda d: d["disk"].update(min_free_mb="2 GB"), "disk.min_free_mb = '2 GB'"),
    (lambda d: d["disk"].update(min_free_mb=-1), "disk.min_free_mb = -1"),
    (lambda d: d["processing"].update(slam="yes"), "processing.slam = 'yes'"),
    (lambda d: d["logger"].pop("folder"), "logger.folder: missing"),
    (lambda d: d["logger"].update(compression="bz2"), "logger.compression = 'bz2'"),
    (lambda d: d["lrf"].pop("url"), "lrf.url: missing"),
    (lambda d: d["camera"].update(enabled="no"), "camera.enabled = 'no'"),
    (lambda d: d["transforms"][0].update(xyz=[1, 2]), "transforms[0].xyz"),
    (lambda d: d["transforms"][0].update(yaw=1.0), "unknown key transforms[0].yaw"),
    (lambda d: d["robot"].update(id=3), "unknown key robot.id"),
    (lambda d: d["live"].update(port=70000), "live.port = 70000"),
    (lambda d: d["slam"].update(resolutoin=0.1), "unknown key slam.resolutoin (known in [slam]: keyframes, "),
    (lambda d: d["slam"]["submaps"].update(scans_per_submap=25.7),
     "slam.submaps.scans_per_submap = 25.7: expected a whole"),
    (lambda d: d["slam"]["submaps"].update(resolution="0.05"), "slam.submaps.resolution = '0.05': expected a number"),
    (lambda d: d["slam"]["submaps"].update(resolution=1e300),
     "slam.submaps.resolution = 1e+300: expected a number <= 1"),
    (lambda d: d["live"].update(adress="0.0.0.0"), "unknown key live.adress"),
    (lambda d: d.update(camera=[{"url": "http://127.0.0.1:1/a", "name": "cam"},
                                {"url": "http://127.0.0.1:1/b", "name": "cam"}]), "two devices are named 'cam'"),
    (lambda d: [d.pop(k) for k in ("lrf", "can", "camera")], "no device"),
    # what --check once said "ok" to and the daemon then refused (or ran with, failing silently):
    (lambda d: d["can"].update(wheel_radius_m=0), "can.wheel_radius_m = 0: expected a number > 0"),
    (lambda d: d["can"].update(wheel_radius_m=-0.1), "can.wheel_radius_m = -0.1: expected a number > 0"),
    (lambda d: d["can"].update(track_m=0), "can.track_m = 0: expected a number > 0"),
    (lambda d: d["can"].update(wheel_radus_m=0.1), "unknown key can.wheel_radus_m (known in [can]: "),
    (lambda d: d["lrf"].update(baud=9600), "unknown key lrf.baud (known in [lrf]: "),
    (lambda d: d["lrf"].update(url="foo://x"), "unknown laser URL 'foo://x'"),
    (lambda d: d["lrf"].update(url=5), "lrf.url = 5"),
    (lambda d: d["camera"].update(url="v4l2:///dev/video0?width=abc&height=480"),
     "camera.width = 'abc': expected a whole number"),
    (lambda d: d["can"].update(encoders="odrive:0,99"), "node id 0..63"),
    (lambda d: d["processing"].update(aruco_dictionary="DICT_7X7_5"), "unknown ArUco dictionary 'DICT_7X7_5'"),
    (lambda d: d["slam"]["submaps"].update(resolution=0), "slam.submaps.resolution = 0"),
    (lambda d: d["slam"]["submaps"].update(resolution=-0.05), "slam.submaps.resolution = -0.05"),
    (lambda d: d["slam"]["submaps"].update(resolution=float("nan")), "slam.submaps.resolution = nan"),
    (lambda d: d["slam"]["submaps"].update(resolution=float("inf")), "slam.submaps.resolution = inf"),
    (lambda d: d["logger"].update(flush_period_s=0), "logger.flush_period_s = 0"),
    (lambda d: d["logger"].update(folder="/proc/trundle"), "/proc is on a virtual file system"),
    (lambda d: d["logger"].update(folder="/proc"), "/proc is on a virtual file system"),
    (lambda d: d.update(odometry={"wheel_radius_m": 0.1}), "odometry: odometry needs both wheel_radius_m and track_m"),
    (lambda d: d.update(laser={"x_m": "front"}), "laser.x_m = 'front'"),
])
def test_mistakes_name_the_key(edit, message, tmp_path):
    data = example()
    data["logger"]["folder"] = str(tmp_path / "logs")
    edit(data)
    with pytest.raises(UserError) as error:
        daemon_check(data)
    text = str(error.value)
    assert text.startswith("robot.toml: ") and message in text and "\n" not in text


def test_a_log_folder_that_is_a_file_is_refused(tmp_path):
    data = example()
    (tmp_path / "logs").write_text("not a folder")
    for folder, fragment in ((tmp_path / "logs", "is not a folder"), (tmp_path / "logs" / "sub", "cannot be made")):
        data["logger"]["folder"] = str(folder)
        with pytest.raises(UserError, match=fragment):
            daemon_check(data)


def test_live_view_without_the_extra_is_refused(tmp_path, monkeypatch):
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "foxglove" else real(name, *a))
    data = example()
    data["logger"]["folder"] = str(tmp_path)
    data["live"]["enabled"] = True
    with pytest.raises(UserError, match=r"pip install 'trundle\[live\]'"):
        daemon_check(data)


def test_daemon_check_runs_the_daemons_validation(tmp_path, capsys):
    """`--check` says ok only to what the daemon accepts; a mistake is one line and exit code 2."""
    data = example()
    data["logger"]["folder"] = str(tmp_path / "logs")
    good = tmp_path / "robot.toml"
    good.write_text(format_config(data))
    assert main(["daemon", "--config", str(good), "--check"]) == 0
    assert ": ok; devices: lrf" in capsys.readouterr().out
    data["can"]["wheel_radius_m"] = 0
    bad = tmp_path / "bad.toml"
    bad.write_text(format_config(data))
    assert main(["daemon", "--config", str(bad), "--check"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "bad.toml: can.wheel_radius_m = 0: expected a number > 0" in err
    assert main(["daemon", "--config", str(bad)]) == 2  # the daemon refuses the same, before it logs anything
    assert capsys.readouterr().err == err
    assert not (tmp_path / "logs").exists()


@pytest.mark.parametrize("command", [["record", "--lrf", "scip2:///dev/null", "--duration", "1", "-o", "{tmp}/r.mcap"],
                                     ["slam", "{log}", "-o", "{tmp}/out"],
                                     ["localize", "{log}", "--map", "{tmp}"]])
def test_record_and_slam_refuse_misspelt_tables_as_the_daemon_does(command, tmp_path, capsys):
    config = tmp_path / "robot.toml"
    config.write_text("[slma]\nresolution = 0.1\n")
    log = Path(__file__).resolve().parent / "data" / "demo_short" / "demo.mcap"
    argv = [a.format(tmp=tmp_path, log=log) for a in command] + ["--config", str(config)]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "unknown key slma" in err
    assert not (tmp_path / "r.mcap").exists() and not (tmp_path / "out").exists()


def test_print_example_config_is_the_shipped_example(capsys):
    assert main(["daemon", "--print-example-config"]) == 0
    assert capsys.readouterr().out == EXAMPLE.read_text()


def test_device_lists_and_disabled_devices():
    data = example()
    data["camera"] = [{"url": "http://127.0.0.1:1/front", "name": "front"},
                      {"url": "http://127.0.0.1:1/rear", "name": "rear", "enabled": False}]
    data["lrf"]["enabled"] = False
    config = parse_config(data)
    assert [d.name for d in config.devices] == ["can", "front"]
    assert config.devices[1].options == {"name": "front"}


def test_files_that_cannot_be_read(tmp_path):
    with pytest.raises(UserError, match="config file not found"):
        load_config(tmp_path / "none.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[logger\nfolder = 1")
    with pytest.raises(UserError, match="not valid TOML"):
        load_config(bad)


def test_default_socket_follows_systemd_then_xdg(monkeypatch):
    monkeypatch.setenv("RUNTIME_DIRECTORY", "/run/trundle")
    assert default_socket_path() == Path("/run/trundle/status.sock")
    monkeypatch.delenv("RUNTIME_DIRECTORY")
    monkeypatch.setenv("XDG_RUNTIME_DIR", "/run/user/1000")
    assert default_socket_path() == Path("/run/user/1000/trundle/status.sock")


values = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-10, 10**6),
    st.floats(allow_nan=True),
    st.text(max_size=4),
    st.lists(st.integers(-2, 2), max_size=4),
    st.dictionaries(st.text(max_size=3), st.integers(), max_size=2),
)


@settings(max_examples=200, deadline=None)
@given(st.data())
def test_any_mutation_gives_a_config_or_one_user_error_line(data):
    document = copy.deepcopy(example())
    section = data.draw(st.sampled_from(sorted(k for k in document if isinstance(document[k], dict))))
    key = data.draw(st.one_of(st.sampled_from(sorted(document[section]) or ["x"]), st.text(max_size=6)))
    document[section][key] = data.draw(values)
    if data.draw(st.booleans()):
        document[data.draw(st.text(max_size=5))] = data.draw(values)
    try:
        parse_config(document, "robot.toml")
    except UserError as error:
        assert "\n" not in str(error) and str(error).startswith("robot.toml: ")


toml_values = st.one_of(st.booleans(), st.integers(-2**63, 2**63 - 1), st.floats(allow_nan=False), st.text(),
                        st.lists(st.integers(-5, 5), max_size=4), st.lists(st.text(max_size=4), max_size=3))
bare_keys = st.text(alphabet="abcdefghijklmnopqrstuvwxyz_", min_size=1, max_size=8)


@settings(max_examples=100, deadline=None)
@given(st.dictionaries(bare_keys, st.dictionaries(bare_keys, toml_values, max_size=4), max_size=4))
def test_format_config_round_trips_through_tomllib(tables):
    assert tomllib.loads(format_config(tables)) == tables


def test_formatted_example_parses_to_the_same_config():
    assert parse_config(tomllib.loads(format_config(example()))) == parse_config(example())
