"""Checkpoints of ``far_field="hierarchical"``: the built H-matrix, so a rerun skips its build.

The H-matrix is most of the hierarchical precompute's time (161,808 patches: 232 of 393 s), and
everything after it (statistics, certificate, factorization, the near field's LU) is a function
of it and the plan. So one checkpoint, written once the H-matrix is built, is what a rerun
needs: it loads the blocks and goes on from the statistics. The file is protected as the HF
stream's checkpoints are (:mod:`hfrad.lowrank.streaming`): Fletcher-32 on every array, a
SHA-256 digest of the attributes, the dataset list; a damaged file, another version or a
checkpoint made for another input (the plan's key) is refused, never resumed and never deleted.
"""

from __future__ import annotations

import dataclasses
import json
import os

import numpy as np

from ..atomic import atomic_path
from ..errors import FileFormatError, InputError
from ..formfactors.bfloat16 import VALUE_DTYPES
from ..formfactors.hmatrix import BlockList, FormFactorHMatrix
from ..integrity import checked_dataset, seal
from ..lowrank.streaming import check_checkpoint, open_checkpoint

__all__ = ["save_hmatrix_checkpoint", "load_hmatrix_checkpoint", "FORMAT", "VERSION"]

FORMAT = "hfrad-hmatrix-checkpoint"
VERSION = 1
#: The block list's arrays, in the order of :class:`BlockList`'s fields.
_ARRAYS = tuple(f.name for f in dataclasses.fields(BlockList))
#: HDF5 chunks of 4M entries: the default chunking of a multi-GB dataset makes its writes slow.
_CHUNK = 1 << 22
_DELETE = "delete it to start over (the precompute then builds the H-matrix again)"


def save_hmatrix_checkpoint(hm: FormFactorHMatrix, path: str | os.PathLike, key: str) -> None:
    """Write the H-matrix ``hm`` (before :meth:`~FormFactorHMatrix.take_near`) to ``path`` atomically
    (a temporary name, then a rename); refused before writing when the disk has less room than it needs.

    ``key`` identifies the input (:meth:`~hfrad.precompute.assemble.PrecomputePlan.key`).
    """
    import h5py

    if hm.removed is not None:
        raise InputError("the H-matrix checkpoint is of the built H-matrix, before its near field is taken")
    arrays = {name: getattr(hm.blocks, name) for name in _ARRAYS}
    size = sum(a.nbytes for a in arrays.values()) + hm.perm.nbytes + (64 << 10)
    with atomic_path(path, size=size) as tmp, h5py.File(tmp, "w") as f:
        f.attrs["format"], f.attrs["version"], f.attrs["key"] = FORMAT, VERSION, key
        f.attrs["info"] = json.dumps(hm.info, default=lambda x: x.item() if isinstance(x, np.generic) else str(x))
        checked_dataset(f, "perm", hm.perm)
        for name, a in arrays.items():
            checked_dataset(f, f"blocks/{name}", a, chunks=(min(_CHUNK, a.size),) if a.size else None)
        seal(f)


def load_hmatrix_checkpoint(path: str | os.PathLike, key: str, perm: np.ndarray) -> FormFactorHMatrix:
    """The H-matrix saved by :func:`save_hmatrix_checkpoint` at ``path``, checked against ``key`` and
    the plan's tree order ``perm``.

    Raises
    ------
    FileNotFoundError
        No file at ``path``.
    FileFormatError
        Not an H-matrix checkpoint, damaged or truncated, or of another version.
    InputError
        Made for another input (another key, or a checkpoint of the column-block pass).
    """
    f = open_checkpoint(path, FORMAT, _DELETE)
    with f:
        if f.attrs.get("format") != FORMAT:
            raise FileFormatError(f"{path}: not an hfrad checkpoint; {_DELETE}")
        if int(f.attrs.get("version", -1)) != VERSION:
            raise FileFormatError(f"{path}: H-matrix checkpoint version {f.attrs.get('version')}, this hfrad "
                                  f"reads {VERSION} only; {_DELETE}")
        check_checkpoint(f, path, key, _DELETE)
        try:
            saved_perm = f["perm"][()]
            blocks = BlockList(*(f[f"blocks/{name}"][()] for name in _ARRAYS))
            info = json.loads(f.attrs["info"])
        except (OSError, KeyError, ValueError) as exc:     # a checksum that fails as the data are read
            raise FileFormatError(f"{path}: damaged checkpoint ({str(exc)[:200]}); {_DELETE}") from None
    if blocks.U.dtype not in VALUE_DTYPES.values() or blocks.V.dtype != blocks.U.dtype:
        raise FileFormatError(f"{path}: the blocks' values are {blocks.U.dtype} and {blocks.V.dtype}, not float32 or "
                              f"bfloat16 (uint16) alike; {_DELETE}")
    if not np.array_equal(saved_perm, perm):
        raise InputError(f"{path}: checkpoint was made for another patch order; {_DELETE}")
    return FormFactorHMatrix(saved_perm, blocks, info)
