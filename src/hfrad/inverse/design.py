"""``hfrad.design(fac, spec)``: which luminaires, how strong, to meet lighting goals at least power."""

from __future__ import annotations

import json
import math
import time
import warnings
from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np

from ..errors import InputError
from ..progress import ProgressCallback, report
from .optimize import GOAL_RTOL, optimise, power_per_intensity
from .spec import DesignSpec, Target, parse_spec
from .transfer import adjoint_response, adjoint_rows, adjoint_solves, background_exitance, design_exitance, response

__all__ = ["design", "DesignResult"]


@dataclass
class DesignResult:
    """The outcome of :func:`design`.

    Attributes
    ----------
    report : dict
        JSON-ready summary (see :func:`design` for the fields).
    spec : DesignSpec
    exitance : (n, 3) float or None, W/m^2, user patch order
        The designed emission (background included); None when infeasible.
    radiosity : (n, 3) float or None, W/m^2
        Its radiosity from the verification solve (None when infeasible or not verified).
    """

    report: dict
    spec: DesignSpec
    exitance: np.ndarray | None = None
    radiosity: np.ndarray | None = field(default=None, repr=False)

    @property
    def feasible(self) -> bool:
        return bool(self.report["feasible"])

    @property
    def intensity(self) -> dict[str, float | None]:
        """Emitter name -> designed intensity (None when infeasible)."""
        return {e["name"]: e["intensity"] for e in self.report["emitters"]}

    def to_json(self) -> str:
        return json.dumps(self.report, indent=2, allow_nan=False)


def _stats(values: np.ndarray, weight: np.ndarray) -> dict[str, float]:
    mean = float(weight @ values)
    lo = float(values.min())
    return {"min": lo, "mean": mean, "max": float(values.max()),
            "uniformity": lo / mean if mean > 0 else None}


def _met(t: Target, stats: dict, objective: str) -> dict[str, bool]:
    """Goal -> met (within GOAL_RTOL of its value). A least-squares mean is a fit, not a goal to meet."""
    out = {}
    for goal, g in t.goals().items():
        tol = GOAL_RTOL * (abs(g) if g else max(abs(stats["max"]), 1e-300))
        if goal == "min":
            out[goal] = stats["min"] >= g - tol
        elif goal == "max":
            out[goal] = stats["max"] <= g + tol
        elif goal == "mean" and objective == "min_power":
            out[goal] = stats["mean"] >= g - tol
        elif goal == "uniformity":
            out[goal] = stats["uniformity"] is not None and stats["uniformity"] >= g - GOAL_RTOL
    return out


def _solver_accuracy(fac) -> dict:
    """The factorization's accuracy figures, by whichever public name this version offers."""
    out = {"relative_error": float(fac.relative_error)}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        bound = fac.error_estimate().bound
    if bound is not None:
        b = np.atleast_1d(np.asarray(bound, dtype=np.float64))
        out["radiosity_error_bound"] = [float(x) if math.isfinite(x) else None for x in b]
    return out


def _mean_error(fac, target: Target, absolute: np.ndarray) -> float | None:
    """A figure for the error of the target's area-weighted mean quantity, from the radiosity's ``||e_c||_A``.

    The quantity is ``q_i = sum_c W_c s_ic B_ic + ...`` (``s = 1`` for radiosity, ``1 / rho_ic`` for
    irradiance), so the mean's error ``sum_c W_c sum_i w_i s_ic e_ic`` is at most
    ``sum_c W_c sqrt(sum_i w_i^2 s_ic^2 / A_i) ||e_c||_A`` (Cauchy-Schwarz). None where a target
    patch is black in a channel (its irradiance is read from F, not from B).
    """
    from ..render.falsecolor import photometric

    areas = np.asarray(fac.scene.areas, np.float64)[target.patches]
    w = areas / areas.sum()
    if target.quantity == "radiosity":
        s = np.ones((len(w), 3))
    else:
        rho = np.asarray(fac.reflectance, np.float64)[target.patches]
        if (rho <= 0).any():
            return None
        s = 1.0 / rho
    spread = np.sqrt(((w[:, None] * s) ** 2 / areas[:, None]).sum(axis=0))      # (3,)
    unit = "lux" if target.quantity == "irradiance_lux" else "W/m2"
    return float(photometric(spread * np.asarray(absolute, np.float64), unit))


def _margins(entry: dict) -> dict:
    """How far each goal is met (positive) or missed (negative), in the target's unit."""
    st, out = entry["achieved"], {}
    for goal, g in entry["goals"].items():
        if goal == "min":
            out[goal] = st["min"] - g
        elif goal == "max":
            out[goal] = g - st["max"]
        elif goal == "mean":
            out[goal] = st["mean"] - g
        elif goal == "uniformity" and st["uniformity"] is not None:
            out[goal] = st["uniformity"] - g
    return out


