"""Output files and folders, the one way trundle writes a result.

A file is written under a temporary name beside its target (``.NAME.<pid>.partial``, same folder
so the last step is a rename on one filesystem) and takes its final name only when it is
complete, without ever replacing a file that appeared meanwhile. On any failure, Ctrl-C
included, the temporary file goes: nothing half-written stays under a name the user gave. A
folder of results remembers what it held before the run and, on failure, removes only what this
run added (and itself, if it made it and it is left empty).

A write that fails for the disk's sake (read-only, no permission, no space, over quota) is an
:class:`~trundle.logs.errors.OutputError`, one line naming the path and the cause, exit code 1.
JSON goes through :func:`json_text`: strict JSON, a non-finite number written as null.
"""

from __future__ import annotations

import contextlib
import errno
import fnmatch
import glob
import json
import math
import os
import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from trundle.logs.errors import OutputError, UserError
from trundle.logs.paths import new_file, output_folder

PARTIAL_SUFFIX = ".partial"
# the causes that are the disk's, not the user's mistake nor a bug: said as an OutputError
OUTPUT_ERRNOS = frozenset({errno.EROFS, errno.EACCES, errno.EPERM, errno.ENOSPC, errno.EDQUOT, errno.EFBIG})
_NO_HARD_LINKS = frozenset({errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EXDEV, errno.EMLINK})


def temporary_path(path: str | os.PathLike[str]) -> Path:
    """The name ``path`` is written under until it is complete: ``.NAME.<pid>.partial`` beside it."""
    path = Path(path)
    return path.with_name(f".{path.name}.{os.getpid()}{PARTIAL_SUFFIX}")


def output_error(error: OSError, path: str | os.PathLike[str]) -> OutputError:
    """``error`` while writing ``path`` as the one line the user reads."""
    return OutputError(f"cannot write {path}: {error.strerror or error} (nothing was written)", str(path), error)


def is_output_failure(error: BaseException) -> bool:
    """True for an OSError that is the disk's: read-only, no permission, no space, over quota."""
    return isinstance(error, OSError) and error.errno in OUTPUT_ERRNOS


def _said_for(error: BaseException, temps: list[Path], finals: list[Path]) -> OutputError | None:
    """``error`` said for the final name of the file it concerns, if it is a failure to write one of
    ``temps`` (an OSError naming it or naming no file, or an OutputError about it); else None."""
    if isinstance(error, OutputError):
        cause, where = error.cause, error.path
        if cause is None or where is None:
            return None
    elif is_output_failure(error):
        assert isinstance(error, OSError)
        cause, where = error, error.filename
    else:
        return None
    if where is None:
        return output_error(cause, finals[0])
    name = os.path.basename(os.fsdecode(where))
    for tmp, final in zip(temps, finals, strict=True):
        if name.startswith(tmp.name):
            return output_error(cause, final)
    return None


def _remove(tmp: Path) -> None:
    """``tmp`` and whatever was written under its name (a logger's ``.active``): the run's own files."""
    with contextlib.suppress(OSError):
        for path in tmp.parent.glob(glob.escape(tmp.name) + "*"):
            if path.is_dir() and not path.is_symlink():
                shutil.rmtree(path, ignore_errors=True)
            else:
                path.unlink(missing_ok=True)


def _install(tmp: Path, final: Path, replace: bool) -> None:
    """Give the complete ``tmp`` its name ``final``; never over a file that appeared meanwhile (unless
    ``replace``: a folder the command owns, whose old result this one replaces)."""
    if replace:
        os.replace(tmp, final)
        return
    try:
        os.link(tmp, final)  # atomic, and refused if ``final`` exists
    except FileExistsError:
        raise UserError(f"{final} appeared while it was being written: it is kept, and this result was not "
                        "written (run again with another name)") from None
    except OSError as error:
        if error.errno not in _NO_HARD_LINKS:
            raise
        if final.exists() or final.is_symlink():  # a filesystem without hard links: check, then rename
            raise UserError(f"{final} appeared while it was being written: it is kept, and this result was "
                            "not written (run again with another name)") from None
        os.rename(tmp, final)
        return
    os.unlink(tmp)


@contextlib.contextmanager
def writing_files(*paths: str | os.PathLike[str], what: str = "output", replace: bool = False
                  ) -> Iterator[list[Path]]:
    """Temporary paths for ``paths``, all renamed to their names when the block ends well; on any
    failure (Ctrl-C included) every temporary file is removed, and any of ``paths`` already renamed
    too, so results that belong together appear together or not at all. A failure to write one is
    an OutputError naming it. ``replace``: an existing file of the name is replaced (only for a
    folder the command owns); otherwise each must not exist (:func:`~trundle.logs.paths.new_file`;
    ``what`` names them in that mistake)."""
    finals = [Path(p) for p in paths]
    if not replace:
        for final in finals:
            new_file(final, what)
    temps = [temporary_path(p) for p in finals]
    installed: list[Path] = []
    try:
        yield temps
        for tmp, final in zip(temps, finals, strict=True):
            _install(tmp, final, replace)
            installed.append(final)
    except BaseException as error:
        for final in installed:
            final.unlink(missing_ok=True)
        for tmp in temps:
            _remove(tmp)
        said = _said_for(error, temps, finals)
        if said is not None:
            raise said from None
        raise


