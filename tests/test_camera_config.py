"""Camera URLs and options: what they mean, and that anything else is one clear UserError."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from trundle.drivers.camera_config import parse_camera_url
from trundle.logs.errors import UserError


def test_v4l2_url_with_table_options() -> None:
    config = parse_camera_url("v4l2:///dev/video0?width=1280&height=720&fps=30&fourcc=MJPG",
                              {"url": "ignored", "controls": {"exposure": 120, "auto_exposure": 1}, "buffers": 1})
    assert (config.scheme, config.target, config.width, config.height, config.fps, config.fourcc, config.buffers) == (
        "v4l2", "/dev/video0", 1280, 720, 30.0, "MJPG", 1)
    assert config.controls == {"exposure": 120.0, "auto_exposure": 1.0}
    assert config.topic_prefix == "/camera"


def test_url_parameters_override_the_table() -> None:
    config = parse_camera_url("file:///data/clip.avi?pace=0&fps=12.5&name=front", {"pace": True, "fps": 30})
    assert (config.target, config.pace, config.fps, config.topic_prefix) == ("/data/clip.avi", False, 12.5, "/front")


def test_http_url_keeps_the_servers_own_parameters() -> None:
    config = parse_camera_url("http://cam.local:8080/?action=stream&stall_timeout_s=1")
    assert config.target == "http://cam.local:8080/?action=stream" and config.stall_timeout_s == 1.0


def test_transform_from_text_or_list() -> None:
    text = parse_camera_url("v4l2:///dev/video0?transform=0.1,0,0.3,0,0,1.5708")
    table = parse_camera_url("v4l2:///dev/video0", {"transform": [0.1, 0, 0.3, 0, 0, 1.5708]})
    assert text.transform == table.transform == (0.1, 0.0, 0.3, 0.0, 0.0, 1.5708)


@pytest.mark.parametrize("url", ["v4l2://", "file://", "gopher://x", "/dev/video0", "v4l2:///dev/video0?fps=-1",
                                 "v4l2:///dev/video0?buffers=0", "v4l2:///dev/video0?decode_check_every=-2",
                                 "v4l2:///dev/video0?stall_timeout_s=0", "v4l2:///dev/video0?name=/",
                                 "v4l2:///dev/video0?fps=nan", "v4l2:///dev/video0?width=1.5&height=2"])
def test_bad_urls_are_user_errors(url: str) -> None:
    with pytest.raises(UserError):
        parse_camera_url(url)


option_values = st.one_of(
    st.text(max_size=8),
    st.integers(-5, 5000),
    st.floats(),
    st.booleans(),
    st.lists(st.floats(-10, 10), max_size=7),
    st.dictionaries(st.text(max_size=8), st.floats(), max_size=2),
)
option_names = st.sampled_from(["width", "height", "fps", "fourcc", "buffers", "controls", "transform", "pace", "loop",
                                "raw_output", "jpeg_quality", "decode_check_every", "stall_timeout_s", "name", "bogus"])


@settings(max_examples=200, deadline=None)
@given(st.sampled_from(["v4l2:///dev/video0", "file:///clip.avi", "http://h:1/s", "v4l2://"]),
       st.text(st.characters(codec="ascii"), max_size=40), st.dictionaries(option_names, option_values, max_size=4))
def test_any_url_and_table_give_a_config_or_user_error(base: str, query: str, table: dict) -> None:
    try:
        config = parse_camera_url(f"{base}?{query}", table)
    except UserError as error:
        assert "\n" not in str(error)
    else:
        assert config.buffers >= 1 and 1 <= config.jpeg_quality <= 100 and config.stall_timeout_s > 0
        assert math.isfinite(config.fps) and config.fps >= 0