def design(fac, spec: "Mapping[str, Any] | DesignSpec | str", *, method: str = "auto", verify: bool = True,
           progress: ProgressCallback = None) -> DesignResult:
    """Find emitter intensities that meet the spec's goals (inverse lighting design).

    Parameters
    ----------
    fac : HFactorization
        A factorization with its scene (``hfrad.load("room.hfr")``).
    spec : dict, DesignSpec, or path of a .json / .toml spec
        See :mod:`hfrad.inverse.spec`.
    method : {"auto", "forward", "adjoint"}
        How the response of the targets to the emitters is computed.
        ``forward``: one solve per emitter (plus one for a fixed background),
        every target patch's response to it. ``adjoint``: one transposed solve
        per row the goals need (every patch of a target with min / max /
        uniformity goals, one row for a mean-only target), each row's response
        to every emitter at once; plus one forward solve for the report.
        ``auto`` takes the one with fewer solves.
    verify : bool
        Check the answer with an independent full solve of the chosen emission
        (one more ``fac.solve``); fills ``report['verified']``.
    progress : callable (done, total), optional
        Radiosity solves done, of at most one per emitter, one for the
        background and one for the verification.

    Returns
    -------
    DesignResult
        ``report`` holds ``feasible``, ``status``, ``message``, ``objective``
        (name, value, unit), ``total_power_W``, ``emitters`` (name, patches,
        area_m2, color, max, intensity, exitance_W_m2, power_W), ``targets``
        (name, quantity, unit, patches, goals, achieved min / mean / max /
        uniformity, met per goal), ``conflicts`` (goals that cannot hold
        together, when infeasible), ``evaluations`` (radiosity solves, i.e.
        right-hand sides, the optimiser used), ``time_s`` and ``timings``,
        ``verified`` and ``factorization``.

    Raises
    ------
    InputError
        A ``method`` other than "auto", "forward" or "adjoint", or a factorization without a scene.
    SpecError
        Malformed spec (names the field). Infeasibility is not an error: it
        is reported with ``feasible: false`` and the conflicting goals.

    Notes
    -----
    Cost: one batched ``fac.solve`` with one right-hand side per emitter (plus
    one for a fixed background), O(m n k), then an LP or bounded least-squares
    problem of m unknowns; plus O(|T0| n) form factors for target patches of
    zero reflectance when their irradiance is asked for (see
    :mod:`hfrad.inverse.transfer`). A dense approach would instead factor the
    n x n matrix (I - RF): O(n^3).

    Examples
    --------
    >>> import hfrad
    >>> fac = hfrad.factorize(hfrad.load_scene("cornell", patches=300), eps=1e-3)   # doctest: +SKIP
    >>> r = hfrad.design(fac, {"emitters": [{"material": "light", "max": 100}],
    ...                        "targets": [{"material": "floor", "quantity": "irradiance", "min": 5}]})  # doctest: +SKIP
    >>> r.feasible                                                                  # doctest: +SKIP
    True
    """
    t_start = time.perf_counter()
    if method not in ("auto", "forward", "adjoint"):
        raise InputError(f"method must be 'auto', 'forward' or 'adjoint', got {method!r}")
    scene = fac.scene
    if scene is None:
        raise InputError("the factorization carries no scene (patches); load it from an .hfr file "
                         "written by `hfrad precompute` or build it with hfrad.factorize(scene)")
    if not isinstance(spec, DesignSpec):
        spec = parse_spec(spec, scene)
    forward_solves = len(spec.emitters) + int(bool(background_exitance(spec, scene).any()))
    # the adjoint method needs one more forward solve for the report when some target has no per-patch rows
    adjoint_total = adjoint_solves(spec) + int(any(r != "patches" for r in adjoint_rows(spec)))
    if method == "auto":
        method = "adjoint" if adjoint_total < forward_solves else "forward"
    total = (forward_solves if method == "forward" else adjoint_total) + 1
    bar = None if progress is None else (lambda d, t: progress(d, total))
    resp = (response if method == "forward" else adjoint_response)(fac, spec, progress=bar)
    t1 = time.perf_counter()
    cost = power_per_intensity(spec, scene)
    sol = optimise(spec, resp, cost)
    t_opt = time.perf_counter() - t1
    s = sol.intensity
    feasible_lp = s is not None
    E = B = measured = None
    t_measure = 0.0
    evaluations = resp.evaluations
    if feasible_lp:
        E = design_exitance(spec, scene, s)
        if not resp.complete or verify:
            # one solve of the chosen emission from scratch (not by superposition): every target patch
            B, measured, t_measure = _measure(fac, spec, E, resp.quantities)
        if not resp.complete:
            evaluations += 1                              # the adjoint rows do not cover every patch
    values = (resp.values(s) if resp.complete else measured) if feasible_lp else None
    area_w = [scene.areas[t.patches] / scene.areas[t.patches].sum() for t in spec.targets]
    targets_out, all_met = [], feasible_lp
    for j, t in enumerate(spec.targets):
        entry = {"name": t.name, "quantity": t.quantity, "unit": t.unit, "patches": int(len(t.patches)),
                 "area_m2": float(scene.areas[t.patches].sum()), "goals": t.goals(), "achieved": None, "met": None}
        if feasible_lp:
            st = _stats(values[j], area_w[j])
            entry["achieved"] = st
            entry["met"] = _met(t, st, spec.objective)
            all_met &= all(entry["met"].values())
            if spec.objective == "least_squares" and t.mean is not None:
                entry["mean_relative_residual"] = (st["mean"] - t.mean) / t.mean if t.mean else st["mean"]
        targets_out.append(entry)
    emitters_out = []
    for j, e in enumerate(spec.emitters):
        x = float(s[j]) if feasible_lp else None
        emitters_out.append({
            "name": e.name, "patches": int(len(e.patches)), "area_m2": float(scene.areas[e.patches].sum()),
            "color": e.color.tolist(), "max": e.max if math.isfinite(e.max) else None, "intensity": x,
            "exitance_W_m2": (x * e.color).tolist() if feasible_lp else None,
            "power_W": x * float(cost[j]) if feasible_lp else None})
    feasible = bool(all_met)
    status, message = sol.status, sol.message
    if feasible_lp and not feasible:
        unmet = [f"{t['name']}.{g}" for t in targets_out for g, ok in t["met"].items() if not ok]
        status = "goals_not_met"
        message = f"best fit leaves these goals unmet: {', '.join(unmet)}"
    out = {
        "feasible": feasible,
        "status": status,
        "message": message,
        "objective": {"name": spec.objective, "value": sol.objective,
                      "unit": "W" if spec.objective == "min_power" else "sum of squared relative residuals"},
        "total_power_W": float(cost @ s) if feasible_lp else None,
        "emitters": emitters_out,
        "targets": targets_out,
        "conflicts": sol.conflicts,
        "background": spec.background,
        "evaluations": int(evaluations),
        "method": resp.method,
        "lp_solves": int(sol.lp_solves),
        "time_s": None,
        "timings": {"response_s": resp.seconds, "optimise_s": t_opt},
        "factorization": {"n_patches": int(fac.n_patches), "rank": int(fac.rank), "eps": float(fac.eps)},
        "verified": None,
    }
    # time_s is the design; a solve done only to verify it is timed in 'verified'
    out["time_s"] = time.perf_counter() - t_start - (t_measure if resp.complete else 0.0)
    if feasible_lp and verify:
        out["verified"] = _verify(fac, spec, resp, resp.values(s), measured, t_measure)
    if B is not None:
        # this design's error figure (from the rows of F kept from the pass) and each goal's margin beside it
        error = fac.solution_error(E, B)
        out["radiosity_error"] = error.as_dict()
        for t, entry in zip(spec.targets, targets_out):
            entry["margin"] = _margins(entry)
            entry["mean_error"] = _mean_error(fac, t, error.absolute)
    report(progress, total, total)
    return DesignResult(out, spec, E, B)


