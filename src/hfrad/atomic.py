"""Atomic file writes: a temporary name in the target folder, fsync, rename.

Every file hfrad writes (factorizations, exports, pictures, checkpoints, form
factor matrices and caches) goes through :func:`atomic_path`, so a reader
never sees half a file and a failed write leaves nothing behind. The
temporary file is created with mode ``0o666`` filtered by the process umask
(what ``open(path, "w")`` would give), so the final file is as readable as
any other file the user creates; ``tempfile.mkstemp`` would leave it 0600.
"""

from __future__ import annotations

import contextlib
import os
import secrets
from pathlib import Path
from typing import Iterator

__all__ = ["atomic_path", "publish", "new_file"]


def new_file(path: "str | os.PathLike") -> None:
    """Create ``path`` empty (it must not exist), with mode 0o666 minus the umask."""
    fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o666)
    os.close(fd)


def _temporary_name(path: Path, suffix: str) -> Path:
    """A fresh, exclusively created, empty file next to ``path``."""
    while True:
        tmp = path.with_name(f".{path.name}.{secrets.token_hex(4)}.tmp{suffix}")
        try:
            new_file(tmp)
            return tmp
        except FileExistsError:  # pragma: no cover - 32 random bits collided
            continue


def _fsync(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def publish(tmp: "str | os.PathLike", path: "str | os.PathLike") -> None:
    """Flush ``tmp`` to disk and rename it to ``path`` (atomic on POSIX), then sync the folder."""
    tmp, path = Path(tmp), Path(path)
    _fsync(tmp)
    os.replace(tmp, path)
    with contextlib.suppress(OSError):  # some file systems cannot open or sync a directory
        _fsync(path.parent if str(path.parent) else Path("."))


@contextlib.contextmanager
def atomic_path(path: "str | os.PathLike", *, suffix: str = "") -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success it becomes ``path``.

    Parameters
    ----------
    path : str or path-like
        The final file. Its folder must exist.
    suffix : str
        Ending of the temporary name, for writers that insist on one
        (``numpy.savez`` appends ``.npz`` otherwise).

    Yields
    ------
    Path
        An existing empty file (mode 0o666 minus the umask) in the same
        folder; write it completely (writers may truncate or replace it).

    Notes
    -----
    On an exception the temporary file is removed and the exception
    propagates; ``path`` is untouched.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> target = pathlib.Path(tempfile.mkdtemp()) / "out.txt"
    >>> with atomic_path(target) as tmp:
    ...     _ = tmp.write_text("complete")
    >>> target.read_text()
    'complete'
    """
    path = Path(path)
    tmp = _temporary_name(path, suffix)
    try:
        yield tmp
        publish(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
