"""Checkpoints of a running HF stream, so an interrupted precompute resumes.

The state of :class:`~hfrad.lowrank.hf.HFStream` is its binary-counter stack
(O(log m) factor pairs) plus counters; saving it lets a long precomputation
resume after the last saved block without redoing finished blocks.

A checkpoint is an HDF5 file protected like an ``.hfr`` file: every array
carries HDF5's Fletcher-32 checksum, the attributes a SHA-256 digest, and the
root a list of the datasets (:func:`~hfrad.integrity.seal`). Policy: a
checkpoint that is damaged (a flipped bit, truncated, not HDF5 at all), written
by an older hfrad (version 1 had no checksums) or made for another scene or
other parameters is **refused** with a :class:`~hfrad.errors.FileFormatError`
or :class:`~hfrad.errors.InputError` naming the file and saying to delete it;
it is never resumed from, and never deleted behind the user's back (it may be
the only copy of hours of work, and the user may have pointed at the wrong
file).
"""

from __future__ import annotations

import json
import os

import numpy as np

from ..errors import FileFormatError, InputError
from ..atomic import atomic_path
from ..integrity import checked_dataset, integrity_problem, seal
from .hf import HFStream, _Node

#: 2: checksums, digest and dataset list (version 1 had none: refused, it cannot be verified).
CHECKPOINT_VERSION = 2
FORMAT = "hfrad-checkpoint"


def _params(stream: HFStream) -> dict:
    return {"n": stream.n, "n_blocks": stream.n_blocks, "eps": stream.eps, "relative": stream.relative,
            "dtype": stream.dtype.name, "leaf_share": stream.leaf_share}


def save_checkpoint(stream: HFStream, path: str | os.PathLike, key: str = "") -> None:
    """Write the stream state to ``path`` atomically (temporary name, then rename).

    ``key`` identifies the input (scene, parameters and form-factor kernel
    version); :func:`load_checkpoint` refuses a checkpoint whose key differs.
    ``stream.extra`` (name -> array) is what else the pass accumulates (row
    sums, probes, the near field) and comes back with the stream.
    """
    import h5py

    # h5py crashes the process on a full disk: atomic_path refuses first when the room is short
    size = (sum(np.asarray(a).nbytes for node in stream.stack for a in (node.U, node.s, node.V))
            + sum(np.asarray(a).nbytes for a in stream.extra.values()) + (64 << 10))
    with atomic_path(path, size=size) as tmp, h5py.File(tmp, "w") as f:
        f.attrs["format"] = FORMAT
        f.attrs["version"] = CHECKPOINT_VERSION
        f.attrs["key"] = key
        f.attrs["params"] = json.dumps(_params(stream))
        f.attrs["blocks_done"] = stream.blocks_done
        f.attrs["columns_done"] = stream.columns_done
        f.attrs["times"] = json.dumps([stream.time_leaf, stream.time_merge])
        checked_dataset(f, "leaf_ranks", np.asarray(stream.leaf_ranks, np.int64))
        for i, node in enumerate(stream.stack):
            g = f.create_group(f"node{i}")
            g.attrs["level"], g.attrs["norm2"] = node.level, node.norm2
            g.attrs["discarded2"], g.attrs["slack2"] = node.discarded2, node.slack2
            checked_dataset(g, "U", node.U)
            checked_dataset(g, "s", node.s)
            checked_dataset(g, "V", node.V)
        f.attrs["nodes"] = len(stream.stack)
        for name, arr in stream.extra.items():
            checked_dataset(f, f"extra/{name}", arr)
        seal(f)


_DELETE = "delete it to start over (the precompute then starts from the first block)"


def open_checkpoint(path: str | os.PathLike, fmt: str, advice: str):
    """``path`` opened for reading as an HDF5 checkpoint of format ``fmt`` (an open ``h5py.File``).

    Raises FileNotFoundError when there is none, FileFormatError when it is not readable HDF5, and
    InputError when it is an hfrad checkpoint of another kind (the other far field's: made with other
    parameters); ``advice`` ends each message (what to do with the file)."""
    import h5py

    try:
        f = h5py.File(path, "r")
    except FileNotFoundError:
        raise
    except (OSError, ValueError) as exc:
        raise FileFormatError(f"{path}: the checkpoint is not a readable HDF5 file (truncated or damaged: "
                              f"{str(exc)[:200]}); {advice}") from None
    other = f.attrs.get("format")
    if isinstance(other, str) and other.startswith("hfrad-") and other.endswith("-checkpoint") and other != fmt:
        f.close()
        raise InputError(f"{path}: a checkpoint of another far field ({other}), made with other parameters; "
                         f"{advice}, or use another output name")
    return f


def check_checkpoint(f, path: str | os.PathLike, key: str, advice: str) -> None:
    """Refuse the open checkpoint ``f`` when it is damaged (FileFormatError) or made for another input
    (InputError: ``key`` differs); ``advice`` ends each message."""
    problem = integrity_problem(f)
    if problem is not None:
        raise FileFormatError(f"{path}: damaged checkpoint, {problem}; {advice}")
    if str(f.attrs["key"]) != key:
        raise InputError(f"{path}: checkpoint was made for another scene or other parameters; "
                         f"{advice}, or use another output name")


def load_checkpoint(path: str | os.PathLike, key: str = "") -> HFStream:
    """Rebuild a stream from a checkpoint written by :func:`save_checkpoint`.

    Raises
    ------
    FileFormatError
        The file is not a checkpoint, is damaged or truncated (checksum or
        digest mismatch, missing data), or was written by another version.
    InputError
        It was made for another input (``key`` differs).
    """
    f = open_checkpoint(path, FORMAT, _DELETE)
    with f:
        try:
            version, fmt = f.attrs.get("version"), f.attrs.get("format")
            if version is None or (int(version) >= 2 and fmt != FORMAT):
                raise FileFormatError(f"{path}: not an hfrad checkpoint; {_DELETE}")
            if int(version) != CHECKPOINT_VERSION:
                raise FileFormatError(f"{path}: checkpoint version {int(version)}, this hfrad writes and reads "
                                      f"{CHECKPOINT_VERSION} only; {_DELETE}")
            check_checkpoint(f, path, key, _DELETE)
            stream = HFStream(**json.loads(f.attrs["params"]))
            stream.blocks_done = int(f.attrs["blocks_done"])
            stream.columns_done = int(f.attrs["columns_done"])
            stream.time_leaf, stream.time_merge = json.loads(f.attrs["times"])
            stream.leaf_ranks = [int(x) for x in f["leaf_ranks"][()]]
            for i in range(int(f.attrs["nodes"])):
                g = f[f"node{i}"]
                stream.stack.append(_Node(int(g.attrs["level"]), g["U"][()], g["s"][()], g["V"][()],
                                          float(g.attrs["norm2"]), float(g.attrs["discarded2"]),
                                          float(g.attrs["slack2"])))
            if "extra" in f:
                stream.extra = {name: ds[()] for name, ds in f["extra"].items()}
        except (FileFormatError, InputError):
            raise
        except (OSError, KeyError, ValueError, TypeError) as exc:  # h5py's errors on damaged data
            raise FileFormatError(f"{path}: damaged checkpoint (checksum mismatch or unreadable data: "
                                  f"{str(exc)[:200]}); {_DELETE}") from None
    return stream
