"""Benchmark: where a form-factor block's time goes, and rays per second against raw Embree.

One process, the pipeline's ray budget (eps/4), a few Z-ordered column blocks of 256:

- ``pipelined``: ``FormFactorEngine.iter_blocks`` (Embree in its thread, the kernel and
  the probes in this one), wall seconds, rays, seconds inside Embree calls, kernel seconds;
- ``serial``: the same blocks one after the other (``block``), with the time of each
  numba step around the rays (culling, probe states, decisions, segment preparation,
  reductions) summed over the blocks;
- ``raw``: the rays of the first two blocks again in one call of embreex's ``run``
  (one ray at a time: "raw Embree") and in one call of hfrad's packet loop
  (``raycast._occluded``, 16 rays a packet), best of 2.

``share_of_raw`` = rays per wall second / raw embreex rays per second. Run it with
``PYTHONPATH=<tree>/src`` to measure another tree (the packet line is skipped where
the tree has no packet loop). Not collected by pytest.

    python benchmarks/bench_rays.py --scene cornell --patches 10000 --blocks 6
    python benchmarks/bench_rays.py --scene /work/shared/scenes/sponza-dabrovic/sponza.obj --patches 10000
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np


def measure(source: str, patches: int, blocks: int, eps: float, modes: str) -> dict:
    import hfrad
    from hfrad.formfactors import probing as P
    from hfrad.formfactors import visibility as V
    from hfrad.formfactors.budget import ray_budget
    from hfrad.formfactors.engine import FormFactorEngine
    from hfrad.scene.zorder import zorder_permutation

    scene = hfrad.load_scene(source, patches=patches)
    n = scene.n_patches
    order = zorder_permutation(scene.centroids)
    starts = list(range(0, n, max(256, n // blocks)))[:blocks]
    col_sets = [order[s:s + 256] for s in starts]
    eng = FormFactorEngine(scene, ray_budget=ray_budget(scene, 0.25 * eps))
    eng.block(order[:64], order[:64])  # numba caches loaded outside the timings
    vis = eng.visibility
    out: dict = {"scene": source, "n_patches": n, "blocks": len(col_sets), "loadavg_start": os.getloadavg()}

    def reset():
        vis.rays_cast = vis.rays_probe = vis.rays_refined = 0
        vis.embree_seconds = eng.kernel_seconds = 0.0

    if "pipe" in modes:
        reset()
        t = time.perf_counter()
        for _ in eng.iter_blocks(order, col_sets):
            pass
        wall = time.perf_counter() - t
        out["pipelined"] = {"wall": wall, "rays": vis.rays_cast, "embree_s": vis.embree_seconds,
                            "kernel_s": eng.kernel_seconds}
    if "serial" in modes:
        steps: dict = {}

        def timed(obj, name, key):
            f = getattr(obj, name)

            def g(*a, **k):
                t0 = time.perf_counter()
                r = f(*a, **k)
                steps[key] = steps.get(key, 0.0) + time.perf_counter() - t0
                return r
            setattr(obj, name, g)
            return f

        saved = [(mod, name, timed(mod, name, key)) for mod, name, key in (
            (V, "_needs_rays", "cull"), (P, "_pair_states", "probe states"), (P, "_decide", "probe decisions"),
            (P, "_probe", "probes incl. Embree"), (V, "valid_rays", "valid rays"), (V, "fill_rays", "fill rays"),
            (V, "_partial_and_large", "second-round test"), (V, "_scale_by_visibility", "scale F"))]
        reset()
        t = time.perf_counter()
        for cols in col_sets:
            eng.block(order, cols)
        wall = time.perf_counter() - t
        for mod, name, f in saved:
            setattr(mod, name, f)
        out["serial"] = {"wall": wall, "rays": vis.rays_cast, "embree_s": vis.embree_seconds,
                         "kernel_s": eng.kernel_seconds, "probe_rays": vis.rays_probe,
                         "second_round_rays": vis.rays_refined, "steps_s": steps}
    # the same rays in one call
    got: list = []
    caster = vis.caster
    plain = caster.occluded
    caster.occluded = lambda o, d, t: (got.append((np.array(o), np.array(d), np.array(t))), plain(o, d, t))[1]
    for cols in col_sets[:2]:
        eng.block(order, cols)
    caster.occluded = plain
    o, d, t = (np.ascontiguousarray(np.concatenate([g[k] for g in got])) for k in range(3))
    best = min(_seconds(lambda: caster._scene.run(o, d, query="OCCLUDED", dists=t)) for _ in range(2))
    out["raw"] = {"rays": len(t), "seconds": best, "rays_per_s": len(t) / best}
    if getattr(caster, "_packets", None) is not None:
        from hfrad.formfactors.raycast import _occluded
        hit = np.empty(len(t), np.bool_)
        best = min(_seconds(lambda: _occluded(caster._packets.scene, caster._packets.width, o, d, t, hit)) for _ in range(2))
        out["raw_packets"] = {"seconds": best, "rays_per_s": len(t) / best}
    for key in ("pipelined", "serial"):
        if key in out:
            out[key]["rays_per_s"] = out[key]["rays"] / out[key]["wall"]
            out[key]["share_of_raw"] = out[key]["rays_per_s"] / out["raw"]["rays_per_s"]
    out["loadavg_end"] = os.getloadavg()
    eng.close()
    return out


def _seconds(fn) -> float:
    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scene", default="cornell", help="built-in name or scene file")
    p.add_argument("--patches", type=int, default=10000)
    p.add_argument("--blocks", type=int, default=6)
    p.add_argument("--eps", type=float, default=0.02, help="the precompute's eps (ray budget eps/4)")
    p.add_argument("--modes", default="pipe,serial")
    args = p.parse_args()
    print(json.dumps(measure(args.scene, args.patches, args.blocks, args.eps, args.modes), indent=1))


if __name__ == "__main__":
    main()
