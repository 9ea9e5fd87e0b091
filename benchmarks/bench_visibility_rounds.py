"""Benchmark: what the visibility rays of a clustered real scene cost, round by round, and how right
the rows of F they give are.

``rounds``: the form-factor pass of ``hfrad precompute SCENE --area-light 50,50,50 --patches N``
(default eps 0.02: its ray budget, block size, order and reciprocity; one process, Embree in its
thread beside the kernel), the blocks thrown away. Prints per round (probe; 4, 16, 64, 256 segments;
"32 picked", "64 picked" for the second round's importance picks; "bent" for pairs with a bent patch) the pairs, rays and Embree seconds, rays per second, why pairs
went to the second round (their rays disagree, or only close), and the pass's wall and CPU seconds.

``rows``: ``--rows`` random rows of F (fixed seed; the precompute's ray budget) against
cosine-weighted ray shooting from the patches' triangles (first hits; ``--shots`` rays a row, cached
in the temporary folder): mean and max |row sum - shot row sum|, mean L1 distance of the rows, their
relative Frobenius distance, how far the budget's second-round rules moved them (against the same
rows with every second round), and the largest row sum. Shooting is the reference we did not write; its noise on a row sum is about
sqrt(s (1 - s) / shots) (0.0025 at 40,000 shots).

Run:  python benchmarks/bench_visibility_rounds.py [--scene sponza] [--patches 3000]
      [--mode rounds,rows] [--rows 200] [--blocks K] [--factors refine_factor=8,...] [--out NAME]   (NAME: results/NAME.json)
"""

from __future__ import annotations

import argparse
import os
import pickle
import tempfile
import time
from pathlib import Path

import common
import numpy as np

import hfrad
from hfrad.formfactors.blocks import iter_column_blocks
from hfrad.formfactors.budget import ray_budget
from hfrad.formfactors.engine import FormFactorEngine
from hfrad.formfactors.raycast import RayCaster
from hfrad.precompute.options import plan_precompute
from hfrad.scene.load import load_scene

SCENES = {
    "sponza": (common.SHARED_SCENES / "sponza-dabrovic" / "sponza.obj", {}),
    "sibenik": (common.SHARED_SCENES / "sibenik" / "sibenik.obj", {}),
    "conference": (common.SHARED_SCENES / "conference" / "conference.ply", {"unit_scale": 0.01}),
}


def scene_of(name: str, patches: int):
    """The scene as ``hfrad precompute --area-light 50,50,50 --patches N`` loads it (pickled in TMPDIR)."""
    cache = Path(tempfile.gettempdir()) / f"hfrad-bench-vis-{name}-{patches}.pkl"
    if cache.exists():
        return pickle.loads(cache.read_bytes())
    path, kw = SCENES[name]
    scene = load_scene(str(path), area_light=(50, 50, 50), patches=patches, **kw)
    cache.write_bytes(pickle.dumps(scene))
    return scene


#: The ray budget's factors (budget.ray_budget's keywords) for every engine here; empty: the defaults.
FACTORS: dict = {}


def _engine(scene, plan, **kw) -> FormFactorEngine:
    budget = ray_budget(scene, plan.one_ray_tol, **FACTORS)
    return FormFactorEngine(scene, ray_budget=budget, **({} if plan.samples is None else {"samples": plan.samples}),
                            **kw)


def _second_round_reasons(vis, reasons: dict) -> None:
    """Wrap ``vis.finish`` to count why first-round pairs go to the second round."""
    finish = vis.finish

    def counted(F, job, hit):
        if not job.final and vis.refine_samples:
            blocked = np.add.reduceat(hit.astype(np.int64), job.first[:-1]) if len(hit) else np.zeros(0, np.int64)
            total = np.diff(job.first)
            blocked = np.where(total > 0, blocked, 0)
            i, j = job.r_idx, job.c_idx
            a = F.reshape(-1)[job.pairs] * vis.areas[i]
            matters = a > vis.refine_above * np.minimum(vis.areas[i], vis.areas[j])
            partial = (blocked > 0) & (blocked < total)
            gap = np.linalg.norm(vis.centroids[i] - vis.centroids[j], axis=1)
            close = gap < vis.refine_near * (vis.diameters[i] + vis.diameters[j])
            tag = "bent" if getattr(job, "round", "").endswith("bent") else "flat"   # older code: no rounds
            for key, sel in ((f"{tag} first-round pairs", np.ones(len(i), bool)),
                             (f"{tag} partial", partial & matters), (f"{tag} close, rays agree", close & ~partial & matters),
                             (f"{tag} close, all visible", close & (blocked == 0) & matters)):
                reasons[key] = reasons.get(key, 0) + int(sel.sum())
        return finish(F, job, hit)

    vis.finish = counted


