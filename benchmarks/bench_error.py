"""Error figures against the truth: how tight is each figure hfrad reports? (issue 10)

For each scene and eps, the factorization that ``hfrad.factorize`` builds from
the scene's form factors (float32 factors, Z-order, HF) is solved for the
scene's own lights, and the radiosity is compared with an exact dense LU solve
of the same F. Per colour channel, relative, in the area-weighted norm
sqrt(sum A_i e_i^2) / sqrt(sum A_i B_i^2); the table shows the worst channel:

- true: the error against the dense solve;
- bound: ``fac.error_estimate().bound``, guaranteed for every solve except
  with probability 1e-6 (probes of the factorization error, contraction from
  row sums);
- residual: ``fac.residual(E, B).bound``, guaranteed for this solution
  (one more pass over F);
- eq5: the paper's eq. 5 (2-norm, sigma_max estimated; no bound where >= 1).

Not a test and not timed: prints a table and writes results/error_figures-CASES.json.
Run: ``PYTHONPATH=src python3 benchmarks/bench_error.py [--cases cornell3k,...] [--eps 0.05,0.02,0.01]``.
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings

import numpy as np

import common
from hfrad.errors import AccuracyWarning


def nonuniform_cornell():
    """The built-in Cornell box with a fine floor (edges <= 0.08 m) and coarse walls and blocks (<= 0.3 m)."""
    import hfrad
    from hfrad.scene.scene import Scene

    base = hfrad.load_scene("cornell")
    fine, coarse = hfrad.subdivide(base, max_edge=0.08), hfrad.subdivide(base, max_edge=0.3)
    floor = base.groups.index("floor")
    parts = [(fine, fine.group == floor), (coarse, coarse.group != floor)]
    vertices, faces, offset = [], [], 0
    for s, keep in parts:
        vertices.append(s.vertices)
        faces.append(s.faces[keep] + offset)
        offset += len(s.vertices)
    pick = lambda name: np.concatenate([np.asarray(getattr(s, name))[keep] for s, keep in parts])  # noqa: E731
    return Scene(vertices=np.vstack(vertices), faces=np.vstack(faces), material=pick("material"),
                 materials=base.materials, group=pick("group"), groups=base.groups, parent=pick("parent"),
                 occluder_vertices=base.occluder_vertices, occluder_faces=base.occluder_faces,
                 name="cornell-nonuniform")


CASES = {
    "cornell3k": lambda: __import__("hfrad").load_scene("cornell", patches=3000),
    "cornell10k": lambda: __import__("hfrad").load_scene("cornell", patches=10000),
    "cbox-original": lambda: __import__("hfrad").load_scene(
        str(common.SHARED_SCENES / "cornell-box" / "CornellBox-Original.obj"), patches=3000),
    "nonuniform": nonuniform_cornell,
}


def area_error(B_approx, B, areas) -> np.ndarray:
    w = np.sqrt(areas)[:, None]
    return np.linalg.norm(w * (B_approx - B), axis=0) / np.linalg.norm(w * B, axis=0)


def run_case(name: str, eps_list: list[float]) -> list[dict]:
    import hfrad
    from hfrad.scene.zorder import patch_order
    from hfrad.solve.denselu import LUFactorization

    t0 = time.perf_counter()
    scene = CASES[name]()
    n = scene.n_patches
    F = hfrad.form_factor_matrix(scene, dtype=np.float64)
    t_ff = time.perf_counter() - t0
    exact = LUFactorization(F, scene.reflectance).solve(scene.emission)
    perm = patch_order(scene.centroids, "zorder")
    rows = []
    for eps in eps_list:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", AccuracyWarning)
            fac = hfrad.factorize_matrix(F, scene.reflectance, areas=scene.areas, eps=eps, order=perm)
            B = fac.solve(scene.emission)
            est = fac.error_estimate()
            res = fac.residual(scene.emission, B, form_factors=F)
        true = area_error(B, exact, scene.areas)
        row = {"case": name, "n": n, "eps": eps, "rank": fac.rank,
               "area_ratio": float(scene.areas.max() / scene.areas.min()),
               "row_sum_max": float(F.sum(axis=1).max()),
               "true": true.tolist(), "bound": est.bound.tolist(), "residual_bound": res.bound.tolist(),
               "eq5": est.eq5_bound.tolist(), "operator_error": est.operator_error.tolist(),
               "contraction": est.contraction.tolist(),
               "true_max": float(true.max()), "bound_max": float(est.bound.max()),
               "residual_max": float(res.bound.max()), "eq5_max": float(est.eq5_bound.max())}
        row["bound/true"] = row["bound_max"] / row["true_max"]
        row["residual/true"] = row["residual_max"] / row["true_max"]
        row["eq5/true"] = row["eq5_max"] / row["true_max"]
        rows.append(row)
        print(f"{name} n={n} eps={eps}: rank {fac.rank}, true {row['true_max']:.3g}, bound {row['bound_max']:.3g}, "
              f"residual {row['residual_max']:.3g}, eq5 {row['eq5_max']:.3g} "
              f"(form factors {t_ff:.0f} s, total {time.perf_counter() - t0:.0f} s)", file=sys.stderr, flush=True)
    return rows


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cases", default="cornell3k,cbox-original,nonuniform,cornell10k")
    p.add_argument("--eps", default="0.05,0.02,0.01")
    common.add_blas_arg(p)
    args = p.parse_args(argv)
    m = common.header("Error figures vs the exact dense solve (area-weighted norm, worst channel)", args.blas_threads)
    eps_list = common.parse_list(args.eps, float)
    rows = []
    for name in common.parse_list(args.cases):
        if name == "cbox-original" and not (common.SHARED_SCENES / "cornell-box").exists():
            print(f"skipping {name}: {common.SHARED_SCENES} not found", file=sys.stderr)
            continue
        rows += run_case(name, eps_list)
    common.print_table("true error vs the figures hfrad reports", rows, [
        "case", "n", "eps", "rank", ("true_max", "true"), ("bound_max", "bound"), "bound/true",
        ("residual_max", "residual bound"), "residual/true", ("eq5_max", "eq. 5"), "eq5/true"])
    common.write_json("error_figures-" + "-".join(common.parse_list(args.cases)), {"machine": m, "rows": rows})


if __name__ == "__main__":
    main()
