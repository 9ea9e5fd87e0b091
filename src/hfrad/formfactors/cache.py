"""On-disk cache of form-factor column blocks (HDF5), resumable.

A cache file holds one n x n matrix ``F`` in the *internal* order (rows
``order``, columns ``order``), written block column by block column as they
are computed, plus a ``done`` flag per block. It is written under a temporary
name ``<path>.partial`` and renamed to ``<path>`` when every block is there,
so ``<path>`` is always complete. An interrupted run leaves the ``.partial``
file; the next run with the same key validates it and computes only the
missing blocks.

Key: SHA-256 of the scene (vertices, faces, occluder mesh) and the parameters
(samples, block size, order, dtype, kernel version, near-field settings).

Policy on mismatch: a complete cache whose key differs raises
:class:`CacheMismatchError` naming the differing fields (silently recomputing
would hide an expensive mistake; delete the file or pass another path). A
``.partial`` file that does not match, or cannot be read (killed while
writing), is only scratch: it is discarded with a ``UserWarning`` and rebuilt.

Integrity (format 2): ``F`` and ``done`` carry HDF5's Fletcher-32 checksum on
every chunk, the attributes a SHA-256 digest and the root the list of datasets
(:func:`hfrad.integrity.seal`, the same checks as HF checkpoints and ``.hfr`` files). A
complete cache that fails them, or a block whose checksum fails when read,
raises :class:`~hfrad.errors.FileFormatError` naming the file (delete it: it
is recomputed); a format-1 cache (no checksums) is refused the same way.
"""

from __future__ import annotations

import hashlib
import json
import warnings
from pathlib import Path

import numpy as np

from ..atomic import publish
from ..errors import FileFormatError
from ..integrity import checked_dataset, integrity_problem, seal

FORMAT_VERSION = 2


class CacheMismatchError(FileFormatError):
    """A form-factor cache file was made for another scene or other parameters."""


def scene_hash(scene) -> str:
    """SHA-256 (hex) of the patch geometry and the occluder mesh."""
    h = hashlib.sha256()
    for a in (scene.vertices, scene.faces, scene.occluder_vertices, scene.occluder_faces, scene.patch_of_triangle):
        a = np.ascontiguousarray(a)
        h.update(str((a.dtype.str, a.shape)).encode())
        h.update(a.tobytes())
    return h.hexdigest()


def array_hash(a: np.ndarray) -> str:
    a = np.ascontiguousarray(a)
    return hashlib.sha256(str((a.dtype.str, a.shape)).encode() + a.tobytes()).hexdigest()


def _h5py():
    try:
        import h5py
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise ImportError("the form-factor cache needs h5py: pip install h5py") from exc
    return h5py


