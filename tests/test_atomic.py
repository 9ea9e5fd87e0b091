"""The one atomic writer: complete files or none, with the mode the user's umask gives."""

from __future__ import annotations

import os
import stat

import numpy as np
import pytest

from hfrad.atomic import atomic_path


@pytest.fixture
def umask_027():
    old = os.umask(0o027)
    yield 0o027
    os.umask(old)


def _mode(path) -> int:
    return stat.S_IMODE(os.stat(path).st_mode)


def test_complete_file_with_umask_mode(tmp_path, umask_027):
    target = tmp_path / "a.bin"
    with atomic_path(target) as tmp:
        assert tmp.parent == tmp_path and tmp != target
        tmp.write_bytes(b"hello")
    assert target.read_bytes() == b"hello"
    assert _mode(target) == 0o666 & ~umask_027          # 0640, not mkstemp's 0600
    assert [p.name for p in tmp_path.iterdir()] == ["a.bin"]


def test_failure_leaves_nothing_and_keeps_old_file(tmp_path):
    target = tmp_path / "a.bin"
    target.write_bytes(b"old")
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_bytes(b"half")
            raise RuntimeError("disk full")
    assert target.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["a.bin"]


def test_every_writer_follows_the_umask(tmp_path, umask_027):
    """Exports, pictures, .hfr files and checkpoints all go through the helper."""
    import hfrad
    from hfrad.lowrank.hf import HFStream
    from hfrad.lowrank.streaming import save_checkpoint
    from hfrad.io.export import write_radiosity
    from hfrad.render.image import save_png
    from hfrad.scene.builtin import furnace
    from hfrad.scene.patches import subdivide

    scene = subdivide(furnace(), patches=60)
    n = scene.n_patches
    B = np.full((n, 3), 2.0)
    write_radiosity(scene, B, tmp_path / "b.ply")
    write_radiosity(scene, B, tmp_path / "b.npz")
    save_png(np.zeros((4, 5, 3), np.uint8), tmp_path / "c.png")
    stream = HFStream(n, 2, eps=0.1)
    save_checkpoint(stream, tmp_path / "s.partial")
    F = np.full((n, n), 1.0 / n)
    fac = hfrad.factorize_matrix(F, np.full((n, 3), 0.5), eps=0.05, block_size=32)
    hfrad.save(fac, tmp_path / "f.hfr")
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == ["b.npz", "b.ply", "c.png", "f.hfr", "s.partial"]
    for name in names:
        assert _mode(tmp_path / name) == 0o640, name