def rounds(scene, plan, blocks: int = 0, ray_threads: int | None = 1) -> dict:
    """The precompute's form-factor pass, blocks dropped; per-round counters. ``blocks`` > 0: only
    that many column blocks spread over the order, every row (no reciprocity; a quicker sample).
    ``ray_threads``: threads casting each batch (the engine's; None: every core)."""
    engine = _engine(scene, plan, ray_threads=ray_threads)
    vis = engine.visibility
    reasons: dict = {}
    _second_round_reasons(vis, reasons)
    load0 = os.getloadavg()[0]
    t0, c0 = time.perf_counter(), time.process_time()
    if blocks:
        b = plan.block_size
        starts = np.linspace(0, scene.n_patches - b, blocks).astype(int)
        passes = engine.iter_blocks(plan.perm, [plan.perm[s:s + b] for s in starts])
    else:
        passes = iter_column_blocks(scene, plan.block_size, order=plan.perm, engine=engine, dtype=np.float32,
                                    reciprocity=plan.reciprocity)
    for _ in passes:
        pass
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    out = {"wall_s": wall, "cpu_s": cpu, "kernel_s": engine.kernel_seconds, "embree_s": vis.embree_seconds,
           "pairs": engine.pairs, "rays": vis.rays_cast, "load": [load0, os.getloadavg()[0]],
           "bent_patches": int(vis.bent.sum()) if vis.bent is not None else 0, "culling": bool(vis.cull),
           "occluders": vis.n_occluders, "one_ray_below": vis.budget.one_ray_below,
           "few_rays_below": vis.budget.few_rays_below, "reasons": reasons,
           "rounds": {k: {"pairs": v[0], "rays": v[1], "embree_s": v[2], "Mrays_per_s": v[1] / max(v[2], 1e-9) / 1e6}
                      for k, v in sorted(getattr(vis, "rounds", {}).items(), key=lambda kv: -kv[1][1])}}
    engine.close()
    return out


def shot_rows(scene, rows: np.ndarray, shots: int) -> np.ndarray:
    """(len(rows), n) share of each row patch's light that first reaches each patch (ray shooting)."""
    tri = np.asarray(scene.triangles, np.float64)
    caster = RayCaster(tri.reshape(-1, 3), np.arange(3 * len(tri)).reshape(-1, 3))
    size = float(np.ptp(scene.bounds, axis=0).max())
    start, index = scene.patch_triangles
    out = np.zeros((len(rows), scene.n_patches))
    for r, i in enumerate(rows):
        rng = np.random.default_rng(int(i))
        own = index[start[i]:start[i + 1]]
        t = rng.choice(own, shots, p=scene.triangle_areas[own] / scene.triangle_areas[own].sum())
        u, v = rng.random((2, shots))
        flip = u + v > 1
        u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
        T, N = tri[t], scene.triangle_normals[t]
        x = T[:, 0] + u[:, None] * (T[:, 1] - T[:, 0]) + v[:, None] * (T[:, 2] - T[:, 0])
        helper = np.where(np.abs(N[:, :1]) > 0.9, [[0.0, 1.0, 0.0]], [[1.0, 0.0, 0.0]])
        e1 = np.cross(N, helper)
        e1 /= np.linalg.norm(e1, axis=1)[:, None]
        e2 = np.cross(N, e1)
        phi, rr = 2 * np.pi * rng.random(shots), rng.random(shots)
        d = (np.sqrt(rr)[:, None] * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2)
             + np.sqrt(1 - rr)[:, None] * N)
        face, _, _ = caster.intersect(x + 1e-6 * size * N, d)
        hit = face >= 0
        hit[hit] = np.einsum("rd,rd->r", d[hit], scene.triangle_normals[face[hit]]) < 0  # front faces only
        out[r] = np.bincount(scene.triangle_patch[face[hit]], minlength=scene.n_patches) / shots
    caster.close()
    return out


