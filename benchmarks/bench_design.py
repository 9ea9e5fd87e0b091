"""Benchmark: inverse lighting design (``hfrad.design``) through HF vs through a dense LU.

The office of ``examples/office`` (``--patches`` patches), three specs:

* ``office``: ``examples/office/spec.json``, the six luminaires as six emitters;
* ``every-patch``: the same targets, but every patch of the ceiling (luminaires
  included) is an emitter of its own ("painting with light": m in the hundreds);
* ``every-patch, means``: those emitters, and only mean goals (550 lux on each desk,
  200 on the floor): ``design`` takes the adjoint method, one transposed solve per goal.

For each, the same :func:`hfrad.design` call runs twice, once on the HF factorization
(``fac.solve``, Woodbury, O(nk) per right-hand side) and once on an exact dense solver
(``scipy.linalg.lu_factor`` of ``I - R_c F`` for the three channels, then ``lu_solve``
per evaluation). The table gives the radiosity solves (evaluations) the optimiser used,
the design's wall time, and the
one-off costs (form factors, HF / LU), plus what refactoring the dense matrix at every
evaluation would cost (3 LU factorizations per evaluation, measured once and multiplied).
Accuracy: the HF design's least power against the exact (dense) design's, and the HF
design's worst goal violation in the exact model (relative to the goal; 0 = every goal
holds). Intensities themselves are not compared: with near-equivalent luminaires the
least-power LP has near-degenerate optima, and a 0.1% change of the model can trade one
luminaire against another at the same power.

Run:  python benchmarks/bench_design.py [--patches 3000] [--eps 0.01]
Writes benchmarks/results/design.json (or --name).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np
import scipy.linalg as sla

import common
import hfrad
from hfrad.formfactors.blocks import form_factor_matrix
from hfrad.inverse import design, parse_spec
from hfrad.inverse.optimize import goal_items
from hfrad.inverse.transfer import adjoint_response, response
from hfrad.pipeline import factorize

OFFICE = Path(__file__).resolve().parent.parent / "examples" / "office"


class DenseSolver:
    """Exact dense solves, ``lu_factor(I - R_c F)`` per channel, with the attributes :func:`hfrad.design` reads."""

    def __init__(self, scene, F, reflectance):
        self.scene, self.reflectance, self.params = scene, np.asarray(reflectance, np.float64), {}
        self.n_patches, self.rank, self.eps, self.relative_error = scene.n_patches, scene.n_patches, 0.0, 0.0
        n = scene.n_patches
        self._lu = [sla.lu_factor(np.eye(n) - self.reflectance[:, c:c + 1] * F, check_finite=False)
                    for c in range(3)]
        self.solves = 0

    def solve(self, exitance, trans: str = "N", *, transpose: bool = False):
        """(n, 3[, m]) radiosity (or the adjoint solution with ``trans='T'``) for (n, 3[, m]) exitance."""
        E = np.asarray(exitance, np.float64)
        self.solves += E.shape[2] if E.ndim == 3 else 1
        t = 1 if (transpose or trans == "T") else 0
        out = np.empty_like(E)
        for c in range(3):
            out[:, c] = sla.lu_solve(self._lu[c], E[:, c], trans=t, check_finite=False)
        return out


def every_patch_spec(spec: dict, scene, *, means_only: bool = False) -> dict:
    """Every ceiling patch an emitter; with ``means_only`` the goals are the desks' and floor's means."""
    ceiling = np.flatnonzero(np.isin(scene.material, [scene.material_names.index(m)
                                                       for m in ("ceiling", "luminaire")]))
    out = dict(spec)
    out["emitters"] = [{"name": f"p{i}", "patches": [int(i)], "max": 60.0} for i in ceiling]
    if means_only:
        out["targets"] = [{k: v for k, v in t.items() if k not in ("min", "max", "uniformity")} | {"mean": 550.0}
                          for t in spec["targets"] if t["name"].startswith("desk")]
        out["targets"].append({"name": "floor", "material": "floor", "quantity": "irradiance_lux", "mean": 200.0})
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--patches", type=int, default=3000)
    p.add_argument("--eps", type=float, default=0.01)
    p.add_argument("--repeat", type=int, default=3, help="design runs per case (best is reported)")
    p.add_argument("--name", default="design", help="results/NAME.json")
    common.add_blas_arg(p)
    args = p.parse_args()
    m = common.header("inverse design: HF vs dense LU", args.blas_threads)
    load_before = os.getloadavg()

    scene = hfrad.load_scene(str(OFFICE / "office.obj"), patches=args.patches)
    n = scene.n_patches
    t0 = time.perf_counter()
    fac = factorize(scene, eps=args.eps)
    t_hf = time.perf_counter() - t0
    t0 = time.perf_counter()
    F = form_factor_matrix(scene)
    t_ff = time.perf_counter() - t0
    t0 = time.perf_counter()
    dense = DenseSolver(scene, F, fac.reflectance)
    t_lu = time.perf_counter() - t0
    del F

    base = json.loads((OFFICE / "spec.json").read_text())
    rows, cases = [], []
    for name, raw in (("office", base), ("every-patch", every_patch_spec(base, scene)),
                      ("every-patch, means", every_patch_spec(base, scene, means_only=True))):
        spec = parse_spec(raw, scene)
        runs = {}
        for solver_name, solver in (("HF", fac), ("dense LU", dense)):
            total = common.best_of(lambda: design(solver, spec), args.repeat, max_seconds=60.0)
            method = total.result.report["method"]
            solves = common.best_of(lambda: (response if method == "forward" else adjoint_response)(solver, spec),
                                    args.repeat, max_seconds=60.0)
            r = total.result.report
            runs[solver_name] = {"design_s": total.best, "design_times_s": total.times,
                                 "solves_s": solves.best, "evaluations": r["evaluations"],
                                 "optimise_s": r["timings"]["optimise_s"], "feasible": r["feasible"],
                                 "power_W": r["total_power_W"], "intensity": [e["intensity"] for e in r["emitters"]]}
        hf, lu = runs["HF"], runs["dense LU"]
        # the HF design checked in the exact model: worst goal violation, relative to the goal
        exact = goal_items(spec, (response if method == "forward" else adjoint_response)(dense, spec))
        s_hf = np.array(hf["intensity"], float)
        violation = max(float((it.A @ s_hf - it.b).max()) for it in exact if it.A is not None)
        evals = hf["evaluations"]
        refactor = evals * t_lu      # a dense solver that refactors (I - R_c F) at every evaluation
        case = {"spec": name, "emitters": len(spec.emitters), "evaluations": evals, "runs": runs,
                "power_rel_diff": (hf["power_W"] - lu["power_W"]) / lu["power_W"],
                "hf_design_worst_goal_violation_in_exact_model": max(violation, 0.0),
                "method": method, "dense_refactor_per_eval_s": refactor}
        cases.append(case)
        rows.append({"spec": name, "m": len(spec.emitters), "method": method, "evals": evals,
                     "HF design s": hf["design_s"], "LU design s": lu["design_s"],
                     "HF solves s": hf["solves_s"], "LU solves s": lu["solves_s"],
                     "LU refactor/eval s": refactor, "LP s": hf["optimise_s"],
                     "power HF/LU-1": case["power_rel_diff"], "exact viol.": max(violation, 0.0)})
    load_after = os.getloadavg()
    common.print_table(f"office, n = {n}, HF rank {fac.rank} (eps {args.eps}); one-off: form factors "
                       f"{t_ff:.1f} s, HF precompute {t_hf:.1f} s, 3 dense LU {t_lu:.1f} s",
                       rows, list(rows[0]))
    print(f"load average before {load_before[0]:.2f}, after {load_after[0]:.2f}")
    path = common.write_json(args.name, {
        "machine": m, "n_patches": n, "eps": args.eps, "rank": fac.rank,
        "one_off_s": {"form_factors_dense": t_ff, "hf_precompute": t_hf, "dense_lu_3_channels": t_lu},
        "loadavg_before": load_before, "loadavg_after": load_after, "cases": cases})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
