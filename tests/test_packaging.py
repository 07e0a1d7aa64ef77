"""The distribution as a user gets it: a wheel holding only the `trundle` package (with its data
files), installed non-editable into a fresh virtual environment and run from an unrelated folder."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest

import trundle

REPO = Path(__file__).resolve().parents[1]
# what a source checkout holds that is not part of the distribution's sources
NOT_SOURCES = shutil.ignore_patterns(".git", ".venv", "build", "*.egg-info", "__pycache__", ".pytest_cache",
                                     ".hypothesis", "bench-results", "trundle-demo", "*.mcap.active")
DATA_FILES = ("trundle/drivers/data/vesc_status.dbc", "trundle/drivers/data/cia406_encoder.eds",
              "trundle/tools/sim/worlds/office.json", "trundle/tools/emulators/room.toml",
              "trundle/tools/config/example.toml")


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    """``pip wheel --no-deps`` of a clean copy of the sources (no stale build/ folder to leak in)."""
    source = tmp_path_factory.mktemp("source") / "trundle"
    shutil.copytree(REPO, source, ignore=NOT_SOURCES)
    out = tmp_path_factory.mktemp("wheel")
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--quiet", "-w", str(out), str(source)],
                   check=True, capture_output=True)
    (path,) = out.glob("trundle-*.whl")
    return path


def test_wheel_holds_only_the_trundle_package_and_its_data(wheel: Path) -> None:
    with zipfile.ZipFile(wheel) as archive:
        names = archive.namelist()
    assert {name.split("/")[0] for name in names} == {"trundle", f"trundle-{trundle.__version__}.dist-info"}
    for data in DATA_FILES:
        assert data in names
    packages = {str(p.parent.relative_to(REPO)).replace(os.sep, "/") for p in REPO.glob("*/**/__init__.py")
                if p.parts[len(REPO.parts)] not in ("tests", "build", ".venv")}
    for package in packages:  # every subpackage on disk is in the wheel, so none is left out of pyproject
        assert f"trundle/{package}/__init__.py" in names, package
    assert "trundle/__init__.py" in names and not any(name.startswith("trundle/tests/") for name in names)


def test_installed_wheel_runs_from_an_unrelated_folder(wheel: Path, tmp_path: Path) -> None:
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    bin_dir = venv / "bin"
    python = bin_dir / "python"
    site = subprocess.run([python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                          check=True, capture_output=True, text=True).stdout.strip()
    # the test run's dependencies (pip too) as a plain path: its .pth files (the editable install) are not read
    Path(site, "dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    subprocess.run([python, "-m", "pip", "install", "--no-deps", "--no-index", "--ignore-installed", "--quiet",
                    str(wheel)], check=True, capture_output=True)
    folder = tmp_path / "elsewhere"
    folder.mkdir()
    env = {key: value for key, value in os.environ.items() if key != "PYTHONPATH"}
    where = subprocess.run([python, "-c", "import trundle; print(trundle.__file__)"], cwd=folder, env=env,
                           check=True, capture_output=True, text=True).stdout.strip()
    assert Path(where).is_relative_to(venv)
    version = subprocess.run([bin_dir / "trundle", "--version"], cwd=folder, env=env, check=True,
                             capture_output=True, text=True)
    assert version.stdout.strip() == f"trundle {trundle.__version__}"
    demo = subprocess.run([bin_dir / "trundle", "demo", "--duration", "10", "-o", "out"], cwd=folder, env=env,
                          capture_output=True, text=True, timeout=600)
    assert "Traceback" not in demo.stderr + demo.stdout, demo.stderr
    report = json.loads((folder / "out" / "report.json").read_text())
    assert report["trajectory"]["scans"] > 100 and report["log"]["topics"]["/scan"] > 100
    assert (folder / "out" / "map.pgm").is_file() and (folder / "out" / "map.yaml").is_file()


def test_every_data_folder_is_a_listed_package_so_the_build_is_quiet() -> None:
    """setuptools prints a 40-line "Package would be ignored" box for each folder of package data that
    is not itself a listed package (``make demo`` printed two): every folder of a listed package that
    holds files is listed, and its package data is declared on it."""
    import tomllib

    config = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    packages, data = set(config["packages"]), config["package-data"]
    for package in sorted(packages - {"trundle"}):   # the root's other folders (tests, docs) are not shipped
        folder = REPO.joinpath(*package.split(".")[1:])
        for child in folder.iterdir():
            if child.is_dir() and child.name != "__pycache__" and any(child.iterdir()):
                assert f"{package}.{child.name}" in packages, f"{child.relative_to(REPO)} is not a listed package"
    assert all("/" not in pattern for patterns in data.values() for pattern in patterns), data
    assert data["trundle.drivers.data"] == ["*.dbc", "*.eds"] and data["trundle.tools.sim.worlds"] == ["*.json"]
