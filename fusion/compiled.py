"""How trundle compiles its kernels: numba, no Python objects, the GIL released, cached on disk in a folder
named for every source file of ``trundle.fusion`` together.

numba keys a cached kernel by its own file's time stamp alone. A kernel that calls a kernel of another file
compiles that one into itself, so when only the other file changes (a ``git pull`` that changes
``field_residuals.py`` and not ``pose_solver.py``), the cache goes on returning the old code (numba issue
1833, open since 2016). Naming the cache's folder for the sources makes any change to them a new, empty
cache. The folder is in ``NUMBA_CACHE_DIR`` when that is set, else in the user's cache
(``$XDG_CACHE_HOME`` or ``~/.cache``) under ``trundle/numba``; a folder of other sources that no process
has used for a week is removed there, as the caches of a developer's earlier edits would pile up.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, TypeVar, overload

import numba

if TYPE_CHECKING:
    from numba.core.dispatcher import Dispatcher

F = TypeVar("F", bound=Callable[..., object])
STALE_S = 7 * 24 * 3600.0   # a cache folder of other sources unused this long is removed (user cache only)


def sources_digest(root: Path) -> str:
    """A digest of every ``.py`` file under ``root``: its path and its bytes, in path order."""
    digest = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        digest.update(path.relative_to(root).as_posix().encode() + b"\0")
        digest.update(path.read_bytes() + b"\0")
    return digest.hexdigest()[:16]


def cache_folder(digest: str) -> Path | None:
    """Where kernels compiled from sources of ``digest`` are kept (see the module's docstring); None when
    there is no user cache to name (no home folder)."""
    given = os.environ.get("NUMBA_CACHE_DIR")
    if given:
        return Path(given) / f"trundle-{digest}"
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path("~/.cache").expanduser())
    return base / "trundle" / "numba" / digest if base.is_absolute() else None


def _remove_stale(folder: Path) -> None:
    """Remove the sibling cache folders of ``folder`` (the user cache's) not used for :data:`STALE_S`."""
    try:
        siblings = [path for path in folder.parent.iterdir() if path.is_dir() and path != folder]
    except OSError:
        return
    for path in siblings:
        try:
            if time.time() - path.stat().st_mtime > STALE_S:
                shutil.rmtree(path)
        except OSError:
            continue


def _use_cache_folder() -> None:
    folder = cache_folder(sources_digest(Path(__file__).parent))
    if folder is None:
        return   # numba then caches beside the sources, as it does without a folder
    try:
        folder.mkdir(parents=True, exist_ok=True)
        os.utime(folder)   # in use: not stale
    except OSError:
        return   # numba then caches beside the sources, or not at all, as it does without a folder
    numba.config.CACHE_DIR = str(folder)   # type: ignore[attr-defined]  # numba's stub leaves its settings out
    if not os.environ.get("NUMBA_CACHE_DIR"):
        _remove_stale(folder)


_use_cache_folder()


@overload
def kernel(function: F) -> Dispatcher[F]: ...


@overload
def kernel(*, inline: bool = False) -> Callable[[F], Dispatcher[F]]: ...


def kernel(function: F | None = None, *, inline: bool = False) -> Dispatcher[F] | Callable[[F], Dispatcher[F]]:
    """``function`` compiled as every trundle kernel is (``@kernel``; ``@kernel(inline=True)`` for a small
    helper compiled into its callers)."""
    def compile_(python: F) -> Dispatcher[F]:
        return numba.njit(cache=True, nogil=True, inline="always" if inline else "never")(python)

    return compile_ if function is None else compile_(function)