class BlockCache:
    """A resumable HDF5 store of column blocks.

    Parameters
    ----------
    path : str or Path
        Final file name (``.h5`` recommended); ``<path>.partial`` while incomplete.

    Use through ``iter_column_blocks(..., cache=path)``; the methods below are
    what it calls: :meth:`open` with the key, :meth:`get` / :meth:`put` per
    block, :meth:`finish` at the end.
    """

    def __init__(self, path) -> None:
        self.path = Path(path)
        self.partial = self.path.with_name(self.path.name + ".partial")
        self._file = None
        self._readonly = False

    # -- life cycle ------------------------------------------------------
    def open(self, key: dict, n: int, block_size: int, dtype) -> None:
        """Open (validating ``key``) or create the cache for an n x n matrix."""
        h5py = _h5py()
        dtype = np.dtype(dtype)
        n_blocks = -(-n // block_size) if n else 0
        if self.path.exists():
            f = self._open_existing(self.path, h5py)
            self._check_key(f, key, self.path)
            self._file, self._readonly = f, True
            return
        if self.partial.exists():
            try:
                f = self._open_existing(self.partial, h5py, mode="r+")
                self._check_key(f, key, self.partial)
                if f["F"].shape != (n, n) or len(f["done"]) != n_blocks:
                    raise CacheMismatchError("shape")
                self._file, self._readonly = f, False
                return
            except (CacheMismatchError, FileFormatError, OSError, KeyError) as exc:
                try:
                    f.close()  # type: ignore[possibly-undefined]
                except Exception:
                    pass
                warnings.warn(f"discarding the unusable partial form-factor cache {self.partial} ({exc})",
                              UserWarning, stacklevel=3)
                self.partial.unlink()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        f = h5py.File(self.partial, "w")
        f.attrs["hfrad_format"] = "formfactor-blocks"
        f.attrs["format_version"] = FORMAT_VERSION
        f.attrs["key"] = json.dumps(key, sort_keys=True)
        chunk_rows = max(1, min(n, (1 << 20) // max(1, block_size)))
        checked_dataset(f, "F", shape=(n, n), dtype=dtype,
                        chunks=(chunk_rows, max(1, min(n, block_size))) if n else None)
        checked_dataset(f, "done", shape=(n_blocks,), dtype=np.bool_, fillvalue=False)
        seal(f)   # the attributes are final: the chunks' checksums follow the data as it is written
        f.flush()
        self._file, self._readonly = f, False

    @staticmethod
    def _open_existing(path: Path, h5py, mode: str = "r"):
        try:
            f = h5py.File(path, mode)
        except OSError as exc:
            raise FileFormatError(f"{path}: not a readable HDF5 file ({exc})") from exc
        if f.attrs.get("hfrad_format") != "formfactor-blocks":
            f.close()
            raise FileFormatError(f"{path}: not an hfrad form-factor cache")
        version = int(f.attrs.get("format_version", -1))
        if version > FORMAT_VERSION:
            f.close()
            raise FileFormatError(f"{path}: written by a newer hfrad (format {f.attrs['format_version']})")
        problem = ("it was written by an older hfrad, without checksums" if version < FORMAT_VERSION
                   else integrity_problem(f))
        if problem is not None:
            f.close()
            raise FileFormatError(f"{path}: damaged form-factor cache, {problem}; delete it (it is recomputed)")
        return f

    @staticmethod
    def _check_key(f, key: dict, path: Path) -> None:
        stored = json.loads(f.attrs["key"])
        diff = sorted(k for k in set(stored) | set(key) if stored.get(k) != key.get(k))
        if diff:
            f.close()
            raise CacheMismatchError(
                f"{path}: form-factor cache was computed for different "
                + ", ".join(f"{k} (cached {stored.get(k)!r}, requested {key.get(k)!r})" for k in diff)
                + "; delete the file or choose another cache path")

    # -- blocks ----------------------------------------------------------
    def get(self, index: int, start: int, stop: int) -> np.ndarray | None:
        """Block ``index`` (columns start:stop) if stored, else None."""
        f = self._file
        try:
            if not bool(f["done"][index]):
                return None
            return f["F"][:, start:stop]
        except OSError as exc:   # HDF5: checksum mismatch or unreadable chunk
            raise FileFormatError(f"{f.filename}: block {index} of the form-factor cache is damaged ({exc}); "
                                  "delete the file (it is recomputed)") from None

    def has(self, index: int) -> bool:
        """Whether block ``index`` is stored (reads only its flag)."""
        try:
            return bool(self._file["done"][index])
        except OSError as exc:
            raise FileFormatError(f"{self._file.filename}: the form-factor cache is damaged ({exc}); "
                                  "delete the file (it is recomputed)") from None

    def put(self, index: int, start: int, stop: int, block: np.ndarray) -> None:
        """Store a block and mark it done (data first, then the flag, each flushed)."""
        if self._readonly:
            return
        f = self._file
        f["F"][:, start:stop] = block
        f.flush()
        f["done"][index] = True
        f.flush()

    def finish(self) -> None:
        """Close; if every block is done, atomically rename the partial file to the final name."""
        f = self._file
        if f is None:
            return
        complete = bool(np.all(f["done"][...]))
        f.close()
        self._file = None
        if not self._readonly and complete:
            publish(self.partial, self.path)

    def close(self) -> None:
        """Close without renaming (an interrupted run keeps its partial file)."""
        if self._file is not None:
            self._file.close()
            self._file = None
