"""Occlusion in packets (formfactors/raycast.py) answers exactly as embreex's one-ray ``run``.

The packet path builds its own Embree scene with the library embreex ships and
casts rtcOccluded16, 8 or 4 (the widest the CPU runs natively) from numba; embreex casts rtcOccluded1 per ray. Both must
say the same for every ray (random rays over random triangles, negative and
zero lengths included), and the form factors computed with either must be the
same bit for bit: on the built-in Cornell box (all of F, probes and both
refinement rounds) and on a clustered Sponza (three column blocks).

Observed by hand (too slow for a test): the 28,339,901 rays of two column blocks of a
10,057-patch Sponza answer alike in both; with Embree's default multi-threaded
BVH build (not the one-thread build embreex uses) 59 of them did not.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from hfrad.formfactors.engine import FormFactorEngine
from hfrad.formfactors.raycast import RayCaster
from hfrad.scene.builtin import cornell_box
from hfrad.scene.patches import subdivide
from hfrad.scene.zorder import zorder_permutation

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "scenes"
needs_shared = pytest.mark.skipif(not SHARED.is_dir(),
                                  reason="../shared/scenes is absent (only in the developers' checkout)")


def _embreex_answer(caster: RayCaster, o, d, t) -> np.ndarray:
    """embreex's own one-ray-at-a-time answer, in the caster's frame (what occluded() did before packets)."""
    oo = caster._in_frame(o)
    tt = np.ascontiguousarray(np.asarray(t, np.float64) / caster.unit, np.float32)
    return caster._scene.run(oo, np.ascontiguousarray(d, np.float32), query="OCCLUDED", dists=tt) >= 0


@pytest.mark.parametrize("threads", [1, 2])
def test_packets_match_embreex_on_random_rays(threads):
    rng = np.random.default_rng(7)
    tri = rng.random((400, 3, 3)) * 10.0 + 100.0  # off the origin: the caster's frame is exercised too
    caster = RayCaster(tri.reshape(-1, 3), np.arange(1200).reshape(-1, 3), threads=threads)
    assert caster._packets is not None, "the Embree library shipped with embreex was not found"
    n = 140_005  # not a multiple of 16: the last packet is partly valid
    o = rng.random((n, 3)) * 14.0 + 98.0
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    t = rng.random(n) * 20.0 - 3.0  # some negative (Embree ignores the ray; embreex calls it blocked)
    t[:50] = 0.0
    got = caster.occluded(o, d, t)
    want = _embreex_answer(caster, o, d, t)
    assert 0.2 < want[t > 0].mean() < 0.8  # both answers occur
    np.testing.assert_array_equal(got, want)
    caster.close()


@pytest.mark.parametrize("width", [4, 8, 16])
def test_every_native_packet_width_matches_embreex(width):
    """Each packet size Embree runs natively here answers as embreex does. A size the CPU lacks is never
    used: rtcOccluded16 on a CPU without AVX-512 corrupted the heap (glibc aborted the process)."""
    from hfrad.formfactors.raycast import _NATIVE_PACKETS

    rng = np.random.default_rng(11)
    tri = rng.random((300, 3, 3)) * 10.0
    caster = RayCaster(tri.reshape(-1, 3), np.arange(900).reshape(-1, 3), threads=1)
    assert caster._packets is not None, "the Embree library shipped with embreex was not found"
    native = [k for k, prop in _NATIVE_PACKETS
              if caster._packets._lib.rtcGetDeviceProperty(caster._packets.device, prop) > 0]
    assert caster._packets.width == max(native)
    if width not in native:
        caster.close()
        pytest.skip(f"Embree runs no packets of {width} natively on this CPU (native: {native})")
    caster._packets.width = width
    n = 20_003  # not a multiple of any width: the last packet is partly valid
    o = rng.random((n, 3)) * 12.0 - 1.0
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    t = rng.random(n) * 15.0 - 2.0
    got = caster.occluded(o, d, t)
    want = _embreex_answer(caster, o, d, t)
    assert 0.2 < want[t > 0].mean() < 0.8
    np.testing.assert_array_equal(got, want)
    caster.close()


def _engine_F(scene, rows, col_sets, packets: bool) -> list[np.ndarray]:
    eng = FormFactorEngine(scene)
    if not packets:
        eng.visibility.caster._packets = None  # embreex's run, one ray at a time
    out = [F.copy() for F in eng.iter_blocks(rows, col_sets)]
    rays = eng.rays
    eng.close()
    return out, rays


def test_cornell_F_same_with_packets():
    scene = subdivide(cornell_box(), patches=700)
    order = zorder_permutation(scene.centroids)
    n = scene.n_patches
    cols = [order[s:s + 128] for s in range(0, n, 128)]
    F0, rays0 = _engine_F(scene, order, cols, packets=False)
    F1, rays1 = _engine_F(scene, order, cols, packets=True)
    assert rays0 == rays1 > 100_000
    for a, b in zip(F0, F1):
        np.testing.assert_array_equal(a, b)
    assert any((a > 0).sum() < a.size * 0.99 for a in F1)  # some pairs are shadowed: rays mattered


@pytest.mark.slow   # the Cornell box's test of the same property runs by default
@needs_shared
def test_clustered_sponza_F_same_with_packets():
    from hfrad.scene.cluster import cluster
    from hfrad.scene.load import load_scene

    scene = cluster(load_scene(SHARED / "sponza-dabrovic" / "sponza.obj", emit={"ceiling": 1.0}), patches=1000)
    n = scene.n_patches
    order = zorder_permutation(scene.centroids)
    cols = [order[s:s + 64] for s in (0, n // 2, n - 64)]
    F0, rays0 = _engine_F(scene, order, cols, packets=False)
    F1, rays1 = _engine_F(scene, order, cols, packets=True)
    assert rays0 == rays1 > 100_000
    for a, b in zip(F0, F1):
        np.testing.assert_array_equal(a, b)
