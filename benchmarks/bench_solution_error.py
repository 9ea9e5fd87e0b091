"""The per-solve error figure against the truth, and what it costs (issue 42).

For each scene, ``hfrad.factorize`` (eps 0.02 unless told) builds the factorization with its
stored rows of F; then for 20+ emissions of several kinds the figure ``fac.solve(E,
return_error=True)`` gives is compared with the true error against an exact dense LU solve
with the full-ray form factors ``hfrad.form_factor_matrix`` (both relative to the reflected
light ``B - E``, area norm, per channel). Kinds: the scene's lights, the same lights tinted
blue, one patch, 20 random patches, random exitance everywhere, a lamp-like falloff from a
point, and (the office) catalogue luminaires of ``examples/office/layout.json`` through
``hfrad.lighting.LightingModel``. Adjoint solves (``trans="T"``) are checked in the dual norm.

Columns: figure / true error (min, median, max over emissions and channels), the true errors'
range, and the cost: a solve of one emission against its figure (best of 5, 1 BLAS thread),
the stored rows' bytes against the factors' and the whole .hfr.

``--redraws K`` also measures the stated failure probability: the sample of rows is drawn again K times
(the pass's design with seeds 1..K; the rows from the full-ray F, so this simulates the sample rather than
reading the stored one) and every emission's figure is recomputed from each draw; the share of figures
below the true error, by norm (forward: area; adjoint: dual), is what the stated probability claims.

Not a test: prints tables and writes results/solution-error-CASES.json.
Run: ``PYTHONPATH=src python3 benchmarks/bench_solution_error.py [--cases cornell,conference,office,
conference-near] [--patches 3000] [--eps 0.02] [--cache DIR]``; ``conference-near`` forces the near-field
solver (``near_field=120``) on the conference room (its F is computed once for both). ``--cache DIR`` keeps
each case's factorization (``CASE-nPATCHES-epsEPS-kKERNEL.hfr``) and full-ray F (``SCENE-nPATCHES-kKERNEL-F.npy``,
KERNEL the form-factor kernel's version) there and reuses them on the next run:
the figure is computed at solve time from what the pass stored, so a change to it needs no new pass (the
precompute time is then the file's load time).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
from scipy.linalg import lu_factor, lu_solve

import common
from hfrad.errors import AccuracyWarning

ROOT = Path(__file__).resolve().parents[1]
CASES = {
    "cornell": ("cornell", {}),
    "conference": (str(common.SHARED_SCENES / "conference" / "conference.ply"), {"area_light": (8.0, 8.0, 8.0)}),
    "office": (str(ROOT / "examples" / "office" / "office.obj"), {}),
}
#: Cases solved through the near-field solver (near_field=120 forced): the same scene and F.
NEAR_CASES = {"conference-near": "conference"}
#: Full-ray F by (scene source, patches): the near-field case reuses its scene's.
_F_CACHE: dict = {}


def emissions(scene, count: int, rng) -> list[tuple[str, np.ndarray]]:
    n = scene.n_patches
    c = np.asarray(scene.centroids)
    E0 = np.asarray(scene.emission, float)
    out = [("lights", E0), ("lights blue", E0 * [0.2, 0.4, 1.0])]
    kinds = ("patch", "20 patches", "random", "falloff")
    while len(out) < count:
        kind = kinds[len(out) % len(kinds)]
        E = np.zeros((n, 3))
        if kind == "patch":
            E[rng.integers(n)] = 10.0
        elif kind == "20 patches":
            E[rng.choice(n, 20, replace=False)] = rng.random((20, 3)) * 50
        elif kind == "random":
            E = rng.random((n, 3))
        else:
            p = c[rng.integers(n)]
            E = (1.0 / (0.05 + ((c - p) ** 2).sum(axis=1)))[:, None] * np.ones(3)
        out.append((kind, E))
    return out


def luminaire_emissions(fac, scene) -> list[tuple[str, np.ndarray]]:
    """The office's catalogue luminaires: their light reflected once off every patch, one by one and all."""
    from hfrad.lighting import LightingModel, read_layout

    model = LightingModel(fac, read_layout(ROOT / "examples" / "office" / "layout.json"))
    E = model.exitance_basis
    out = [(f"luminaire {j}", E[:, :, j]) for j in range(min(E.shape[2], 4))]
    return out + [("all luminaires", E.sum(axis=2))]


def norm(weights, X):
    return np.sqrt(np.einsum("i,ic->c", weights, X ** 2))


