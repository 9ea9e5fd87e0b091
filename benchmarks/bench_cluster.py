"""Benchmark: clustering real meshes into patches, and precomputes of clustered scenes.

Part 1 times :func:`hfrad.scene.cluster.cluster` on the shared scenes (Sponza, Sibenik,
the conference room) at the requested patch counts: patches obtained, triangles per
patch, worst non-flatness, seconds (best of 2; the first call of a process also
compiles the numba kernels and is not counted).

Part 2 (``--hfr FILE.hfr ...``) reads finished ``hfrad precompute`` outputs of
clustered scenes and tabulates their patch count, triangles, rank, achieved error and
the times stored in the file, so the README's numbers come from one place.

Run:  python benchmarks/bench_cluster.py [--patches 5000,20000] [--hfr a.hfr b.hfr]
Writes benchmarks/results/cluster.json (with the machine and its load average).
"""

from __future__ import annotations

import argparse
import os
import time

import common
import numpy as np

from hfrad.scene.cluster import cluster, cluster_summary
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
            rows.append({"scene": name, "faces": scene.n_patches, "asked": n, "patches": result.n_patches,
                         "triangles": result.n_triangles, "tri_per_patch": s["triangles_per_patch"]["mean"],
                         "max_tri": s["triangles_per_patch"]["max"], "non_flatness": s["worst_non_flatness"],
                         "area_cv": s["area_cv"], "seconds": best, "load": os.getloadavg()[0]})
    return rows


def hfr_rows(paths: list[str]) -> list[dict]:
    from hfrad.io.hfr import load_hfr

    rows = []
    for p in paths:
        fac = load_hfr(p)
        s = fac.scene
        rows.append({"file": os.path.basename(p), "patches": fac.n_patches,
                     "triangles": s.n_triangles if s is not None else None, "rank": fac.rank,
                     "achieved": fac.relative_error, "eps": fac.eps,
                     "sigma_max": float(np.max(fac.sigma_max)),
                     **{k: v for k, v in (fac.timings or {}).items() if isinstance(v, (int, float))}})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--patches", default="5000,20000")
    ap.add_argument("--hfr", nargs="*", default=[])
    args = ap.parse_args()
    info = common.header("clustering real meshes")
    rows = clustering_rows(common.parse_sizes(args.patches))
    common.print_table("clustering", rows, ["scene", "faces", "asked", "patches", "triangles", "tri_per_patch",
                                            "max_tri", "non_flatness", "area_cv", "seconds", "load"])
    pre = hfr_rows(args.hfr)
    if pre:
        common.print_table("precomputed clustered scenes", pre, list(pre[0].keys()))
    common.write_json("cluster", {**info, "clustering": rows, "precompute": pre})


if __name__ == "__main__":
    main()
