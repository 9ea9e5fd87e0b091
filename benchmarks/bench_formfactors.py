"""Benchmark: form factors with visibility (hfrad) vs raw Embree and pyviewfactor.

Run:  PYTHONPATH=src python benchmarks/bench_formfactors.py [--patches 10000] [--pvf-patches 800]
Writes benchmarks/results/formfactors.json and prints a table. Not collected by pytest.
pyviewfactor is optional (pip install pyviewfactor==1.1.0).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np

from hfrad.formfactors import analytic, form_factor_matrix
from hfrad.formfactors.blocks import FormFactorEngine, iter_column_blocks
from hfrad.scene.builtin import cornell_box, parallel_plates, perpendicular_plates
from hfrad.scene.patches import subdivide
from hfrad.scene.zorder import zorder_permutation


def machine() -> dict:
    mem = 0
    with open("/proc/meminfo") as fh:
        for line in fh:
            if line.startswith("MemTotal:"):
                mem = int(line.split()[1]) * 1024
    import numba
    return {"cores": len(os.sched_getaffinity(0)), "memory_gib": round(mem / 2**30, 1),
            "cpu": platform.processor() or platform.machine(), "numba_threads": numba.get_num_threads(),
            "python": platform.python_version()}


def bench_hfrad_full(patches: int, samples: int, block: int) -> dict:
    scene = subdivide(cornell_box(), patches=patches)
    n = scene.n_patches
    order = zorder_permutation(scene.centroids)
    warm = subdivide(cornell_box(), patches=100)  # load the numba cache outside the timing
    form_factor_matrix(warm, samples=samples)
    t0 = time.perf_counter()
    engine = FormFactorEngine(scene, samples=samples)
    sums = np.zeros(n)
    for start, stop, B in iter_column_blocks(scene, block, order=order, samples=samples, engine=engine):
        sums += B.sum(axis=1)
    total = time.perf_counter() - t0
    err = np.abs(sums - 1)
    res = {"patches": n, "samples": samples, "block_size": block, "seconds": total,
           "pairs_per_s": n * n / total, "kernel_seconds": engine.kernel_seconds,
           "embree_seconds": engine.embree_seconds, "rays": engine.rays,
           "rays_per_pair_nonzero_avg": engine.rays / max(1, n * n),
           "embree_rays_per_s_in_pipeline": engine.rays / max(engine.embree_seconds, 1e-9),
           "rays_per_s_end_to_end": engine.rays / total,
           "row_sum_mean_abs_err": float(err.mean()), "row_sum_max_abs_err": float(err.max())}
    # raw embreex throughput on the very same rays (a few blocks), same process
    vis = engine.visibility
    rows = order
    rays, raw_t = 0, 0.0
    for start in range(0, n, max(block, n // 4))[:4]:
        cols = order[start:start + block]
        F = engine._kernel(rows, cols)
        for job in vis.jobs(F, rows, cols):
            t = time.perf_counter()
            vis.caster._scene.run(job.o, job.d, query="OCCLUDED", dists=job.t)
            raw_t += time.perf_counter() - t
            rays += len(job.t)
            job.pool.put(job.buf)
    res["raw_embree_rays_per_s"] = rays / raw_t
    res["raw_embree_seconds_for_all_rays"] = engine.rays / res["raw_embree_rays_per_s"]
    engine.close()
    return res


def plate_vf(scene, F) -> float:
    p1 = scene.group == scene.groups.index("plate1")
    p2 = scene.group == scene.groups.index("plate2")
    return float((scene.areas[p1, None] * F[np.ix_(p1, p2)]).sum() / scene.areas[p1].sum())


def pvf_matrix(scene):
    """pyviewfactor's F in hfrad's convention (F[i, j] = i -> j)."""
    import pyvista as pv
    from pyviewfactor import compute_viewfactor_matrix
    faces = np.hstack([np.full((scene.n_patches, 1), 3), scene.faces]).ravel()
    mesh = pv.PolyData(np.asarray(scene.vertices, float), faces)
    return compute_viewfactor_matrix(mesh).T


def bench_plates(max_edge: float, with_pvf: bool) -> list[dict]:
    rows = []
    cases = [("parallel 1x1 d=1", parallel_plates(1, 1, 1), analytic.parallel_rectangles(1, 1, 1)),
             ("perpendicular 1,1,1", perpendicular_plates(1, 1, 1), analytic.perpendicular_rectangles(1, 1, 1))]
    for name, base, exact in cases:
        scene = subdivide(base, max_edge=max_edge)
        form_factor_matrix(scene)  # warm
        t = time.perf_counter()
        F = form_factor_matrix(scene)
        th = time.perf_counter() - t
        row = {"case": name, "patches": scene.n_patches, "exact": exact,
               "hfrad_seconds": th, "hfrad_rel_err": plate_vf(scene, F) / exact - 1}
        if with_pvf:
            pvf_matrix(subdivide(base, max_edge=0.5))  # numba warm-up of pyviewfactor
            t = time.perf_counter()
            P = pvf_matrix(scene)
            tp = time.perf_counter() - t
            vf = plate_vf(scene, P)
            if vf == 0:  # other normal convention: flip the faces
                P = pvf_matrix(scene.replace(faces=scene.faces[:, ::-1]))
                vf = plate_vf(scene, P)
            row.update({"pyviewfactor_seconds": tp, "pyviewfactor_rel_err": vf / exact - 1,
                        "speedup": tp / th})
        rows.append(row)
    return rows


def bench_pvf_cornell(patches: int) -> dict:
    scene = subdivide(cornell_box(), patches=patches)
    t = time.perf_counter()
    F = form_factor_matrix(scene)
    th = time.perf_counter() - t
    out = {"patches": scene.n_patches, "hfrad_seconds": th,
           "hfrad_row_sum_max_err": float(np.abs(F.sum(1) - 1).max()),
           "hfrad_row_sum_mean_err": float(np.abs(F.sum(1) - 1).mean())}
    try:
        t = time.perf_counter()
        P = pvf_matrix(scene)
        tp = time.perf_counter() - t
        if np.abs(P.sum(1)).mean() < 0.1:
            P = pvf_matrix(scene.replace(faces=scene.faces[:, ::-1]))
        out.update({"pyviewfactor_seconds": tp, "speedup": tp / th,
                    "pyviewfactor_row_sum_max_err": float(np.abs(P.sum(1) - 1).max()),
                    "pyviewfactor_row_sum_mean_err": float(np.abs(P.sum(1) - 1).mean())})
    except ImportError:
        pass
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--patches", type=int, default=10000, help="Cornell-box patches for the full matrix")
    ap.add_argument("--samples", type=int, default=4)
    ap.add_argument("--block", type=int, default=256)
    ap.add_argument("--plate-edge", type=float, default=0.05, help="max patch edge on the plates")
    ap.add_argument("--pvf-patches", type=int, default=600, help="Cornell patches for pyviewfactor (0 = skip)")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "formfactors.json"))
    args = ap.parse_args()
    try:
        import pyviewfactor  # noqa: F401
        have_pvf = True
    except ImportError:
        have_pvf = False
        print("pyviewfactor not installed: pip install pyviewfactor==1.1.0 (comparison skipped)")
    res = {"machine": machine(), "full": bench_hfrad_full(args.patches, args.samples, args.block)}
    res["plates"] = bench_plates(args.plate_edge, have_pvf)
    if args.pvf_patches:
        res["cornell_small"] = bench_pvf_cornell(args.pvf_patches) if have_pvf else None
    f = res["full"]
    m = res["machine"]
    print(f"machine: {m['cores']} cores, {m['memory_gib']} GiB, numba threads {m['numba_threads']}")
    print(f"Cornell box {f['patches']} patches, samples={f['samples']}: full F in {f['seconds']:.1f} s "
          f"({f['pairs_per_s'] / 1e6:.2f} M pairs/s), kernel {f['kernel_seconds']:.1f} s, "
          f"Embree {f['embree_seconds']:.1f} s (overlapped)")
    print(f"rays {f['rays'] / 1e6:.1f} M: {f['embree_rays_per_s_in_pipeline'] / 1e6:.2f} M/s in the pipeline, "
          f"{f['rays_per_s_end_to_end'] / 1e6:.2f} M/s end to end; raw embreex {f['raw_embree_rays_per_s'] / 1e6:.2f} M/s "
          f"(ratio {f['rays_per_s_end_to_end'] / f['raw_embree_rays_per_s']:.0%} end to end)")
    print(f"row sums: mean |err| {f['row_sum_mean_abs_err']:.2e}, worst {f['row_sum_max_abs_err']:.2e}")
    print(f"{'case':22s} {'n':>6s} {'hfrad s':>8s} {'hfrad err':>10s} {'pvf s':>8s} {'pvf err':>10s} {'speedup':>8s}")
    for r in res["plates"]:
        print(f"{r['case']:22s} {r['patches']:6d} {r['hfrad_seconds']:8.3f} {r['hfrad_rel_err']:10.2e} "
              f"{r.get('pyviewfactor_seconds', float('nan')):8.3f} {r.get('pyviewfactor_rel_err', float('nan')):10.2e} "
              f"{r.get('speedup', float('nan')):8.1f}")
    if res.get("cornell_small"):
        c = res["cornell_small"]
        print(f"Cornell {c['patches']} patches: hfrad {c['hfrad_seconds']:.2f} s (worst row {c['hfrad_row_sum_max_err']:.2e}), "
              f"pyviewfactor {c.get('pyviewfactor_seconds', float('nan')):.2f} s "
              f"(worst row {c.get('pyviewfactor_row_sum_max_err', float('nan')):.2e}), speedup {c.get('speedup', float('nan')):.1f}x")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(res, indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