def _measure(fac, spec: DesignSpec, E: np.ndarray, quantities) -> tuple[np.ndarray, list, float]:
    """Radiosity of ``E`` by one full solve, and every target patch's quantity from it."""
    t0 = time.perf_counter()
    B = np.asarray(fac.solve(E), dtype=np.float64)
    q = [quantities(t, B[:, :, None], E[:, :, None])[:, 0] for t in spec.targets]
    return B, q, time.perf_counter() - t0


def _verify(fac, spec: DesignSpec, resp, predicted: list, measured: list, seconds: float) -> dict:
    """Compare the optimiser's prediction with the full solve's measurement, and re-check every goal."""
    targets, deviation, met = [], 0.0, True
    for t, kind, q_pred, q in zip(spec.targets, resp.rows, predicted, measured):
        wt = fac.scene.areas[t.patches] / fac.scene.areas[t.patches].sum()
        st = _stats(q, wt)
        ok = _met(t, st, spec.objective)
        met &= all(ok.values())
        if kind != "none":
            q_cmp = q if kind == "patches" else np.array([wt @ q])    # what the optimiser's rows predicted
            scale = max(float(np.abs(q_pred).max()), 1e-300)
            deviation = max(deviation, float(np.abs(q_cmp - q_pred).max()) / scale)
        targets.append({"name": t.name, **st, "met": ok})
    return {"method": "one fac.solve of the designed emission, quantities re-measured from its radiosity",
            "evaluations": 1, "time_s": seconds, "goals_met": bool(met),
            "max_relative_deviation": deviation, "targets": targets,
            "solver": _solver_accuracy(fac)}
