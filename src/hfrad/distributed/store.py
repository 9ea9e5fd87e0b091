"""Checkpoints of a Dask precompute: the finished subtrees' factors in a folder, with checksums.

Each leaf or merge task saves its :class:`~hfrad.distributed.tasks.Part` as
``node-<id>.npz`` (atomically) and then ``node-<id>.sha256`` (the npz's SHA-256):
the checksum file marks the part complete. A merge deletes its children's files
once its own are written, so the folder holds the tree's frontier (at most about
2 n k factor entries plus the near entries and statistics of those subtrees). A
rerun of the same precompute (same key) submits a load task for each saved node
and nothing below it. The folder must be reachable at the same path from every
worker and from the client (a shared file system on a real cluster).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from pathlib import Path

import numpy as np

from ..atomic import atomic_path
from ..errors import FileFormatError, InputError

KEY_FILE = "key"
_STATE = ("row_sums", "col_sums", "sketch", "probes", "seed")
#: ... and those of the sampled rows of F behind the per-solve error figure (hfrad.solve.samples), when kept
_SAMPLES = ("sample_index", "smooth_index", "sample_rows", "sample_reflectance", "sample_exact", "sample_seed",
            "smooth_products")
_NEAR = ("near_rows", "near_cols", "near_values")


def open_folder(folder: str | os.PathLike, key: str) -> set[int]:
    """Create ``folder`` for a run with ``key``, or check an existing one; returns the saved nodes.

    Raises
    ------
    InputError
        The folder is a file, or belongs to another scene or other parameters.
    """
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise InputError(f"{folder}: the Dask checkpoint is a folder, but this is a file (a checkpoint of the "
                         "in-process path?); delete it or choose another name")
    folder.mkdir(parents=True, exist_ok=True)
    key_file = folder / KEY_FILE
    if key_file.exists():
        if key_file.read_text().strip() != key:
            raise InputError(f"{folder}: checkpoint was made for another scene or other parameters; "
                             "delete it to start over")
    else:
        with atomic_path(key_file) as tmp:
            tmp.write_text(key + "\n")
    return {int(p.name[5:-7]) for p in folder.glob("node-*.sha256")}


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 22), b""):
            h.update(chunk)
    return h.hexdigest()


def save_part(folder: str | os.PathLike, node_id: int, part) -> None:
    """Write ``part`` (its node, statistics, near entries and records) as node ``node_id``."""
    folder = Path(folder)
    node = part.node
    arrays = {"U": node.U, "s": node.s, "V": node.V,
              "scalars": np.array([node.level, node.norm2, node.discarded2, node.slack2], np.float64),
              "records": np.array(json.dumps(part.records))}
    if part.stats is not None:
        arrays.update({f"stats_{k}": np.asarray(part.stats[k]) for k in _STATE + _SAMPLES if k in part.stats})
    if part.near is not None:
        arrays.update({k: part.near[k] for k in _NEAR})
    npz = folder / f"node-{node_id}.npz"
    with atomic_path(npz, suffix=".npz") as tmp:
        np.savez(tmp, **arrays)
    with atomic_path(folder / f"node-{node_id}.sha256") as tmp:
        tmp.write_text(_sha256(npz) + "\n")


def load_part(folder: str | os.PathLike, node_id: int):
    """Read node ``node_id`` back as (node, stats, near, records); FileFormatError if it is damaged."""
    from ..lowrank.hf import _Node

    folder = Path(folder)
    npz = folder / f"node-{node_id}.npz"
    want = (folder / f"node-{node_id}.sha256").read_text().strip()
    if not npz.exists() or _sha256(npz) != want:
        raise FileFormatError(f"{npz}: checksum mismatch (a damaged checkpoint part); delete {folder} to start over")
    with np.load(npz, allow_pickle=False) as f:
        level, norm2, discarded2, slack2 = (float(x) for x in f["scalars"])
        node = _Node(int(level), f["U"], f["s"], f["V"], norm2, discarded2, slack2)
        stats = {k: f[f"stats_{k}"] for k in _STATE} if "stats_sketch" in f else None
        if stats is not None:
            stats["probes"], stats["seed"] = int(stats["probes"]), int(stats["seed"])
            stats.update({k: f[f"stats_{k}"] for k in _SAMPLES if f"stats_{k}" in f})
        near = {k: f[k] for k in _NEAR} if "near_rows" in f else None
        records = json.loads(str(f["records"]))
    return node, stats, near, records


def drop_part(folder: str | os.PathLike, node_id: int) -> None:
    """Delete node ``node_id``'s files (its parent is saved): checksum first, so a half-deleted part is not 'saved'."""
    for suffix in (".sha256", ".npz"):
        try:
            (Path(folder) / f"node-{node_id}{suffix}").unlink()
        except FileNotFoundError:
            pass


def remove_folder(folder: str | os.PathLike) -> None:
    """Delete a finished run's checkpoint folder."""
    shutil.rmtree(folder, ignore_errors=True)
