"""Paths a user gives, checked before use so a mistake is said for what it is: a missing file,
a folder where a file belongs (or the reverse), a device such as ``/dev/zero`` that would be
read forever, a binary file where text belongs, an output that would overwrite a result or that
a read-only folder would refuse.
"""

from __future__ import annotations

import errno
import os
import stat
from pathlib import Path

from trundle.logs.errors import UserError


def _a(what: str) -> str:
    """``what`` with its indefinite article: "a file", "an image", "an MCAP log"."""
    first = what.split()[0]
    vowel = what[:1].lower() in "aeiou" or (first.isupper() and first[:1] in "AEFHILMNORSX")
    return f"{'an' if vowel else 'a'} {what}"


def input_file(path: str | os.PathLike[str], what: str = "file") -> Path:
    """``path`` as a regular file to read; otherwise a UserError saying what it is instead."""
    path = Path(path)
    try:
        mode = path.stat().st_mode
    except FileNotFoundError:
        raise UserError(f"no such {what}: {path}") from None
    except PermissionError:
        raise UserError(f"no permission to read {path}") from None
    except OSError as error:
        raise UserError(f"cannot read {path}: {error.strerror or error}") from None
    if stat.S_ISDIR(mode):
        raise UserError(f"{path} is a folder, not {_a(what)}")
    if not stat.S_ISREG(mode):
        raise UserError(f"{path} is not a regular file (a device or a pipe?), not {_a(what)}")
    return path


def read_text(path: str | os.PathLike[str], what: str = "text file") -> str:
    """The UTF-8 text of the regular file ``path``; a binary file is a UserError."""
    path = input_file(path, what)
    try:
        data = path.read_bytes()
    except OSError as error:
        raise UserError(f"cannot read {path}: {error.strerror or error}") from None
    if b"\0" in data[:65536]:
        raise UserError(f"{path} is not {_a(what)} (binary data)")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        raise UserError(f"{path} is not {_a(what)} (not UTF-8 text)") from None


def new_file(path: str | os.PathLike[str], what: str = "output") -> Path:
    """``path`` as a file to create: it must not exist (a result is never overwritten) nor be a folder."""
    path = Path(path)
    if path.is_dir():
        raise UserError(f"{what} {path} is a folder: give a file name in it")
    if path.exists() or path.is_symlink():
        raise UserError(f"{what} {path} exists: give another name, or move it away (it is never overwritten)")
    writable(path)
    return path


def writable(path: str | os.PathLike[str]) -> Path:
    """``path``, a file or folder to write, if the folder it goes in (its nearest existing one) can
    be written; a read-only or forbidden folder is an OutputError at once, before any work."""
    from trundle.logs.outputs import output_error  # the owner of output failures

    path = Path(path)
    folder = path if path.is_dir() else path.parent
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    if folder.is_dir() and not os.access(folder, os.W_OK | os.X_OK):
        cause = errno.EROFS if os.statvfs(folder).f_flag & os.ST_RDONLY else errno.EACCES
        raise output_error(OSError(cause, os.strerror(cause), str(folder)), path)
    return path


def output_folder(path: str | os.PathLike[str], *, empty: bool = True, create: bool = True,
                  marker: str | None = None) -> Path:
    """``path`` as a folder to write results into, created (with its parents) unless ``create`` is
    False (check now, make it once the inputs are known good); an existing file, or (``empty``) a
    folder that already holds files, is a UserError: results are never overwritten.

    ``marker``: the name of a file the command leaves in every folder it writes (written when the
    folder is made here). A folder holding it, made by the same command before, may be written
    again; any other folder that holds files is refused, naming some of them."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise UserError(f"output {path} is a file, not a folder")
    held = sorted(p.name for p in path.iterdir()) if path.is_dir() else []
    if held and marker is not None and marker not in held:
        shown = ", ".join(held[:4]) + (f" and {len(held) - 4} more" if len(held) > 4 else "")
        raise UserError(f"output folder {path} holds files this command did not write ({shown}): give a new or "
                        "empty folder (nothing of yours is overwritten)")
    if held and marker is None and empty:
        raise UserError(f"output folder {path} is not empty: give a new folder, or move its files away "
                        "(results are never overwritten)")
    writable(path)
    if not create:
        return path
    try:
        path.mkdir(parents=True, exist_ok=True)
        if marker is not None:
            (path / marker).touch()
    except OSError as error:
        from trundle.logs.outputs import is_output_failure, output_error  # the owner of output failures

        if is_output_failure(error):
            raise output_error(error, path) from None
        raise UserError(f"cannot create the output folder {path}: {error.strerror or error}") from None
    return path