def _kernel() -> int:
    """The form-factor kernel's version: cached files of another kernel are not reused (a changed kernel
    changes F, and an old F would give wrong true errors)."""
    from hfrad.formfactors import KERNEL_VERSION

    return KERNEL_VERSION


def _factorization(name: str, scene, patches: int, eps: float, cache: Path | None):
    """The case's factorization and whether it came from ``cache`` (else made, and kept there)."""
    import hfrad

    path = None if cache is None else cache / f"{name}-n{patches}-eps{eps}-k{_kernel()}.hfr"
    if path is not None and path.exists():
        return hfrad.load(path), True
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", AccuracyWarning)
        fac = hfrad.factorize(scene, eps=eps, **({"near_field": 120} if name in NEAR_CASES else {}))
    if path is not None:
        fac.save(path)
    return fac, False


def _full_ray_F(name: str, scene, patches: int, cache: Path | None) -> np.ndarray:
    """The scene's full-ray F: from ``cache/SCENE-F.npy`` if there, else computed (and kept there)."""
    import hfrad

    path = None if cache is None else cache / f"{NEAR_CASES.get(name, name)}-n{patches}-k{_kernel()}-F.npy"
    if path is not None and path.exists():
        return np.load(path)
    F = np.asarray(hfrad.form_factor_matrix(scene))
    if path is not None:
        np.save(path, F)
    return F


def redraw_rates(fac, F: np.ndarray, solved: list, redraws: int) -> dict:
    """Figures / true errors over ``redraws`` new draws of the sample (rows from F): by norm, the share
    below 1 and over 10, and min / median / max."""
    from hfrad.solve.samples import SampledRows

    perm, samples = fac.perm, fac.stats.samples
    Fi = np.ascontiguousarray(F[np.ix_(perm, perm)], np.float32)
    rho = np.asarray(fac.reflectance, np.float64)[perm]
    gain = fac.stats.reflection_gain(rho)
    ratios = {"N": [], "T": []}
    for seed in range(1, redraws + 1):
        draw = SampledRows.design(len(perm), samples.weights, rho, seed=seed)
        draw.record(0, len(perm), Fi)
        draw = draw.trimmed(samples.nbytes * 1.01)          # as many rows as the stored sample keeps
        for trans, E, B, true in solved:
            err = draw.figure(E[perm][:, :, None], B[perm][:, :, None], rho, gain, adjoint=trans == "T")
            ratios[trans].append(err.bound[:, 0] / true)
    out = {}
    for trans, rs in ratios.items():
        q = np.concatenate(rs)
        out["forward" if trans == "N" else "adjoint"] = {
            "figures": int(q.size), "below_true": float(np.mean(q < 1)), "over_10x": float(np.mean(q > 10)),
            "min": float(q.min()), "median": float(np.median(q)), "max": float(q.max())}
    return out


def run_case(name: str, patches: int, eps: float, count: int, cache: Path | None = None, redraws: int = 0) -> dict:
    import hfrad

    source, kw = CASES[NEAR_CASES.get(name, name)]
    t0 = time.perf_counter()
    scene = hfrad.load_scene(source, patches=patches, **kw)
    fac, cached = _factorization(name, scene, patches, eps, cache)
    t_fac = time.perf_counter() - t0
    if (source, patches) not in _F_CACHE:
        _F_CACHE[(source, patches)] = _full_ray_F(name, scene, patches, cache)
    F = _F_CACHE[(source, patches)]
    rho, areas = np.asarray(fac.reflectance), np.asarray(scene.areas)
    n = scene.n_patches
    ops = [np.eye(n) - rho[:, c:c + 1] * F for c in range(3)]
    lu = {t: [lu_factor(op if t == "N" else op.T) for op in ops] for t in "NT"}
    rng = np.random.default_rng(42)
    todo = [(k, E, "N") for k, E in emissions(scene, count, rng)]
    if name == "office":
        todo += [(k, E, "N") for k, E in luminaire_emissions(fac, scene)]
    todo += [(k + " (adjoint)", E, "T") for k, E in emissions(scene, 6, np.random.default_rng(7))[2:]]
    rows, solved = [], []
    for kind, E, trans in todo:
        if not E.any():
            continue
        B, err = fac.solve(E, trans=trans, return_error=True)
        exact = np.stack([lu_solve(lu[trans][c], E[:, c]) for c in range(3)], axis=1)
        w = areas if trans == "N" else 1.0 / areas
        true = norm(w, B - exact) / norm(w, exact - E)
        rows.append({"kind": kind, "trans": trans, "true": true, "figure": err.bound, "ratio": err.bound / true,
                     "figure_kind": err.kind, "rows": err.rows})
        solved.append((trans, E, B, true))
    redrawn = redraw_rates(fac, F, solved, redraws) if redraws else None
    # cost: one emission's solve against its figure, best of 5
    E = np.asarray(scene.emission, float) if scene.emission.any() else todo[0][1]
    solve = common.best_of(lambda: fac.solve(E), 5)
    B = solve.result
    figure = common.best_of(lambda: fac.solution_error(E, B), 5)
    samples = fac.stats.samples
    factor_bytes = fac._stored_factor_bytes(fac.Q)        # the rows' budget: Q, V, K (and N, one Z: near field)
    with tempfile.TemporaryDirectory() as tmp:
        size = fac.save(Path(tmp) / "x.hfr").stat().st_size
    ratios = np.concatenate([r["ratio"] for r in rows])
    trues = np.concatenate([r["true"] for r in rows if r["trans"] == "N"])
    return {"case": name, "n": n, "rank": fac.rank, "eps": eps, "solver": fac.solver, "precompute_s": t_fac,
            "factorization_from_cache": cached,
            "emissions": len(rows), "below_true": int((ratios < 1).sum()), "over_10x": int((ratios > 10).sum()),
            "ratio_min": ratios.min(), "ratio_median": float(np.median(ratios)), "ratio_max": ratios.max(),
            "true_min": trues.min(), "true_max": trues.max(),
            "solve_ms": solve.best * 1e3, "figure_ms": figure.best * 1e3,
            "rows": f"{samples.index.size}+{samples.smooth_index.size}+{samples.dual_index.size}",
            "rows_bytes": samples.nbytes,
            "rows_share_of_factors": samples.nbytes / factor_bytes, "rows_share_of_hfr": samples.nbytes / size,
            "hfr_bytes": size, "redraws": redraws, "redrawn": redrawn, "by_emission": rows}


