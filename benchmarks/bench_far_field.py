"""The sampled far field against the exact pass, side by side in one run (issue 43).

For each size, ``hfrad.factorize(scene, eps, far_field=...)`` runs with ``"exact"`` (every
pair; half copied by reciprocity) and ``"sampled"`` (near rows exactly, far rows from a checked
interpolative decomposition, visibility of far pairs from cluster tests and probe rays), on
the same scene, one after the other. Columns: wall time of the whole precompute, form-factor
time, rank, the share of the n^2 pairs evaluated (and with rays), the sampled field's
certified ``||G - G~||_F`` (estimate and upper figure from the certification rows) against a
second, held-out sample of exact rows, and the radiosity of the scene's lights: sampled
against exact, relative to the reflected light (``||B_s - B_e||_A / ||B_e - E||_A`` per
channel), beside the per-solve error figure each gives for its own solution.

Not a test: prints a table and writes results/far-field-cornell-SIZES.json.
Run: ``PYTHONPATH=src python3 benchmarks/bench_far_field.py [--patches 40000,80000] [--eps 0.02]
[--modes exact,sampled] [--scene cornell]``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

import common
import hfrad
from hfrad.formfactors.farfield import FarFieldOptions


def reflected_difference(B, B_ref, E, areas) -> list[float]:
    """Per channel ``||B - B_ref||_A / ||B_ref - E||_A``."""
    w = np.asarray(areas)[:, None]
    return list(np.sqrt((w * (B - B_ref) ** 2).sum(axis=0) / (w * (B_ref - E) ** 2).sum(axis=0)))


def run(scene, mode: str, eps: float) -> dict:
    options = hfrad.PrecomputeOptions(far=FarFieldOptions(holdout_rows=256))
    t0 = time.perf_counter()
    fac = hfrad.factorize(scene, eps, far_field=mode, options=options)
    wall = time.perf_counter() - t0
    info = fac.lowrank.info
    E = np.asarray(scene.emission, float)
    B, err = fac.solve(E, return_error=True)
    row = {"mode": mode, "n": scene.n_patches, "wall_s": wall, "formfactors_s": info.get("time_formfactors"),
           "hf_s": info.get("time_total"), "rank": fac.rank, "B": B,
           "figure": [float(x) for x in np.ravel(err.bound)],
           "operator_error": [float(x) for x in fac.error_estimate().operator_error]}
    far = info.get("far_field")
    if far:
        row.update(pairs_share=far["pairs_share"], traced_share=far["traced_share"],
                   certificate=far["error_estimate"], certificate_upper=far["error_upper"],
                   holdout=far.get("holdout_estimate"), exact_groups=far["exact_groups"], groups=far["groups"],
                   refined_groups=far["refined_groups"], skeleton_mean=far["skeleton_mean"], far_field=far)
    else:
        copied = info.get("reciprocity", {}).get("copied_pairs", 0)
        row.update(pairs_share=1.0 - copied / scene.n_patches ** 2, traced_share=None)
    return row


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--patches", default="40000")
    p.add_argument("--eps", type=float, default=0.02)
    p.add_argument("--modes", default="exact,sampled")
    p.add_argument("--scene", default="cornell")
    common.add_blas_arg(p)
    args = p.parse_args()
    m = common.header("The sampled far field against the exact pass", args.blas_threads)
    rows = []
    for size in common.parse_sizes(args.patches):
        scene = common.load_bench_scene(args.scene, size)
        results = {mode: run(scene, mode, args.eps) for mode in common.parse_list(args.modes)}
        exact = results.get("exact")
        for r in results.values():
            if exact is not None and r is not exact:
                r["vs_exact"] = reflected_difference(r["B"], exact["B"], np.asarray(scene.emission, float),
                                                     scene.areas)
                r["time_ratio"] = exact["wall_s"] / r["wall_s"]
            rows.append({k: v for k, v in r.items() if k != "B"})
    common.print_table(f"{args.scene}, eps {args.eps}: exact pass vs sampled far field", rows,
                       ["n", "mode", ("wall_s", ".1f"), ("formfactors_s", ".1f"), "rank", ("pairs_share", ".3%"),
                        ("traced_share", ".3%"), ("certificate", ".3g"), ("certificate_upper", ".3g"),
                        ("holdout", ".3g"), "vs_exact", "figure", ("time_ratio", ".2f")])
    path = common.write_json(f"far-field-{args.scene}-" + "-".join(str(r["n"]) for r in rows[::len(results)]),
                             {"machine": m, "eps": args.eps, "rows": rows})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
