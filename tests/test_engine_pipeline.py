"""The in-process form-factor pipeline: kernel columns between ray batches, a second Embree thread
when the kernel is done, and the same blocks, to the bit, as computing each block alone."""

from __future__ import annotations

import threading

import numpy as np
import pytest

import hfrad.formfactors.engine as engine_module
import hfrad.formfactors.visibility as visibility_module
from hfrad.formfactors.engine import FormFactorEngine
from hfrad.resources import numba_loops_at_once
from hfrad.scene.builtin import cornell_box
from hfrad.scene.patches import subdivide
from hfrad.scene.zorder import zorder_permutation


@pytest.fixture(scope="module")
def scene():
    return subdivide(cornell_box(), patches=400)


@pytest.fixture
def small_batches(monkeypatch):
    """Many ray batches a block and kernel chunks of a few columns: every interleaving is exercised."""
    monkeypatch.setattr(visibility_module, "RAY_BATCH", 32768)
    monkeypatch.setattr(engine_module, "_KERNEL_STEP_SECONDS", 1e-3)


def _requests(order):
    """Blocks of uneven widths, two with rows left to the caller (the reciprocity copy's skip)."""
    return [order[:80], (order[80:180], slice(0, 80)), order[180:200], (order[200:], slice(30, 150))]


@pytest.mark.parametrize("ahead", [True, False])
def test_pipelined_blocks_equal_blocks_computed_alone(scene, small_batches, ahead):
    order = zorder_permutation(scene.centroids)
    eng = FormFactorEngine(scene)
    eng.block(order[:2], order[:2])  # a parallel loop has run: numba's threading layer is known
    rays_before = eng.rays
    kernel_calls = []
    kernel = eng._kernel
    eng._kernel = lambda rows, cols: kernel_calls.append(threading.current_thread().name) or kernel(rows, cols)
    threads = []
    cast = eng.visibility.cast
    eng.visibility.cast = lambda job: threads.append(threading.current_thread().name) or cast(job)
    got = [F.copy() for F in eng.iter_blocks(order, _requests(order), ahead=ahead)]
    rays = eng.rays - rays_before
    eng.close()
    alone = FormFactorEngine(scene)
    for F, item in zip(got, _requests(order)):
        cols, skip = item if isinstance(item, tuple) else (item, None)
        keep = np.ones(len(order), bool)
        if skip is not None:
            keep[skip] = False
        np.testing.assert_array_equal(F[keep], alone.block(order[keep], cols))
    assert rays == alone.rays  # the same rays, each cast once
    alone.close()
    assert len(kernel_calls) > 3 * len(got) + 1   # the kernel came in column chunks
    # ... computed in the pipeline's own thread where numba allows two threads' parallel loops
    threaded = ahead and numba_loops_at_once()
    assert set(kernel_calls[1:]) == {"hfrad-formfactors" if threaded else threading.current_thread().name}
    # both Embree threads cast batches (the second one once this thread has no kernel left)
    assert {name.rsplit("_", 1)[0] for name in threads} == {"hfrad-embree", "hfrad-embree-tail"}


@pytest.mark.parametrize("ahead", [True, False])
def test_a_consumer_that_stops_early_leaves_the_engine_usable(scene, small_batches, ahead):
    order = zorder_permutation(scene.centroids)
    eng = FormFactorEngine(scene)
    blocks = eng.iter_blocks(order, _requests(order), ahead=ahead)
    first = next(blocks).copy()
    blocks.close()  # rays of later blocks may be in flight: they are waited for, not left running
    again = next(eng.iter_blocks(order, _requests(order)))
    np.testing.assert_array_equal(again, first)
    eng.close()


def test_an_error_in_the_pipeline_reaches_the_caller(scene):
    order = zorder_permutation(scene.centroids)
    eng = FormFactorEngine(scene)
    eng.block(order[:2], order[:2])

    def requests():
        yield order[:50]
        raise RuntimeError("the column sets failed")

    with pytest.raises(RuntimeError, match="the column sets failed"):
        list(eng.iter_blocks(order, requests()))   # from the pipeline's thread, or this one
    np.testing.assert_array_equal(next(eng.iter_blocks(order, [order[:50]])), eng.block(order, order[:50]))
    eng.close()
