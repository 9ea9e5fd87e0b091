"""Dask checkpoint folders are tied to their run (issue 47, item 3).

Each part's digest names its node, the run's key and the factors' shapes; a
swapped, copied-in, foreign or junk part is refused naming the file, never
resumed; stray files in the folder are ignored.
"""

from __future__ import annotations

import hashlib
import shutil

import numpy as np
import pytest

from hfrad.distributed import store, tasks
from hfrad.errors import FileFormatError
from hfrad.lowrank.hf import _Node


def _part(seed: int, rows: int = 30) -> tasks.Part:
    rng = np.random.default_rng(seed)
    node = _Node(1, rng.standard_normal((rows, 4)), np.arange(4.0)[::-1].copy(), rng.standard_normal((12, 4)),
                 5.0, 0.25, 0.5)
    return tasks.Part(node, [{"kind": "leaf", "node": seed}], None, None)


@pytest.fixture
def folder(tmp_path):
    f = tmp_path / "ckpt"
    assert store.open_folder(f, "run-A") == set()
    store.save_part(f, 3, _part(3))
    store.save_part(f, 5, _part(5, rows=28))
    return f


def _swap(a, b):
    tmp = a.with_name("tmp")
    a.rename(tmp), b.rename(a), tmp.rename(b)


def test_an_honest_folder_resumes(folder):
    assert store.open_folder(folder, "run-A") == {3, 5}
    node = store.load_part(folder, 5)[0]
    assert np.array_equal(node.U, _part(5, rows=28).node.U)


def test_parts_swapped_with_their_digests_are_refused(folder):
    """Main resumed these silently (radiosity off 0.25-0.34% in the issue's run)."""
    for suffix in (".npz", ".sha256"):
        _swap(folder / f"node-3{suffix}", folder / f"node-5{suffix}")
    with pytest.raises(FileFormatError, match=r"node-[35]\.sha256.*not node"):
        store.open_folder(folder, "run-A")
    with pytest.raises(FileFormatError, match="node-3"):
        store.load_part(folder, 3)


def test_a_node_replaced_by_another_nodes_files_is_refused(folder):
    for suffix in (".npz", ".sha256"):
        shutil.copy(folder / f"node-5{suffix}", folder / f"node-3{suffix}")
    with pytest.raises(FileFormatError, match=r"node-3\.sha256"):
        store.open_folder(folder, "run-A")


def test_a_part_of_another_run_is_refused(folder, tmp_path):
    other = tmp_path / "other"
    store.open_folder(other, "run-B")
    store.save_part(other, 3, _part(3))
    for suffix in (".npz", ".sha256"):
        shutil.copy(other / f"node-3{suffix}", folder / f"node-3{suffix}")
    with pytest.raises(FileFormatError, match=r"node-3\.sha256.*another run"):
        store.open_folder(folder, "run-A")


def test_junk_with_a_matching_plain_checksum_is_refused(folder):
    """Main: a junk .npz with its SHA-256 beside it raised a traceback from the npz reader."""
    junk = folder / "node-3.npz"
    junk.write_bytes(b"not an npz at all")
    (folder / "node-3.sha256").write_text(hashlib.sha256(junk.read_bytes()).hexdigest() + "\n")
    with pytest.raises(FileFormatError, match=r"node-3\.sha256"):
        store.open_folder(folder, "run-A")
    with pytest.raises(FileFormatError, match=r"node-3"):
        store.load_part(folder, 3)


def test_stray_files_are_ignored(folder):
    """Main: 'node-x.sha256' in the folder raised ValueError from int()."""
    for name in ("node-x.sha256", "node-.sha256", "notes.txt", "node-3.sha256.bak"):
        (folder / name).write_text("stray\n")
    (folder / "sub").mkdir()
    assert store.open_folder(folder, "run-A") == {3, 5}
