"""The kernels' on-disk cache: keyed by every source of trundle.fusion, so a change to a kernel that another
kernel compiles into itself cannot leave the old code running (numba keys a kernel by its own file alone)."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from trundle.fusion import compiled
from trundle.fusion.matching import pose_solver


def write_tree(root: Path, files: dict[str, str]) -> Path:
    for name, text in files.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_text(text)
    return root


def test_the_digest_changes_with_any_source_and_only_then(tmp_path: Path) -> None:
    """pose_solver compiles field_residuals into itself: a change to field_residuals alone (or a new file)
    must name a new cache; the same sources, copied elsewhere or read again, the same one."""
    files = {"matching/pose_solver.py": "from .field_residuals import f\n", "matching/field_residuals.py": "X = 1\n",
             "notes.txt": "not a source\n"}
    first = compiled.sources_digest(write_tree(tmp_path / "a", files))
    assert compiled.sources_digest(write_tree(tmp_path / "b", files)) == first
    assert compiled.sources_digest(write_tree(tmp_path / "c", {**files, "notes.txt": "changed\n"})) == first
    changed = compiled.sources_digest(write_tree(tmp_path / "d", {**files, "matching/field_residuals.py": "X = 2\n"}))
    added = compiled.sources_digest(write_tree(tmp_path / "e", {**files, "mapping/new.py": ""}))
    moved = {"matching/pose_solver.py": files["matching/pose_solver.py"], "mapping/field_residuals.py": "X = 1\n"}
    moved_digest = compiled.sources_digest(write_tree(tmp_path / "f", moved))
    assert len({first, changed, added, moved_digest}) == 4


def test_kernels_are_cached_in_the_folder_of_these_sources() -> None:
    """Every kernel module's cache lives in the folder named for the digest of trundle.fusion as it is now."""
    folder = compiled.cache_folder(compiled.sources_digest(Path(compiled.__file__).parent))
    cache_path = Path(pose_solver.solve_pose_in_window._cache.cache_path)   # numba's FunctionCache
    assert folder is not None and folder in cache_path.parents


def test_the_cache_folder_is_numba_cache_dir_or_the_users_cache(monkeypatch: pytest.MonkeyPatch,
                                                              tmp_path: Path) -> None:
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "given"))
    assert compiled.cache_folder("0123") == tmp_path / "given" / "trundle-0123"
    monkeypatch.delenv("NUMBA_CACHE_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert compiled.cache_folder("0123") == tmp_path / "xdg" / "trundle" / "numba" / "0123"
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert compiled.cache_folder("0123") == tmp_path / "home" / ".cache" / "trundle" / "numba" / "0123"


def test_only_cache_folders_unused_for_a_week_are_removed(tmp_path: Path) -> None:
    """Earlier sources' folders pile up as a developer edits; a week unused, they go. The folder in use and
    anything recently used stay, and so does every file that is not a folder of ours."""
    base = tmp_path / "trundle" / "numba"
    current, recent, old = base / "current", base / "recent", base / "old"
    for folder in (current, recent, old):
        folder.mkdir(parents=True)
        (folder / "kernel.nbi").write_bytes(b"index")
    stray = base / "README"
    stray.write_text("somebody's file\n")
    week_ago = time.time() - compiled.STALE_S - 60.0
    os.utime(old, (week_ago, week_ago))
    os.utime(stray, (week_ago, week_ago))
    compiled._remove_stale(current)
    assert current.exists() and recent.exists() and stray.exists()
    assert not old.exists()


def test_a_cache_that_cannot_be_made_leaves_numba_its_own(tmp_path: Path) -> None:
    """Where the user's cache cannot be written (here a file stands where the folder would go), kernels still
    compile and run: numba keeps its own choice of cache."""
    blocked = tmp_path / "not-a-folder"
    blocked.write_text("a file the user put here\n")
    environment = {key: value for key, value in os.environ.items() if key != "NUMBA_CACHE_DIR"}
    environment["XDG_CACHE_HOME"] = str(blocked)
    program = ("import numpy as np, numba\n"
               "from trundle.fusion.mapping.nearest_cells import squared_nearest\n"
               "print(squared_nearest(np.array([0, 1, 1]), np.array([0]), 1, 1, 3), repr(numba.config.CACHE_DIR))")
    done = subprocess.run([sys.executable, "-c", program], capture_output=True, text=True, env=environment,
                          check=True, timeout=300)
    assert done.stdout.split() == ["2", "''"]
    assert blocked.read_text() == "a file the user put here\n"