def row_accuracy(scene, plan, name: str, count: int, shots: int) -> dict:
    """``count`` random rows of F (the precompute's ray budget) against ray shooting."""
    rows = np.sort(np.random.default_rng(46).choice(scene.n_patches, count, replace=False))
    cache = Path(tempfile.gettempdir()) / f"hfrad-bench-vis-shots-{name}-{scene.n_patches}-{count}-{shots}.npy"
    if cache.exists():
        ref = np.load(cache)
    else:
        ref = shot_rows(scene, rows, shots)
        np.save(cache, ref)
    engine = _engine(scene, plan, ray_threads=None)
    t0 = time.perf_counter()
    F = engine.block(rows, np.arange(scene.n_patches))
    seconds = time.perf_counter() - t0
    engine.close()
    ref[np.arange(count), rows] = 0.0   # what a bent patch sends to itself: F's diagonal is 0
    diff = F.sum(axis=1) - ref.sum(axis=1)
    # the same rows with the second round on every pair that asks for it (no budget rule for it)
    FACTORS_ALL = {**FACTORS, "refine_factor": 0.0, "large_factor": 0.0}
    full = FormFactorEngine(scene, ray_budget=ray_budget(scene, plan.one_ray_tol, **FACTORS_ALL), ray_threads=None)
    F_all = full.block(rows, np.arange(scene.n_patches))
    full.close()
    return {"rows": count, "shots": shots, "seconds": seconds, "mean_abs_sum_diff": float(np.abs(diff).mean()),
            "max_abs_sum_diff": float(np.abs(diff).max()), "mean_sum_diff": float(diff.mean()),
            "mean_l1": float(np.abs(F - ref).sum(axis=1).mean()),
            "rel_fro_vs_shots": float(np.linalg.norm(F - ref) / np.linalg.norm(ref)),
            "rel_fro_moved": float(np.linalg.norm(F - F_all) / np.linalg.norm(F_all)),
            "rel_fro_all_vs_shots": float(np.linalg.norm(F_all - ref) / np.linalg.norm(ref)),
            # the shots' own share of those distances: binomial variance F_ij / shots per entry
            "rel_fro_shot_noise": float(np.sqrt(ref.sum() / shots) / np.linalg.norm(ref)),
            "mean_abs_sum_diff_all": float(np.abs(F_all.sum(axis=1) - ref.sum(axis=1)).mean()),
            "max_row_sum": float(F.sum(axis=1).max()), "max_row_sum_all": float(F_all.sum(axis=1).max()),
            "rows_over_1.05": int((F.sum(axis=1) > 1.05).sum()), "rays": engine.rays, "rays_all": full.rays}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scene", default="sponza", choices=sorted(SCENES))
    p.add_argument("--patches", type=int, default=3000)
    p.add_argument("--mode", default="rounds,rows")
    p.add_argument("--rows", type=int, default=200)
    p.add_argument("--shots", type=int, default=40000)
    p.add_argument("--blocks", type=int, default=0, help="rounds: only this many column blocks (0: the whole pass)")
    p.add_argument("--factors", default="", help="ray budget factors, e.g. refine_factor=0,large_factor=0")
    p.add_argument("--ray-threads", type=int, default=1, help="rounds: threads casting a batch (0: every core)")
    p.add_argument("--out", default=None)
    args = p.parse_args()
    FACTORS.update({k: float(v) for k, v in (kv.split("=") for kv in args.factors.split(",") if kv)})
    t = time.perf_counter()
    scene = scene_of(args.scene, args.patches)
    plan = plan_precompute(scene, 0.02)
    result = {"scene": args.scene, "patches": scene.n_patches, "factors": FACTORS, "hfrad": hfrad.__file__,
              "load_s": time.perf_counter() - t,
              "machine": common.machine_line()}
    print(f"{args.scene}: {scene.n_patches} patches, {result['load_s']:.1f} s to load", flush=True)
    for mode in args.mode.split(","):
        result[mode] = rounds(scene, plan, args.blocks, args.ray_threads or None) if mode == "rounds" else row_accuracy(scene, plan, args.scene, args.rows,
                                                                                   args.shots)
        print(mode, common._jsonable(result[mode]), flush=True)
    if args.out:
        print(common.write_json(args.out, result))


if __name__ == "__main__":
    main()
