"""Checkpoints of a Dask precompute: the finished subtrees' factors in a folder, with checksums.

Each leaf or merge task saves its :class:`~hfrad.distributed.tasks.Part` as
``node-<id>.npz`` (atomically) and then ``node-<id>.sha256``, the part's digest: a
JSON line naming the node, the run's key (its SHA-256), the factors' shapes and the npz's
SHA-256; the digest file marks the part complete. The npz holds the node id and the key as
well, so a part of another run or another node, two parts swapped with their digests, or a
damaged or foreign file is refused naming the file, never resumed (files that are not
``node-<id>.*`` are ignored). A merge deletes its children's files
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
import re
import shutil
import zipfile
from pathlib import Path

import numpy as np

from ..atomic import atomic_path
from ..errors import FileFormatError, InputError

KEY_FILE = "key"
_STATE = ("row_sums", "col_sums", "sketch", "probes", "seed")
#: The exact sampled rows of the per-solve figure (hfrad.solve.samples), in parts written since 2026-12-06.
_SAMPLE_STATE = ("sample_index", "smooth_index", "sample_rows", "sample_span", "sample_reflectance",
                 "sample_exact", "sample_seed", "smooth_products", "sample_bounce", "sample_dual_index",
                 "sample_dual_bounce", "sample_gain_vector", "sample_gain_product")
#: The sampled far field's certificate and held-out check (far_field="sampled").
_FAR_STATE = ("far_index", "far_q", "far_holdout_q")
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
    saved = {int(m.group(1)) for m in (_DIGEST_NAME.match(p.name) for p in folder.iterdir()) if m}
    for node_id in saved:
        _check_digest(folder, node_id, key)
    return saved


_DIGEST_NAME = re.compile(r"^node-(\d{1,12})\.sha256$")


def _key_hash(key: str) -> str:
    return hashlib.sha256(key.encode()).hexdigest()


def _digest_text(node_id: int, key: str, shapes: dict, npz_sha: str) -> str:
    return json.dumps({"node": node_id, "key": _key_hash(key), "shapes": shapes, "sha256": npz_sha},
                      sort_keys=True) + "\n"


def _check_digest(folder: Path, node_id: int, key: str) -> dict:
    """The digest of node ``node_id``, checked against the run's key and the npz's bytes."""
    path = folder / f"node-{node_id}.sha256"
    npz = folder / f"node-{node_id}.npz"
    fix = f"; delete {folder} to start over"
    try:
        d = json.loads(path.read_text(encoding="utf-8"))
        ok = isinstance(d, dict) and isinstance(d.get("shapes"), dict) and isinstance(d.get("sha256"), str)
    except (OSError, UnicodeDecodeError, ValueError):
        ok = False
    if not ok:
        raise FileFormatError(f"{path}: not a checkpoint part's digest (damaged, foreign, or from an older "
                              f"hfrad){fix}")
    if d.get("node") != node_id or d.get("key") != _key_hash(key):
        raise FileFormatError(f"{path}: the digest is of node {d.get('node')!r}"
                              + ("" if d.get("key") == _key_hash(key) else " of another run")
                              + f", not node {node_id} of this run (files swapped or copied in){fix}")
    if not npz.is_file() or _sha256(npz) != d["sha256"]:
        raise FileFormatError(f"{npz}: checksum mismatch (a damaged, swapped or missing checkpoint part){fix}")
    return d


def _run_key(folder: Path) -> str:
    try:
        return (folder / KEY_FILE).read_text().strip()
    except OSError as exc:
        raise FileFormatError(f"{folder / KEY_FILE}: cannot read the checkpoint's run key ({exc})") from None


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
        arrays.update({f"stats_{k}": np.asarray(part.stats[k]) for k in _STATE + _SAMPLE_STATE + _FAR_STATE
                       if k in part.stats})
    if part.near is not None:
        arrays.update({k: part.near[k] for k in _NEAR})
    key = _run_key(folder)
    arrays.update({"node_id": np.array(node_id, np.int64), "run_key": np.array(_key_hash(key))})
    npz = folder / f"node-{node_id}.npz"
    with atomic_path(npz, suffix=".npz") as tmp:
        np.savez(tmp, **arrays)
    shapes = {k: list(np.shape(arrays[k])) for k in ("U", "s", "V")}
    with atomic_path(folder / f"node-{node_id}.sha256") as tmp:
        tmp.write_text(_digest_text(node_id, key, shapes, _sha256(npz)))


def load_part(folder: str | os.PathLike, node_id: int):
    """Read node ``node_id`` back as (node, stats, near, records); FileFormatError if it is damaged."""
    from ..lowrank.hf import _Node

    folder = Path(folder)
    npz = folder / f"node-{node_id}.npz"
    key = _run_key(folder)
    digest = _check_digest(folder, node_id, key)
    try:
        with np.load(npz, allow_pickle=False) as f:
            if int(f["node_id"]) != node_id or str(f["run_key"]) != _key_hash(key):
                raise ValueError("it holds another node or run")
            level, norm2, discarded2, slack2 = (float(x) for x in f["scalars"])
            node = _Node(int(level), f["U"], f["s"], f["V"], norm2, discarded2, slack2)
            stats = {k: f[f"stats_{k}"] for k in _STATE + _SAMPLE_STATE + _FAR_STATE if f"stats_{k}" in f} \
                if "stats_sketch" in f else None
            if stats is not None:
                stats["probes"], stats["seed"] = int(stats["probes"]), int(stats["seed"])
            near = {k: f[k] for k in _NEAR} if "near_rows" in f else None
            records = json.loads(str(f["records"]))
    except (OSError, ValueError, KeyError, TypeError, zipfile.BadZipFile) as exc:
        raise FileFormatError(f"{npz}: not a readable checkpoint part of node {node_id} ({exc}); "
                              f"delete {folder} to start over") from None
    shapes = {"U": list(node.U.shape), "s": list(node.s.shape), "V": list(node.V.shape)}
    if shapes != digest["shapes"] or node.U.ndim != 2 or node.U.shape[1:] != node.s.shape \
            or node.V.shape[1:] != node.s.shape:
        raise FileFormatError(f"{npz}: factors of shapes {shapes} do not match the part's digest "
                              f"{digest['shapes']}; delete {folder} to start over")
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
