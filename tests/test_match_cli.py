"""`trundle match`: JSON fields, homography against a known warp, picture, user errors."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from feature_scenes import scene

from trundle.perception.feature_eval import corner_error
from trundle.tools.cli.main import main

WARP = np.array([[0.95, 0.08, 12.0], [-0.06, 0.97, 8.0], [1e-5, -2e-5, 1.0]])


@pytest.fixture(scope="module")
def pair(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    folder = tmp_path_factory.mktemp("match")
    image = scene(noise=2.0)
    warped = cv2.warpPerspective(image, WARP, (image.shape[1], image.shape[0]), flags=cv2.INTER_LINEAR,
                                 borderMode=cv2.BORDER_REFLECT)
    first, second = folder / "a.png", folder / "b.png"
    cv2.imwrite(str(first), cv2.cvtColor(image, cv2.COLOR_GRAY2BGR))
    cv2.imwrite(str(second), cv2.cvtColor(warped, cv2.COLOR_GRAY2BGR))
    return first, second


def _json(capsys: pytest.CaptureFixture, *argv: str) -> dict:
    assert main(["match", *argv, "--json"]) == 0
    return json.loads(capsys.readouterr().out)


@pytest.mark.parametrize("features", ["orb", "sift", "surf", "akaze"])
def test_json_reports_every_stage_and_the_homography(pair: tuple[Path, Path], features: str,
                                                     capsys: pytest.CaptureFixture) -> None:
    out = _json(capsys, str(pair[0]), str(pair[1]), "--features", features)
    assert out["features"] == features and out["model"] == "homography"
    assert len(out["keypoints"]) == 2 and min(out["keypoints"]) > 50
    counts = list(out["matches"].values())
    assert list(out["matches"]) == ["nearest", "max_distance", "ratio", "difference", "cross_check"]
    assert counts == sorted(counts, reverse=True) and counts[0] == out["keypoints"][0]
    assert 20 <= out["inliers"] <= counts[-1]
    mean, worst = corner_error(np.array(out["homography"]), WARP, (240, 320))
    assert worst < 1.5, (mean, worst)


def test_text_output_draw_and_fundamental(pair: tuple[Path, Path], tmp_path: Path,
                                          capsys: pytest.CaptureFixture) -> None:
    picture = tmp_path / "matches.png"
    assert main(["match", str(pair[0]), str(pair[1]), "--draw", str(picture)]) == 0
    text = capsys.readouterr().out
    assert "inliers:" in text and "homography (image 1 -> image 2):" in text and str(picture) in text
    drawn = cv2.imread(str(picture))
    assert drawn.shape == (240, 640, 3)
    out = _json(capsys, str(pair[0]), str(pair[1]), "--model", "fundamental", "--threshold", "1")
    f = np.array(out["fundamental"])
    assert f.shape == (3, 3) and np.linalg.matrix_rank(f, tol=1e-9 * np.abs(f).max()) == 2
    assert out["inliers"] > 20 and "homography" not in out


def test_filters_change_the_counts(pair: tuple[Path, Path], capsys: pytest.CaptureFixture) -> None:
    loose = _json(capsys, str(pair[0]), str(pair[1]), "--features", "orb", "--ratio", "1", "--no-cross-check")
    assert set(loose["matches"].values()) == {loose["keypoints"][0]}
    strict = _json(capsys, str(pair[0]), str(pair[1]), "--features", "orb", "--ratio", "0.7",
                   "--min-difference", "5", "--max-distance", "40")
    m = strict["matches"]
    assert m["max_distance"] < m["nearest"] and m["difference"] <= m["ratio"] < m["max_distance"]


@pytest.mark.parametrize("argv", [
    ["missing.png", "{b}"],
    ["{text}", "{b}"],
    ["{a}", "{b}", "--draw", "{dir}/no/such/dir/out.png"],
    ["{a}", "{b}", "--ratio", "0"],
])
def test_user_errors_are_one_line(pair: tuple[Path, Path], tmp_path: Path, argv: list[str],
                                  capsys: pytest.CaptureFixture) -> None:
    text = tmp_path / "not_an_image.png"
    text.write_text("hello")
    names = {"a": pair[0], "b": pair[1], "text": text, "dir": tmp_path}
    assert main(["match", *(a.format(**names) for a in argv)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("trundle match: ") and err.count("\n") == 1 and "Traceback" not in err
