"""Benchmark: clustering real meshes into patches, and precomputes of clustered scenes.

Part 1 times :func:`hfrad.scene.cluster.cluster` on the shared scenes (Sponza, Sibenik,
the conference room) at the requested patch counts: patches obtained, triangles per
patch, worst non-flatness, seconds (best of 2; the first call of a process also
compiles the numba kernels and is not counted).

Part 2 (``--kernel``) measures form-factor kernel throughput (pairs per second, no
visibility, best of 3, 128 rows x all columns) in one run: the clustered kernel on each
scene clustered to each patch count, with kernel.py's rules for near pairs of few triangles (the default)
and without them (the 32-point rule for every near pair), against the plain kernel on
the same scene unclustered (one triangle per patch, as many rows); and on the built-in
Cornell box at the same patch count both ways (refined 4x and clustered back, against
plain subdivision), where the two kernels do the same work.

Part 3 (``--hfr FILE.hfr ...``) reads finished ``hfrad precompute`` outputs of
clustered scenes and tabulates their patch count, triangles, rank, achieved error and
the times stored in the file, so the README's numbers come from one place.

Run:  python benchmarks/bench_cluster.py [--patches 5000,20000] [--kernel] [--hfr a.hfr b.hfr]
Writes benchmarks/results/cluster.json (with the machine and its load average).
"""

from __future__ import annotations

import argparse
import os
import time

import common
import numpy as np

from hfrad.scene.cluster import cluster, cluster_summary, patch_diameters
from hfrad.scene.load import load_scene

SCENES = {
    "sponza": (str(common.SHARED_SCENES / "sponza-dabrovic" / "sponza.obj"), {"area_light": (50, 50, 50)}),
    "sibenik": (str(common.SHARED_SCENES / "sibenik" / "sibenik.obj"), {"area_light": (50, 50, 50)}),
    "conference": (str(common.SHARED_SCENES / "conference" / "conference.ply"),
                   {"unit_scale": 0.003, "area_light": (50, 50, 50)}),
}


def clustering_rows(patches: list[int]) -> list[dict]:
    rows = []
    for name, (path, kw) in SCENES.items():
        if not os.path.exists(path):
            print(f"skip {name}: {path} is absent")
            continue
        scene = load_scene(path, **kw)
        cluster(scene, patches=patches[0])  # compile
        for n in patches:
            best, result = float("inf"), None
            for _ in range(2):
                t0 = time.perf_counter()
                result = cluster(scene, patches=n)
                best = min(best, time.perf_counter() - t0)
            s = cluster_summary(result)
            d = patch_diameters(result) / np.sqrt(scene.total_area / n)
            rows.append({"scene": name, "faces": scene.n_patches, "asked": n, "patches": result.n_patches,
                         "triangles": result.n_triangles, "tri_per_patch": s["triangles_per_patch"]["mean"],
                         "max_tri": s["triangles_per_patch"]["max"], "non_flatness": s["worst_non_flatness"],
                         "area_cv": s["area_cv"], "area_ratio": float(result.areas.max() / result.areas.min()),
                         "D2/A_p99": s["compactness"]["p99"], "D2/A_max": s["compactness"]["max"],
                         "D/sqrtA*_max": float(d.max()), "seconds": best, "load": os.getloadavg()[0]})
    return rows


def _pairs_per_second(geometry, block, n_rows: int) -> tuple[float, int]:
    """(pairs/s, pairs) of ``block`` on ``n_rows`` evenly spaced rows x all columns (best of 3)."""
    rows = np.linspace(0, geometry.n - 1, min(n_rows, geometry.n)).astype(np.int64)
    cols = np.arange(geometry.n)
    block(geometry, rows[:2], cols[:50])  # compile
    t = common.best_of(lambda: block(geometry, rows, cols), 3, max_seconds=60.0)
    return len(rows) * len(cols) / t.best, len(rows) * len(cols)


def kernel_rows(patches: int, n_rows: int = 128) -> list[dict]:
    from hfrad.formfactors.clustered import ClusterGeometry, clustered_block
    from hfrad.formfactors.kernel import PatchGeometry, unoccluded_block
    from hfrad.scene.builtin import cornell_box
    from hfrad.scene.patches import subdivide

    cases = [("cornell", subdivide(cornell_box(), patches=patches),
              cluster(subdivide(cornell_box(), patches=4 * patches), patches=patches))]
    for name, (path, kw) in SCENES.items():
        if name != "sibenik" and os.path.exists(path):
            scene = load_scene(path, **kw)
            cases.append((name, scene, cluster(scene, patches=patches)))
    rows = []
    for name, plain, clustered in cases:
        for label, geom, block in (
                ("plain (one triangle per patch)", PatchGeometry(plain), unoccluded_block),
                ("clustered, near rule per triangle pair", ClusterGeometry(clustered), clustered_block),
                ("clustered, 32-point near rule", ClusterGeometry(clustered, exact_pairs=0), clustered_block)):
            rate, pairs = _pairs_per_second(geom, block, n_rows)
            rows.append({"scene": name, "kernel": label, "patches": geom.n, "pairs": pairs, "pairs_per_s": rate,
                         "load": os.getloadavg()[0]})
    return rows


def hfr_rows(paths: list[str]) -> list[dict]:
    from hfrad.solve.hfr import load_hfr

    rows = []
    for p in paths:
        fac = load_hfr(p)
        s = fac.scene
        rows.append({"file": os.path.basename(p), "patches": fac.n_patches,
                     "triangles": s.n_triangles if s is not None else None, "rank": fac.rank,
                     "achieved": fac.relative_error, "eps": fac.eps,
                     "sigma_max": float(np.max(fac.sigma_max())),
                     **{k: v for k, v in (fac.timings or {}).items() if isinstance(v, (int, float))}})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--patches", default="5000,20000")
    ap.add_argument("--kernel", action="store_true", help="measure kernel pairs/s (plain vs clustered)")
    ap.add_argument("--skip-clustering", action="store_true")
    ap.add_argument("--hfr", nargs="*", default=[])
    args = ap.parse_args()
    info = common.header("clustering real meshes")
    sizes = common.parse_sizes(args.patches)
    rows = [] if args.skip_clustering else clustering_rows(sizes)
    if rows:
        common.print_table("clustering", rows, ["scene", "faces", "asked", "patches", "triangles", "tri_per_patch",
                                                "max_tri", "non_flatness", "area_ratio", "D2/A_p99", "D2/A_max",
                                                "D/sqrtA*_max", "seconds", "load"])
    kernel = [r for n in sizes for r in kernel_rows(n)] if args.kernel else []
    if kernel:
        common.print_table("kernel throughput (no visibility)", kernel, ["scene", "kernel", "patches", "pairs",
                                                                         "pairs_per_s", "load"])
    pre = hfr_rows(args.hfr)
    if pre:
        common.print_table("precomputed clustered scenes", pre, list(pre[0].keys()))
    common.write_json("cluster", {**info, "clustering": rows, "kernel": kernel, "precompute": pre})


if __name__ == "__main__":
    main()
