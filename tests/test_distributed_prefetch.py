"""The near-field LUs prefetched in the client (hfrad.solve.prefetch): the same solver object as the
plain in-process assembly, used only for the very calls it was made for."""

from __future__ import annotations

import numpy as np
import pytest

from hfrad import DaskBackend, LocalBackend, PrecomputeOptions
from hfrad.distributed import connect
from hfrad.solve.prefetch import NearPrefetch, channel_scales
from hfrad.pipeline import factorize
from hfrad.scene.load import load_scene
from hfrad.precompute.assemble import assemble
from hfrad.precompute.options import plan_precompute
from hfrad.solve.nearfield import InProcess

EPS = 0.02
NEAR = 32


@pytest.fixture(scope="module")
def parts():
    """A 600-patch Cornell box factored locally, and what its assembly step takes (options, factors,
    statistics, near entries)."""
    scene = load_scene("cornell", patches=600)
    fac = factorize(scene, eps=EPS, near_field=NEAR, backend=LocalBackend(reciprocity=False),
                    options=PrecomputeOptions(block_size=64))
    options = plan_precompute(scene, EPS, near_field=NEAR, options=PrecomputeOptions(block_size=64),
                              reciprocity=False)
    n = scene.n_patches
    N = fac.N.tocoo()
    near = {"near_rows": N.row.astype(np.int64), "near_cols": N.col.astype(np.int64), "near_values": N.data}
    return scene, options, fac, near, n


def _same(a, b):
    assert type(a) is type(b) and a.rank == b.rank
    Za, Zb = (np.asarray(getattr(x.Z, "codes", x.Z)) for x in (a, b))
    assert np.array_equal(Za, Zb)
    assert np.array_equal(a.capacitance_inv, b.capacitance_inv)


def test_channel_scales_are_the_assemblys(parts):
    scene, options, fac, near, n = parts
    distinct, d = channel_scales(scene.reflectance, options.perm)
    assert distinct == fac.distinct_channels and len(distinct) > 1      # the Cornell box's walls are coloured
    for c in distinct:
        assert np.array_equal(d[c], fac._D[:, c])


def _assembled_with_prefetch(parts, prefetch_near):
    """The assembly with LUs prefetched from ``prefetch_near``, the plain one, and the prefetch's hits."""
    scene, options, fac, near, n = parts
    plain = assemble(scene, options, fac.lowrank, fac.stats, near, runner=InProcess())
    pre = NearPrefetch(prefetch_near, n, scene.reflectance, options.perm, options.dtype)
    try:
        got = assemble(scene, options, fac.lowrank, fac.stats, near, runner=pre.runner())
    finally:
        pre.close()
    return got, plain, pre.hits


def test_prefetched_assembly_is_the_plain_one(parts):
    """Every distinct channel's LU comes from the prefetch, and Z and K^-1 are bit for bit the plain ones."""
    scene, options, fac, near, n = parts
    got, plain, hits = _assembled_with_prefetch(parts, near)
    assert hits == len(plain.distinct_channels)
    _same(got, plain)
    B, B_plain = got.solve(scene.emission), plain.solve(scene.emission)
    assert np.array_equal(B, B_plain)


def test_channels_after_the_first_are_factored_at_once(parts, monkeypatch):
    """The channels after the first (the Cornell box has three) are factored at the same time, a thread
    each: every one of them waits at a barrier for the others before it factors (one after the other,
    the first waits alone and breaks it), and the assembly is the plain one."""
    import threading

    from hfrad.solve import prefetch

    scene, options, fac, near, n = parts
    distinct = channel_scales(scene.reflectance, options.perm)[0]
    assert len(distinct) == 3
    barrier, real = threading.Barrier(len(distinct) - 1, timeout=5), prefetch.NearPrefetch._factor

    def together(self, channel):
        if channel != distinct[0]:
            try:
                barrier.wait()
            except threading.BrokenBarrierError:     # one after the other: it waited alone
                pass
        return real(self, channel)

    monkeypatch.setattr(prefetch.NearPrefetch, "_factor", together)
    got, plain, hits = _assembled_with_prefetch(parts, near)
    assert hits == 3 and not barrier.broken
    _same(got, plain)


def test_prefetch_of_another_near_field_is_not_used(parts):
    """A prefetch made from other near entries (one value changed) is ignored: the assembly factors
    its own N and the result is the plain one."""
    near = parts[3]
    other = dict(near, near_values=near["near_values"].copy())
    other["near_values"][0] *= 0.5
    got, plain, hits = _assembled_with_prefetch(parts, other)
    assert hits == 0
    _same(got, plain)


def test_two_workers_prefetch_beside_the_panelled_top(parts):
    """LocalCluster(2) (in-process workers), near field on, a panelled root: the run prefetches every
    distinct channel's LU, and gives what the run without the prefetch gives."""
    scene, options, fac, near, n = parts
    with connect(workers=2, processes=False) as cluster:
        runs = [factorize(scene, eps=EPS, near_field=NEAR, backend=DaskBackend(scheduler=cluster),
                          options=PrecomputeOptions(block_size=64)) for _ in range(1)]
        from hfrad.distributed import DaskTuning, factorize_distributed

        opts = plan_precompute(scene, EPS, near_field=NEAR, options=PrecomputeOptions(block_size=64))
        off = factorize_distributed(scene, opts, DaskBackend(scheduler=cluster), tuning=DaskTuning(near_prefetch=False))
    on = runs[0]
    assert on.lowrank.info["panelled_merges"] > 0
    assert on.lowrank.info["near_prefetched"] == len(on.distinct_channels)
    assert "near_prefetched" not in off.lowrank.info
    assert on.rank == off.rank
    B, B_off = on.solve(scene.emission), off.solve(scene.emission)
    # separate runs: merges on other BLAS threads round apart (float32 factors), nothing more
    assert np.abs(B - B_off).max() <= 1e-5 * np.abs(B_off).max()


def test_close_without_waiting_leaves_the_lu_in_flight(parts, monkeypatch):
    """A run given up (Ctrl-C, an error) closes the prefetch with ``wait=False``: it returns at once, where
    ``close()`` waits for the LU in flight (SuperLU cannot be interrupted), which finishes on its daemon thread
    (the interpreter's exit joins it)."""
    import threading
    import time

    from hfrad.solve import prefetch

    scene, options, fac, near, n = parts
    real = prefetch.channel_solver
    started = threading.Event()

    def slow(*args):
        started.set()
        time.sleep(1.5)
        return real(*args)

    monkeypatch.setattr(prefetch, "channel_solver", slow)
    seconds = []
    for wait in (False, True):
        started.clear()
        pre = NearPrefetch(near, n, scene.reflectance, options.perm, options.dtype)
        assert started.wait(10)
        t = time.perf_counter()
        pre.close(wait=wait)
        seconds.append(time.perf_counter() - t)
        assert pre._thread.is_alive() != wait and pre._thread.daemon
    assert seconds[0] < 0.2 < 1.0 < seconds[1], seconds
