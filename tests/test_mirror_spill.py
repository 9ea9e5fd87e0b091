"""Reciprocity tiles beyond the memory band spilled to a scratch file: every pair computed once."""

from __future__ import annotations

import os
import warnings

import numpy as np
import pytest

import hfrad.formfactors.blocks as blocks_mod
from hfrad.errors import InputError, WriteError
from hfrad.formfactors import iter_column_blocks
from hfrad.formfactors.blocks import FormFactorEngine
from hfrad.formfactors.mirror import (MIRROR_LAG, ReciprocityMirror, ScratchDamageError, TileScratch, band_for,
                                      scratch_bytes, slot_bytes, spill_band_for)
from hfrad.scene.builtin import cornell_box
from hfrad.scene.patches import subdivide
from hfrad.scene.zorder import zorder_permutation

BLOCK = 32


def _scratch_fds() -> list[str]:
    """Open descriptors of this process that point at a scratch file (unlinked ones included)."""
    out = []
    for fd in os.listdir("/proc/self/fd"):
        try:
            target = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            continue
        if "hfrad-tiles-" in target:
            out.append(target)
    return out


def _reciprocal(n=700, seed=0):
    """F = S / A with S symmetric: A_i F_ij = A_j F_ji exactly."""
    rng = np.random.default_rng(seed)
    S = rng.random((n, n))
    S = S + S.T
    areas = rng.uniform(0.5, 2.0, n)
    return (S / areas[:, None]).astype(np.float32), areas


def _run(m, F, starts, damage=None):
    out = []
    for k in range(len(starts) - 1):
        rows = m.copied_rows(k)
        block = F[:, starts[k]:starts[k + 1]].copy()
        block[rows] = np.nan
        if damage is not None and damage[0] == k:
            m.scratch.damage(damage)
        m.fill(k, block, rows)
        m.keep(k, block)
        out.append(block)
    return np.concatenate(out, axis=1)


def test_spilled_tiles_are_bit_identical_and_leave_nothing(tmp_path):
    F, areas = _reciprocal()
    n, b, lag = F.shape[0], 50, 2
    starts = np.r_[np.arange(0, n, b), n]
    blocks = len(starts) - 1
    full = blocks - lag - 1
    memory = ReciprocityMirror(areas, starts, band=full, lag=lag)
    expected = _run(memory, F, starts)
    near = band_for(blocks, b, 4, 6 * b * b * 4, lag=lag)
    assert 0 < near < full
    slots = scratch_bytes(blocks, b, 4, near, full, lag) // slot_bytes(b, 4)
    scratch = TileScratch(tmp_path, slots, slot_bytes(b, 4))
    assert os.listdir(tmp_path) == []            # unlinked at once: nothing to leave behind
    spilled = ReciprocityMirror(areas, starts, band=full, lag=lag, near=near, scratch=scratch)
    got = _run(spilled, F, starts)
    np.testing.assert_array_equal(got, expected)     # the same bytes, wherever the tile waited
    assert spilled.copied_pairs == memory.copied_pairs == memory.possible_pairs()
    assert 0 < spilled.spilled_pairs < spilled.copied_pairs
    assert spilled.peak_bytes <= 6 * b * b * 4 < memory.peak_bytes
    assert scratch.written == scratch.read == 4 * spilled.spilled_pairs      # written once, read once
    assert not scratch.keys() and len(scratch._free) == slots               # every slot came back
    assert _scratch_fds()
    spilled.close()
    assert not _scratch_fds()


def test_damaged_tile_is_recomputed_or_refused(tmp_path):
    F, areas = _reciprocal(n=400, seed=1)
    n, b, lag = F.shape[0], 40, 1
    starts = np.r_[np.arange(0, n, b), n]
    blocks = len(starts) - 1
    full = blocks - lag - 1
    near = 1
    victim = (blocks - 1, 0)                         # kept by block 0 for the last block: on disk

    def mirror(recompute=None):
        slots = scratch_bytes(blocks, b, 4, near, full, lag) // slot_bytes(b, 4)
        return ReciprocityMirror(areas, starts, band=full, lag=lag, near=near, recompute=recompute,
                                 scratch=TileScratch(tmp_path, slots, slot_bytes(b, 4)))

    calls = []

    def recompute(rows, cols):
        calls.append((rows, cols))
        return F[rows, cols]

    m = mirror(recompute)
    got = _run(m, F, starts, damage=victim)
    assert m.repaired_tiles == 1 and calls == [(slice(0, b), slice(starts[-2], n))]
    np.testing.assert_allclose(got, F, rtol=1e-6)    # float32 F, copied in float64 then cast
    assert not np.isnan(got).any()
    m.close()
    m = mirror()
    with pytest.raises(ScratchDamageError, match="checksum"):
        _run(m, F, starts, damage=victim)
    m.close()