@contextlib.contextmanager
def writing_file(path: str | os.PathLike[str], what: str = "output", replace: bool = False) -> Iterator[Path]:
    """A temporary path for the output ``path`` (a file that must not exist; ``what`` names it in that
    mistake), renamed to ``path`` when the block ends well, removed on any failure; see
    :func:`writing_files`."""
    with writing_files(path, what=what, replace=replace) as (tmp,):
        yield tmp


@contextlib.contextmanager
def writing_folder(path: str | os.PathLike[str], *, empty: bool = True, marker: str | None = None,
                   keep: tuple[str, ...] = ()) -> Iterator[Path]:
    """The results folder ``path``, checked and made as :func:`~trundle.logs.paths.output_folder`
    does; results go into it in the block (each file through :func:`writing_file`). On any failure
    what this run added to it is removed (what it held before stays), and the folder itself (and
    any parent made for it) if this run made it and it is left empty. ``keep``: glob patterns of
    names that stay even then (a partial recording the user is told about), and with them the
    ``marker``. A failure to write a file in it is an OutputError naming that file."""
    path = Path(path)
    made = [p for p in (path, *path.parents) if not p.exists()][::-1]  # outermost first
    before = set(os.listdir(path)) if path.is_dir() else set()
    try:
        output_folder(path, empty=empty, marker=marker)
        yield path
    except BaseException as error:
        with contextlib.suppress(OSError):
            added = set(os.listdir(path)) - before
            kept = {name for name in added if any(fnmatch.fnmatchcase(name, pattern) for pattern in keep)}
            if kept and marker is not None:
                kept.add(marker)
            for name in added - kept:
                new = path / name
                if new.is_dir() and not new.is_symlink():
                    shutil.rmtree(new, ignore_errors=True)
                else:
                    new.unlink(missing_ok=True)
        for folder in reversed(made):
            try:
                folder.rmdir()
            except OSError:
                break
        if isinstance(error, OSError) and is_output_failure(error):
            where = os.fsdecode(error.filename) if error.filename is not None else str(path)
            if error.filename is None or Path(where).resolve().is_relative_to(path.resolve()):
                raise output_error(error, where) from None
        raise


def plain(value: Any) -> Any:
    """``value`` with NumPy scalars and arrays as the numbers and lists they hold, tuples as lists,
    and every non-finite float (NaN, infinity) as None: what strict JSON can hold."""
    if isinstance(value, dict):
        return {str(k) if not isinstance(k, str) else k: plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return plain(value.tolist())
    if isinstance(value, np.generic):
        return plain(value.item())
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _default(value: Any) -> Any:
    """What ``json.dumps`` knows no form for: NumPy values as :func:`plain` makes them, anything else
    (a path, an object) as its text."""
    return plain(value) if isinstance(value, (np.ndarray, np.generic)) else str(value)


def json_text(value: Any, indent: int | None = None, sort_keys: bool = False) -> str:
    """``value`` as strict JSON (RFC 8259: no NaN or Infinity, which :func:`plain` makes null); a
    value JSON has no form for (a path, an object) is written as its text."""
    try:  # most values hold only finite numbers: no walk over them first
        return json.dumps(value, indent=indent, sort_keys=sort_keys, allow_nan=False, default=_default)
    except ValueError:  # a NaN or infinity somewhere: null
        return json.dumps(plain(value), indent=indent, sort_keys=sort_keys, allow_nan=False, default=_default)


def write_bytes(path: str | os.PathLike[str], data: bytes, replace: bool = False) -> Path:
    """Write ``data`` to the new file ``path`` (through :func:`writing_file`); returns the path."""
    with writing_file(path, replace=replace) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def write_text(path: str | os.PathLike[str], text: str, replace: bool = False) -> Path:
    """Write ``text`` (UTF-8) to the new file ``path`` (through :func:`writing_file`); returns the path."""
    return write_bytes(path, text.encode("utf-8"), replace)


def write_json(path: str | os.PathLike[str], value: Any, indent: int | None = 2, replace: bool = False) -> Path:
    """Write ``value`` as strict JSON (:func:`json_text`, a final newline) to the new file ``path``."""
    return write_text(path, json_text(value, indent) + "\n", replace)


def encode_image(image: np.ndarray, suffix: str, path: str | os.PathLike[str] = "") -> bytes:
    """``image`` (OpenCV's BGR or grey) encoded as the extension ``suffix`` says (``.png``, ``.pgm``,
    ``.jpg``); in memory, so the file is written by Python and a full disk is said as such. A suffix
    OpenCV has no encoder for is a UserError naming ``path``."""
    import cv2

    try:
        ok, data = cv2.imencode(suffix, image)
    except cv2.error:
        ok = False
    if not ok:
        raise UserError(f"cannot write {path or 'a picture'}: OpenCV encodes no picture as {suffix or 'no extension'}")
    return data.tobytes()


def write_image(path: str | os.PathLike[str], image: np.ndarray, replace: bool = False) -> Path:
    """Write ``image`` (OpenCV's BGR or grey) to the new file ``path``, encoded as its extension says."""
    path = Path(path)
    return write_bytes(path, encode_image(image, path.suffix, path), replace)


def save_figure(figure: Any, path: str | os.PathLike[str], dpi: int = 100, replace: bool = False) -> Path:
    """Save the Matplotlib ``figure`` to the new file ``path`` (its format from the extension)."""
    path = Path(path)
    with writing_file(path, replace=replace) as tmp:
        figure.savefig(tmp, dpi=dpi, format=path.suffix.lstrip(".") or None)
    return path
