"""Checkpoints of a running HF stream, so an interrupted precompute resumes.

The state of :class:`~hfrad.factorize.hf.HFStream` is its binary-counter stack
(O(log m) factor pairs) plus counters; saving it lets a long precomputation
resume after the last saved block without redoing finished blocks.
"""

from __future__ import annotations

import json
import os

import numpy as np

from ..errors import InputError
from ..atomic import atomic_path
from .hf import HFStream, _Node

CHECKPOINT_VERSION = 1


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

    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        f.attrs["version"] = CHECKPOINT_VERSION
        f.attrs["key"] = key
        f.attrs["params"] = json.dumps(_params(stream))
        f.attrs["blocks_done"] = stream.blocks_done
        f.attrs["columns_done"] = stream.columns_done
        f.attrs["times"] = json.dumps([stream.time_leaf, stream.time_merge])
        f.create_dataset("leaf_ranks", data=np.asarray(stream.leaf_ranks, np.int64))
        for i, node in enumerate(stream.stack):
            g = f.create_group(f"node{i}")
            g.attrs["level"], g.attrs["norm2"] = node.level, node.norm2
            g.attrs["discarded2"], g.attrs["slack2"] = node.discarded2, node.slack2
            g.create_dataset("U", data=node.U)
            g.create_dataset("s", data=node.s)
            g.create_dataset("V", data=node.V)
        f.attrs["nodes"] = len(stream.stack)
        for name, arr in stream.extra.items():
            f.create_dataset(f"extra/{name}", data=arr)


def load_checkpoint(path: str | os.PathLike, key: str = "") -> HFStream:
    """Rebuild a stream from a checkpoint; ValueError if it belongs to another input."""
    import h5py

    with h5py.File(path, "r") as f:
        if int(f.attrs.get("version", -1)) != CHECKPOINT_VERSION:
            raise InputError(f"{path}: checkpoint version {f.attrs.get('version')} is not "
                             f"{CHECKPOINT_VERSION}; delete it to start over")
        if str(f.attrs["key"]) != key:
            raise InputError(f"{path}: checkpoint was made for another scene or other parameters; "
                             "delete it to start over")
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
    return stream

