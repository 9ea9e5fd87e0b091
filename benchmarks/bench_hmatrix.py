"""F as an H-matrix (formfactors/hmatrix.py) against the n^2 pass, at growing n (issue 43).

For each size: the H-matrix is built (k-d cluster tree, exact near leaves with rays, far
blocks by cluster-pair visibility, per-row probes and cross approximation), then

- its error against exact rows of F drawn afresh (``--rows`` patches spread over the tree
  order, computed with the same engine): ``||diag(rho)(F - F~)||_F / ||diag(rho) F||_F`` over them;
- the global rank of G = diag(rho_max) F~ at each ``--eps`` from products only
  (:func:`hfrad.lowrank.operator.operator_factorization`), with its time and products;
- the share of the n^2 pairs evaluated (exact, with rays; kernel only), storage, stages' seconds,
  peak resident memory of the process;
- with ``--exact-pass``, the exact pass of today (``hfrad.factorize(scene, eps, far_field="exact")``)
  on the same scene in the same run, its wall time and rank, for the side by side.

Not a test: prints a table and writes results/hmatrix-SCENE-SIZES.json with the machine.
Run: ``PYTHONPATH=src python3 benchmarks/bench_hmatrix.py --patches 40000,163000 [--eps 0.05,0.02]
[--scene cornell] [--exact-pass]``.
"""

from __future__ import annotations

import argparse
import resource
import time

import numpy as np

import common
from hfrad.formfactors.budget import ray_budget
from hfrad.formfactors.engine import FormFactorEngine
from hfrad.formfactors.hmatrix import HMatrixOptions, build_hmatrix
from hfrad.lowrank.operator import operator_factorization


def peak_rss_gb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20


def sampled_row_error(scene, engine, hm, rows: int, seed: int = 7) -> float:
    """Relative error of diag(rho) F~ on ``rows`` exact rows, one from each stratum of the tree order."""
    n = hm.n
    rng = np.random.default_rng(seed)
    edges = np.linspace(0, n, rows + 1)
    pos = np.minimum(np.floor(edges[:-1] + rng.random(rows) * np.diff(edges)).astype(np.int64), n - 1)
    exact = engine.block(hm.perm[pos], hm.perm)
    E = np.zeros((n, rows))
    E[pos, np.arange(rows)] = 1.0
    approx = hm.rmatmat(E).T                       # rows of F~ = (F~^T e_i)^T
    rho = scene.reflectance.max(axis=1)[hm.perm][pos, None]
    return float(np.linalg.norm(rho * (exact - approx)) / np.linalg.norm(rho * exact))


def run_size(scene_name: str, patches: int, eps_list, rows: int, options: HMatrixOptions, exact_pass: bool) -> dict:
    scene = common.load_bench_scene(scene_name, patches)
    n = scene.n_patches
    engine = FormFactorEngine(scene, ray_threads=None, ray_budget=ray_budget(scene, min(eps_list) / 4))
    t0 = time.perf_counter()
    hm = build_hmatrix(scene, engine, options)
    build_s = time.perf_counter() - t0
    row = {"n": n, "build_s": build_s, **{k: v for k, v in hm.info.items() if k != "n"}}
    rho = scene.reflectance.max(axis=1)[hm.perm]
    norm2 = hm.frobenius2(rho)
    for eps in eps_list:
        t = time.perf_counter()
        lr = operator_factorization(lambda X: rho[:, None] * hm.matmat(X), lambda X: hm.rmatmat(rho[:, None] * X),
                                    n, norm2, eps=eps, dtype=np.float32, rng=np.random.default_rng(0))
        row[f"rank_{eps}"] = lr.rank
        row[f"factor_s_{eps}"] = time.perf_counter() - t
        row[f"products_{eps}"] = lr.info.get("vectors")
        row[f"achieved_{eps}"] = lr.relative_error
    t = time.perf_counter()
    row["row_error"] = sampled_row_error(scene, engine, hm, rows)
    row["check_s"] = time.perf_counter() - t
    row["peak_rss_gb"] = peak_rss_gb()
    engine.close()
    if exact_pass:
        import hfrad
        for eps in eps_list:
            t = time.perf_counter()
            fac = hfrad.factorize(scene, eps, far_field="exact")
            row[f"exact_pass_s_{eps}"] = time.perf_counter() - t
            row[f"exact_rank_{eps}"] = fac.rank
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="cornell")
    ap.add_argument("--patches", default="40000")
    ap.add_argument("--eps", default="0.05,0.02")
    ap.add_argument("--rows", type=int, default=128, help="exact rows for the error check")
    ap.add_argument("--leaf", type=int, default=HMatrixOptions.leaf_size)
    ap.add_argument("--eta", type=float, default=HMatrixOptions.eta)
    ap.add_argument("--probe-size", type=int, default=HMatrixOptions.probe_size)
    ap.add_argument("--tolerance", type=float, default=HMatrixOptions.tolerance)
    ap.add_argument("--exact-pass", action="store_true", help="also run today's exact pass (slow)")
    args = ap.parse_args()
    eps_list = [float(e) for e in args.eps.split(",")]
    options = HMatrixOptions(leaf_size=args.leaf, eta=args.eta, probe_size=args.probe_size, tolerance=args.tolerance)
    rows = []
    for p in [int(x) for x in args.patches.split(",")]:
        rows.append(run_size(args.scene, p, eps_list, args.rows, options, args.exact_pass))
        common.print_table(f"H-matrix of F, {args.scene}", rows, _columns(eps_list, args.exact_pass))
    common.write_json(f"hmatrix-{args.scene}-{'-'.join(str(r['n']) for r in rows)}",
                      {"machine": common.machine(), "options": vars(args), "rows": rows})


def _columns(eps_list, exact_pass: bool) -> list:
    cols = ["n", "build_s", "pairs_share", "exact_pairs", "kernel_pairs", "time_exact", "time_aca", "time_probes",
            "time_visibility", "storage_floats", "mean_rank", "row_error"]
    for eps in eps_list:
        cols += [f"rank_{eps}", f"factor_s_{eps}"]
        if exact_pass:
            cols += [f"exact_rank_{eps}", f"exact_pass_s_{eps}"]
    return cols + ["peak_rss_gb"]


if __name__ == "__main__":
    main()
