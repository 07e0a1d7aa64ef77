"""Where the logs are: paths (files, folders, globs) on a filesystem every node mounts, or
object-store URLs (``s3://``, ``gs://``, ``az://``, ``http(s)://``, ``file://`` ...) read through fsspec.

A folder stands for every ``*.mcap`` below it; a glob may use ``**``. A URL's object is copied to
the worker's local disk for the job and removed after it (the jobs read files). Each log gets an
output folder named for its file without ``.mcap``/``.mcap.active``; logs whose names collide
(``robot1/run.mcap``, ``robot2/run.mcap``) get their parent folders prefixed (``robot1__run``).
"""

from __future__ import annotations

import glob
import os
import re
import shutil
import tempfile
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path, PurePosixPath
from typing import Any

from trundle.logs.errors import UserError

URL = re.compile(r"^[a-zA-Z][a-zA-Z0-9+.-]*://")
LOG_SUFFIXES = (".mcap.active", ".mcap")
SEPARATOR = "__"


def is_url(source: str) -> bool:
    """Whether ``source`` is a URL (``scheme://...``) rather than a path."""
    return bool(URL.match(source))


def _filesystem(url: str) -> tuple[Any, str]:
    """The fsspec filesystem of ``url`` and the path in it; a missing package is a UserError."""
    try:
        from fsspec.core import url_to_fs
    except ImportError:
        raise UserError("log URLs need fsspec: pip install 'trundle[fleet]'") from None
    try:
        return url_to_fs(url)
    except (ImportError, ValueError) as error:
        raise UserError(f"cannot open {url}: {error}") from None


def _expand_url(url: str) -> list[str]:
    fs, path = _filesystem(url)
    if glob.has_magic(path):
        found = fs.glob(path)
    elif fs.isdir(path):
        found = fs.glob(path.rstrip("/") + "/**/*.mcap")
    else:
        found = [path] if fs.exists(path) else []
    return sorted(fs.unstrip_protocol(p) for p in found if not fs.isdir(p))


def _expand_path(text: str) -> list[str]:
    path = Path(text).expanduser()
    if glob.has_magic(text):
        found = [Path(p) for p in glob.glob(str(path), recursive=True)]
    elif path.is_dir():
        found = list(path.rglob("*.mcap"))
    else:
        found = [path] if path.exists() else []
    return sorted(str(p.resolve()) for p in found if p.is_file())


def expand(patterns: Sequence[str], exclude: Path | None = None) -> list[str]:
    """The logs that ``patterns`` name, each once, in the order given (sorted within a pattern);
    files under ``exclude`` (the output folder) are left out. A pattern that names nothing is a UserError."""
    logs: dict[str, None] = {}
    outside = exclude.resolve() if exclude is not None else None
    for pattern in patterns:
        found = _expand_url(pattern) if is_url(pattern) else _expand_path(pattern)
        if outside is not None:
            found = [f for f in found if is_url(f) or not Path(f).is_relative_to(outside)]
        if not found:
            raise UserError(f"no log matches {pattern}")
        logs.update(dict.fromkeys(found))
    return list(logs)


def _parts(source: str) -> list[str]:
    """The path components of ``source`` (a path or URL), the last without its log suffix."""
    parts = [p for p in PurePosixPath(URL.sub("", source) if is_url(source) else Path(source).as_posix()).parts
             if p not in ("/", "")]
    last = parts[-1]
    for suffix in LOG_SUFFIXES:
        if last.endswith(suffix) and len(last) > len(suffix):
            last = last[:-len(suffix)]
            break
    return parts[:-1] + [last]


def folder_names(sources: Sequence[str]) -> list[str]:
    """A distinct output folder name for each log: its file name without the log suffix, with
    as many parent folders prefixed (joined by ``__``) as it takes to tell colliding logs apart."""
    parts = [_parts(s) for s in sources]
    depth = [1] * len(parts)
    while True:
        names = [SEPARATOR.join(p[-d:]) for p, d in zip(parts, depth, strict=True)]
        groups: dict[str, list[int]] = {}
        for i, name in enumerate(names):
            groups.setdefault(name, []).append(i)
        grow = [i for members in groups.values() if len(members) > 1 for i in members if depth[i] < len(parts[i])]
        if not grow:
            break
        for i in grow:
            depth[i] += 1
    seen: dict[str, int] = {}
    unique = []
    for name in names:   # identical full paths cannot occur (expand dedups); this guards odd spellings
        seen[name] = seen.get(name, 0) + 1
        unique.append(name if seen[name] == 1 else f"{name}-{seen[name]}")
    return unique


def identity(source: str) -> str:
    """A cheap fingerprint of the input (size and modification time, or the object's ETag) that
    says whether a recorded content hash still holds, without reading the file."""
    if is_url(source):
        fs, path = _filesystem(source)
        info = fs.info(path)
        version = info.get("ETag") or info.get("etag") or info.get("mtime") or info.get("LastModified")
        return f"{info.get('size')}:{version}"
    if not Path(source).is_file():
        raise _missing(source)
    st = os.stat(source)
    return f"{st.st_size}:{st.st_mtime_ns}"


def _missing(source: str) -> UserError:
    return UserError(f"no such file on this node: {source} (logs must be on a filesystem every node mounts)")


@contextmanager
def local_copy(source: str) -> Iterator[Path]:
    """The log as a local file: the path itself, or a copy of the URL's object in a temporary
    folder of this node (removed afterwards). A missing file is a UserError naming this node."""
    if not is_url(source):
        if not Path(source).is_file():
            raise _missing(source)
        yield Path(source)
        return
    fs, path = _filesystem(source)
    folder = Path(tempfile.mkdtemp(prefix="trundle-fleet-"))
    try:
        local = folder / PurePosixPath(path).name
        try:
            fs.get_file(path, str(local))
        except FileNotFoundError:
            raise UserError(f"no such object: {source}") from None
        yield local
    finally:
        shutil.rmtree(folder, ignore_errors=True)
