"""File writing that never leaves a half-written file and never loses a user's file.

A file is written to a hidden temporary sibling and renamed over the target (rename is
atomic on POSIX). A new directory is filled as a temporary sibling and renamed into place;
an existing one only gets the files the caller writes, each renamed in, and nothing else
in it is touched. Files get the user's umask (a temporary file made by ``mkstemp`` would
be 0600). Any OS error becomes one :class:`OutputError` naming the path.
"""
from __future__ import annotations

import contextlib
import errno
import json
import os
import shutil
import uuid
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from .errors import OutputError


def _why(e: OSError) -> str:
    return e.strerror or str(e)


def _temp_sibling(path: Path, suffix: str = ".tmp") -> Path:
    return path.parent / f".{path.name}.{uuid.uuid4().hex[:12]}{suffix}"


def _make_parent(path: Path) -> None:
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise OutputError(f"{path}: a parent of it is a file, not a folder") from None
    except NotADirectoryError:
        raise OutputError(f"{path}: a parent of it is a file, not a folder") from None
    except OSError as e:
        raise OutputError(f"{path}: cannot create its folder ({_why(e)})") from None


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (temporary sibling, then rename), with the
    user's umask. An :class:`OutputError` names the file when it cannot be written."""
    path = Path(path)
    if path.is_dir():
        raise OutputError(f"{path}: is a folder, expected a file name")
    _make_parent(path)
    tmp = _temp_sibling(path)
    try:
        # os.open with 0o666 lets the umask decide the permissions, as open() would.
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as e:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if isinstance(e, OSError):
            raise OutputError(f"{path}: cannot write ({_why(e)})") from None
        raise


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    atomic_write_bytes(path, text.encode("utf-8"))


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"cannot write {type(obj).__name__} as JSON")


def to_json(obj: Any, indent: int | None = 1) -> str:
    """JSON text of ``obj``; NumPy arrays and scalars become lists and numbers."""
    return json.dumps(obj, indent=indent, default=_jsonable)


def atomic_write_json(path: str | os.PathLike, obj: Any, indent: int | None = 1) -> None:
    atomic_write_text(path, to_json(obj, indent) + "\n")


# ------------------------------------------------------------------ checks before work
def _nearest_existing(path: Path) -> Path:
    p = path.absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    return p


def check_writable_folder(folder: str | os.PathLike, what: str | None = None) -> None:
    """Raise :class:`OutputError` unless files can be created in ``folder`` (or, when it does
    not exist yet, in its nearest existing ancestor, where it would be created). Tries it:
    permission bits do not tell for root or for a read-only file system."""
    folder = Path(folder)
    base = _nearest_existing(folder)
    name = what or str(folder)
    if not base.is_dir():
        raise OutputError(f"{name}: {base} is a file, not a folder")
    probe = base / f".tapecell-write-test.{uuid.uuid4().hex[:12]}"
    try:
        fd = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        raise OutputError(f"{name}: cannot write in {base} ({_why(e)})") from None


def check_new_file(path: str | os.PathLike, force: bool = False) -> Path:
    """Check before any work that ``path`` can be written as a file: it is not a folder, it
    does not exist (unless ``force``: then it will be replaced) and its folder is writable."""
    path = Path(path)
    if path.is_dir():
        raise OutputError(f"{path}: is a folder, expected a file name")
    if path.exists() and not force:
        raise OutputError(f"{path}: already exists; choose another name or add --force to replace it")
    check_writable_folder(path.parent, str(path))
    return path


def check_output_dir(path: str | os.PathLike, force: bool = False) -> Path:
    """Check before any work that ``path`` can take a command's output files: it is not a
    file, and it does not exist, is empty, or ``force`` allows adding to it (even then only
    the files the command names are written; nothing else in it is touched)."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise OutputError(f"{path}: exists and is a file, expected a folder")
    if path.is_dir() and any(path.iterdir()) and not force:
        raise OutputError(f"{path}: folder is not empty; choose a new or empty folder, or add --force to "
                          "write into it (only this command's files are replaced)")
    check_writable_folder(path)
    return path


@contextlib.contextmanager
def atomic_dir(path: str | os.PathLike, force: bool = False) -> Iterator[Path]:
    """Fill a directory: yields a temporary sibling to write the files in.

    A new ``path`` (or an empty one) gets the temporary folder renamed into place, so it
    appears complete or not at all. A non-empty ``path`` is refused with an
    :class:`OutputError` unless ``force``; then each written file is renamed into it, and
    nothing else in it is removed or replaced. On an error the temporary folder is removed
    and ``path`` is left as it was.
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise OutputError(f"{path}: exists and is a file, expected a folder")
    existing = path.is_dir() and any(path.iterdir())
    if existing and not force:
        check_output_dir(path, force)   # raises the refusal
    _make_parent(path)
    tmp = _temp_sibling(path)
    try:
        os.mkdir(tmp, 0o777)            # the umask applies, as for a folder made by mkdir
    except OSError as e:
        raise OutputError(f"{path}: cannot create a folder next to it ({_why(e)})") from None
    try:
        yield tmp
        if not existing:
            try:
                os.replace(tmp, path)   # onto nothing or onto an empty folder: atomic
                return
            except OSError as e:
                if e.errno not in (errno.ENOTEMPTY, errno.EEXIST):
                    raise
                if not force:           # something appeared in it meanwhile
                    raise OutputError(f"{path}: folder is not empty any more; nothing written") from None
        for item in sorted(tmp.iterdir()):
            target = path / item.name
            if target.is_dir() and not item.is_dir():
                raise OutputError(f"{target}: is a folder; cannot replace it with a file")
            os.replace(item, target)
        os.rmdir(tmp)
    except BaseException as e:
        shutil.rmtree(tmp, ignore_errors=True)
        if isinstance(e, OSError):
            raise OutputError(f"{path}: cannot write ({_why(e)})") from None
        raise