def test_scratch_size_formula_and_partial_bands():
    # with no memory band, the scratch peak is about n^2 s / 4 (a quarter of F): the slots are reused
    blocks, b, s = 200, 256, 4
    n = blocks * b
    full = blocks - MIRROR_LAG - 1
    need = scratch_bytes(blocks, b, s, 0, full)
    assert 0.95 * n * n * s / 4 <= need <= n * n * s / 4
    near = band_for(blocks, b, s, need // 10)
    assert scratch_bytes(blocks, b, s, near, full) < need
    assert spill_band_for(blocks, b, s, near, 1 << 62) == full
    assert spill_band_for(blocks, b, s, near, 0) == near
    part = spill_band_for(blocks, b, s, near, need // 3)
    assert near < part < full and scratch_bytes(blocks, b, s, near, part) <= need // 3


def test_missing_or_full_scratch_folder_is_refused(tmp_path):
    with pytest.raises(WriteError, match="does not exist"):
        TileScratch(tmp_path / "nope", 4, slot_bytes(16, 4))
    with pytest.raises(WriteError, match="free"):
        TileScratch(tmp_path, 1 << 40, 1 << 20)      # a pebibyte
    assert os.listdir(tmp_path) == []


@pytest.fixture(scope="module")
def box():
    scene = subdivide(cornell_box(), patches=700)
    return scene, zorder_permutation(scene.centroids)


def _F(scene, order, processes=1, **kw):
    stats = {}
    engine = FormFactorEngine(scene) if processes == 1 else None
    F = np.concatenate([b for _, _, b in iter_column_blocks(scene, BLOCK, order=order, dtype=np.float32,
                                                            engine=engine, processes=processes,
                                                            mirror_stats=stats, **kw)], axis=1)
    if engine is not None:
        engine.close()
    return F, (engine.pairs if engine is not None else None), stats


def test_spilling_pass_matches_the_all_in_memory_pass(box, tmp_path, monkeypatch):
    scene, order = box
    n = scene.n_patches
    memory, pairs_memory, stats_memory = _F(scene, order)             # small: every tile fits in memory
    assert stats_memory["near"] == stats_memory["band"] and stats_memory["scratch_bytes"] == 0
    # a memory band of 3 blocks: the rest spill
    monkeypatch.setattr(blocks_mod, "mirror_bytes", lambda *a, **k: 3 * 8 * BLOCK * BLOCK * 4)
    spilled, pairs_spilled, stats = _F(scene, order, scratch=tmp_path)
    np.testing.assert_array_equal(spilled, memory)
    assert pairs_spilled == pairs_memory                       # every pair computed once, as in memory
    assert stats["copied_pairs"] == stats["possible_pairs"] == stats_memory["copied_pairs"]
    assert stats["near"] < stats["band"] and stats["spilled_pairs"] > 0.3 * stats["copied_pairs"]
    assert os.listdir(tmp_path) == [] and not _scratch_fds()
    two = _F(scene, order, processes=2, scratch=tmp_path)[0]   # process count does not change the copies
    np.testing.assert_array_equal(two, memory)
    # no file: the far rows are computed, F equal to rounding
    off, pairs_off, stats_off = _F(scene, order, scratch=False)
    assert pairs_off > pairs_spilled and stats_off["scratch_bytes"] == 0
    np.testing.assert_allclose(off, memory, rtol=0, atol=2e-7 * memory.max())
    # a short disk: spill what fits, say so
    monkeypatch.setattr("hfrad.atomic.free_bytes", lambda folder: 2 * stats["scratch_bytes"] // 3)
    with pytest.warns(RuntimeWarning, match="copies from"):
        short, pairs_short, stats_short = _F(scene, order, scratch=tmp_path)
    assert stats_short["near"] < stats_short["band"] < stats["band"]
    assert pairs_spilled < pairs_short < pairs_off
    np.testing.assert_allclose(short, memory, rtol=0, atol=2e-7 * memory.max())
    print(f"\n{n} patches: pairs {pairs_memory} (memory band), {pairs_spilled} (spilled), {pairs_short} "
          f"(short disk), {pairs_off} (no file); {stats['scratch_bytes']} scratch bytes")


def test_abandoned_pass_leaves_no_file(box, tmp_path, monkeypatch):
    scene, order = box
    monkeypatch.setattr(blocks_mod, "mirror_bytes", lambda *a, **k: 0)
    gen = iter_column_blocks(scene, BLOCK, order=order, dtype=np.float32, scratch=tmp_path)
    for _ in range(MIRROR_LAG + 4):
        next(gen)
    assert _scratch_fds()
    gen.close()                                       # as on an error or Ctrl-C in the consumer
    assert not _scratch_fds() and os.listdir(tmp_path) == []
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(WriteError, match="does not exist"):
            next(iter_column_blocks(scene, BLOCK, order=order, scratch=tmp_path / "missing"))
        with pytest.raises(InputError, match="scratch must be a folder"):
            next(iter_column_blocks(scene, BLOCK, order=order, scratch=3))