def kind_table(result: dict) -> list[dict]:
    out = {}
    for r in result["by_emission"]:
        key = r["kind"].split(" ")[0] if r["kind"].startswith("luminaire") else r["kind"]
        out.setdefault(key, []).append(r)
    table = []
    for kind, rs in out.items():
        q = np.concatenate([r["ratio"] for r in rs])
        t = np.concatenate([r["true"] for r in rs])
        table.append({"case": result["case"], "kind": kind, "count": len(rs), "true %": f"{100 * t.min():.3g}-{100 * t.max():.3g}",
                      "min": q.min(), "median": float(np.median(q)), "max": q.max()})
    return table


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cases", default="cornell,conference,office")
    p.add_argument("--patches", type=int, default=3000)
    p.add_argument("--eps", type=float, default=0.02)
    p.add_argument("--emissions", type=int, default=20)
    p.add_argument("--cache", type=Path, default=None, help="keep and reuse factorizations and F here")
    p.add_argument("--redraws", type=int, default=0, help="draw the sample again this many times (failure rates)")
    common.add_blas_arg(p)
    args = p.parse_args(argv)
    m = common.header("The per-solve error figure against an exact dense solve", args.blas_threads)
    results = []
    for name in common.parse_list(args.cases):
        if name not in CASES and name not in NEAR_CASES:
            print(f"unknown case {name!r}; known: {', '.join([*CASES, *NEAR_CASES])}", file=sys.stderr)
            return 2
        source = CASES[NEAR_CASES.get(name, name)][0]
        if name != "cornell" and not Path(source).exists():
            print(f"skipping {name}: {source} not found (the shared scenes)", file=sys.stderr)
            continue
        results.append(run_case(name, args.patches, args.eps, args.emissions, args.cache, args.redraws))
        common.print_table(f"{name}: figure / true error by emission kind (forward: area norm; adjoint: dual)",
                           kind_table(results[-1]), ["case", "kind", "count", "true %", "min", "median", "max"])
    common.print_table("summary", results,
                       ["case", "n", "rank", "emissions", "below_true", "over_10x", "ratio_min", "ratio_median",
                        "ratio_max", "solve_ms", "figure_ms", "rows", "rows_share_of_factors", "rows_share_of_hfr"])
    if args.redraws:
        common.print_table(f"the sample drawn {args.redraws} more times: figure / true error by norm",
                           [{"case": r["case"], "norm": k, **v} for r in results for k, v in r["redrawn"].items()],
                           ["case", "norm", "figures", "below_true", "over_10x", "min", "median", "max"])
    path = common.write_json("solution-error-" + "-".join(r["case"] for r in results),
                             {"machine": m, "args": {**vars(args), "cache": None if args.cache is None else str(args.cache)},
                              "results": results})
    print(f"\nwrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
