"""Atomic file writes: a temporary name in the target folder, fsync, rename.

Every file hfrad writes (factorizations, exports, pictures, checkpoints, form
factor matrices and caches) goes through :func:`atomic_path`, so a reader
never sees half a file and a failed write leaves nothing behind. The
temporary file is created with mode ``0o666`` filtered by the process umask
(what ``open(path, "w")`` would give), so the final file is as readable as
any other file the user creates; ``tempfile.mkstemp`` would leave it 0600.

A write that fails for a reason of the file system (no space left, a
read-only or missing folder, no permission, an I/O error) raises
:class:`~hfrad.errors.WriteError` naming the file the caller asked for, not
the temporary name. :func:`check_writable` finds such a folder before a
long computation starts. A run killed while writing leaves its temporary
file behind; the next write of the same target in a later process removes
it (:func:`remove_stale_temporaries`).
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import secrets
import time
from pathlib import Path
from typing import Iterator

from .errors import WriteError

__all__ = ["atomic_path", "publish", "new_file", "check_writable", "check_space", "free_bytes",
           "remove_stale_temporaries", "write_error"]

#: When this process started writing files (module import): temporaries of a target modified
#: before it belong to an earlier run that was killed.
_RUN_START = time.time()

#: Targets whose stale temporaries this process has already looked for.
_CLEANED: set[str] = set()

_REASONS = {
    errno.ENOSPC: "no space left on device",
    errno.EDQUOT: "disk quota exceeded",
    errno.EFBIG: "file too large for the file system",
    errno.EIO: "input/output error",
    errno.EROFS: "read-only file system",
    errno.EACCES: "permission denied",
    errno.EPERM: "permission denied",
    errno.ENOENT: "its folder does not exist",
    errno.ENOTDIR: "its folder is not a folder",
    errno.EISDIR: "it is a directory",
    errno.ENAMETOOLONG: "file name too long",
}
#: Errors of writing data (not of finding the folder): a writer's own OSError with these is the file system's.
_DATA_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EIO, errno.EROFS}


def _errno_of(exc: OSError) -> int | None:
    """The errno of ``exc``; h5py and zipfile sometimes give it only in the message ("[Errno 28] ...")."""
    if exc.errno is not None:
        return exc.errno
    m = re.search(r"errno = (\d+)|\[Errno (\d+)\]", str(exc))
    if m:
        return int(m.group(1) or m.group(2))
    if "No space left on device" in str(exc):
        return errno.ENOSPC
    return None


def write_error(exc: OSError, path: "str | os.PathLike") -> WriteError | None:
    """A :class:`WriteError` naming ``path`` for a file-system failure ``exc``, or None if ``exc`` is not one."""
    code = _errno_of(exc)
    reason = _REASONS.get(code) if code is not None else None
    if reason is None:
        return None
    err = WriteError(f"{reason} writing {path}" if code in _DATA_ERRNOS - {errno.EROFS} else f"cannot write {path}: {reason}")
    err.errno = code
    return err


def check_writable(path: "str | os.PathLike") -> Path:
    """Refuse at once an output file that could not be written at the end of a run.

    Checks that ``path`` is not a directory and that a file can be created in
    its folder (by creating and removing a temporary one: permission bits
    alone do not tell a read-only mount or root's rights). Removes stale
    temporaries of ``path`` left by a killed earlier run.

    Parameters
    ----------
    path : str or path-like
        The file a command will write.

    Returns
    -------
    Path

    Raises
    ------
    WriteError
        The folder is missing, not a folder, read-only or not writable, or
        ``path`` is a directory; the message names ``path``.
    """
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    if path.is_dir():
        raise WriteError(f"cannot write {path}: it is a directory")
    if not folder.exists():
        raise WriteError(f"cannot write {path}: the folder {folder} does not exist")
    if not folder.is_dir():
        raise WriteError(f"cannot write {path}: {folder} is not a folder")
    remove_stale_temporaries(path)
    try:
        probe = _temporary_name(path, "")
    except OSError as exc:
        raise (write_error(exc, path) or WriteError(f"cannot write {path}: {exc.strerror or exc}")) from None
    with contextlib.suppress(OSError):
        os.unlink(probe)
    return path


def free_bytes(folder: "str | os.PathLike") -> int:
    """Bytes an unprivileged user may still write on the file system of ``folder`` (statvfs)."""
    st = os.statvfs(folder)
    return int(st.f_bavail) * int(st.f_frsize)


def check_space(path: "str | os.PathLike", nbytes: float) -> None:
    """Refuse to start writing ``nbytes`` to ``path`` when its file system has less room.

    Some writers cannot fail cleanly half way (HDF5 2.0 through h5py 3.16
    crashes the process when it closes a file after "no space left on
    device"), so those check first.

    Raises
    ------
    WriteError
        ``nbytes`` exceeds the free space; the message names ``path`` and both sizes.
    """
    from .memory import human

    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    try:
        free = free_bytes(folder)
    except OSError:      # a folder that cannot be asked: the write itself will tell
        return
    if nbytes > free:
        err = WriteError(f"no space left on device writing {path}: it needs about {human(nbytes)}, "
                         f"{human(free)} free")
        err.errno = errno.ENOSPC
        raise err


def remove_stale_temporaries(path: "str | os.PathLike", suffix: str = "") -> list[Path]:
    """Remove the temporaries of ``path`` (``.NAME.XXXXXXXX.tmpSUFFIX``) left by an earlier, killed run.

    Only files of exactly that form, last modified before this process
    started, are removed (a concurrent writer's temporary is newer).
    Returns the removed paths.
    """
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    pattern = re.compile(re.escape(f".{path.name}.") + r"[0-9a-f]{8}\.tmp" + re.escape(suffix) + "$")
    removed = []
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return removed
    for entry in entries:
        if not pattern.match(entry.name):
            continue
        with contextlib.suppress(OSError):
            if entry.is_file(follow_symlinks=False) and entry.stat(follow_symlinks=False).st_mtime < _RUN_START:
                os.unlink(entry.path)
                removed.append(Path(entry.path))
    return removed


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
def atomic_path(path: "str | os.PathLike", *, suffix: str = "", size: float | None = None) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success it becomes ``path``.

    Parameters
    ----------
    path : str or path-like
        The final file. Its folder must exist.
    suffix : str
        Ending of the temporary name, for writers that insist on one
        (``numpy.savez`` appends ``.npz`` otherwise).
    size : float, bytes, optional
        What the writer is about to write: refused before the temporary file
        is made when the file system has less room (:func:`check_space`).
        Writers that cannot fail cleanly on a full disk (HDF5) should give it.

    Yields
    ------
    Path
        An existing empty file (mode 0o666 minus the umask) in the same
        folder; write it completely (writers may truncate or replace it).

    Raises
    ------
    WriteError
        The file system refused: no space left, a read-only or missing
        folder, no permission, an I/O error (the message names ``path``).

    Notes
    -----
    On an exception the temporary file is removed and the exception
    propagates (a file-system error as :class:`WriteError`); ``path`` is
    untouched. Stale temporaries of ``path`` from a killed earlier run are
    removed on the first write of ``path`` in a process.

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
    if size is not None:
        check_space(path, size)
    key = str(path.absolute()) + "\0" + suffix
    if key not in _CLEANED:
        remove_stale_temporaries(path, suffix)
        _CLEANED.add(key)
    try:
        tmp = _temporary_name(path, suffix)
    except OSError as exc:
        err = write_error(exc, path)
        if err is None:
            raise
        raise err from exc
    try:
        yield tmp
    except BaseException as exc:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if isinstance(exc, OSError) and not isinstance(exc, WriteError) and _errno_of(exc) in _DATA_ERRNOS:
            raise write_error(exc, path) from exc
        raise
    try:
        publish(tmp, path)
    except OSError as exc:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        err = write_error(exc, path)
        if err is None:
            raise
        raise err from exc


def check_outputs(outputs: dict, inputs: dict) -> None:
    """InputError if an output names one of the command's inputs or another output.

    ``outputs`` and ``inputs`` map an option's name (``-o/--output``,
    ``--layout``) to a path or None. Paths are compared resolved, and as the
    same file where both exist (links, other spellings).
    """
    from .errors import InputError

    seen: list[tuple[str, Path, str]] = [(name, Path(p), "input") for name, p in inputs.items() if p is not None]
    for name, p in outputs.items():
        if p is None:
            continue
        p = Path(p)
        for other, q, kind in seen:
            same = p.resolve() == q.resolve()
            with contextlib.suppress(OSError):
                same = same or (p.exists() and q.exists() and os.path.samefile(p, q))
            if same:
                raise InputError(f"{name} '{p}' is also the {kind} {other}; choose another name "
                                 "(it would be overwritten)")
        seen.append((name, p, "output"))


@contextlib.contextmanager
def atomic_paths(*paths: "str | os.PathLike") -> Iterator[list[Path]]:
    """Temporaries for several outputs (:func:`atomic_path` each), published only if the block completes.

    A command's outputs are all written or none: an error while writing any
    of them removes every temporary and leaves the targets as they were.
    """
    with contextlib.ExitStack() as stack:
        yield [stack.enter_context(atomic_path(p, suffix=Path(p).suffix)) for p in paths]
