"""The optimisation: goals as linear constraints on the intensities, solved with SciPy.

With ``q_t(s) = a_t + M_t s`` (see :mod:`hfrad.inverse.transfer`) and area
weights w_t, every goal is linear in s:

- ``min g``:        a_t + M_t s >= g            (every patch)
- ``max g``:        a_t + M_t s <= g            (every patch)
- ``mean g``:       w_t . (a_t + M_t s) >= g    (min_power: maintained mean)
- ``uniformity u``: q_i >= u w_t . q for every patch i, i.e. min / mean >= u
  (linear because the mean is linear in s)

``min_power`` minimises ``sum_e s_e A_e Y(color_e)`` (luminance-weighted watts)
over these constraints and ``0 <= s <= max`` with ``scipy.optimize.linprog``
(HiGHS). ``least_squares`` fits the means, ``min sum_t ((w_t . q_t - g_t) /
g_t)^2`` over ``0 <= s <= max`` with ``scipy.optimize.lsq_linear`` (BVLS); its
other goals are checked, not enforced.

An infeasible LP is explained by a deletion filter over the goals and the
emitters' ``max`` bounds: each item is dropped in turn and kept out if the rest
is still infeasible; what remains is an irreducible infeasible set, goals that
conflict with each other (and with the fixed background light), each of them
needed for the conflict. It costs one small LP per item.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linprog, lsq_linear

from ..render.falsecolor import photometric
from .spec import DesignSpec
from .transfer import Response

#: a goal counts as met when violated by at most this fraction of its value
GOAL_RTOL = 1e-4


@dataclass
class Item:
    """One goal (rows ``A s <= b``) or one emitter bound, with its label for reports."""

    label: str
    A: np.ndarray | None = None
    b: np.ndarray | None = None
    emitter: int | None = None


def _rows(A: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Scale each row of ``A s <= b`` to a max-norm of 1 so HiGHS' absolute tolerances are relative."""
    scale = np.maximum(np.abs(A).max(axis=1, initial=0.0), np.abs(b))
    scale[scale == 0] = 1.0
    return A / scale[:, None], b / scale


def goal_items(spec: DesignSpec, resp: Response) -> list[Item]:
    """Every goal of every target as linear rows, then every finite emitter ``max``."""
    items = []
    for t, M, a, w in zip(spec.targets, resp.matrix, resp.offset, resp.weight):
        if t.min is not None:
            items.append(Item(f"{t.name}.min", *_rows(-M, a - t.min)))
        if t.max is not None:
            items.append(Item(f"{t.name}.max", *_rows(M, t.max - a)))
        if t.mean is not None:
            items.append(Item(f"{t.name}.mean", *_rows(-(w @ M)[None], np.array([w @ a - t.mean]))))
        if t.uniformity is not None:
            u = t.uniformity
            items.append(Item(f"{t.name}.uniformity", *_rows(-(M - u * (w @ M)), a - u * (w @ a))))
    items += [Item(f"{e.name}.max", emitter=j) for j, e in enumerate(spec.emitters) if np.isfinite(e.max)]
    return items


def _lp(cost: np.ndarray, items: list[Item], upper: np.ndarray):
    rows = [it for it in items if it.A is not None]
    ub = np.full(len(upper), np.inf)
    for it in items:
        if it.emitter is not None:
            ub[it.emitter] = upper[it.emitter]
    A = np.vstack([it.A for it in rows]) if rows else None
    b = np.concatenate([it.b for it in rows]) if rows else None
    return linprog(cost, A_ub=A, b_ub=b, bounds=list(zip(np.zeros(len(ub)), ub)), method="highs")


def conflicting(items: list[Item], upper: np.ndarray) -> list[str]:
    """Labels of an irreducible infeasible subset of ``items`` (deletion filter)."""
    keep = list(items)
    zero = np.zeros(len(upper))
    for it in list(items):
        trial = [x for x in keep if x is not it]
        if _lp(zero, trial, upper).status == 2:   # still infeasible without it: not needed
            keep = trial
    return [it.label for it in keep]


@dataclass
class Solution:
    """What the optimiser found.

    ``intensity`` is None when infeasible; ``conflicts`` lists the goals that
    conflict then; ``objective`` is watts (min_power) or the sum of squared
    relative mean residuals (least_squares).
    """

    status: str
    message: str
    intensity: np.ndarray | None
    objective: float | None
    conflicts: list
    lp_solves: int


def power_per_intensity(spec: DesignSpec, scene) -> np.ndarray:
    """(m,) W per unit intensity: area of the emitter times the luminance of its colour."""
    return np.array([scene.areas[e.patches].sum() * float(photometric(e.color)) for e in spec.emitters])


def optimise(spec: DesignSpec, resp: Response, cost: np.ndarray) -> Solution:
    """Solve the design problem of ``spec`` on the response ``resp``; never raises for infeasibility."""
    upper = np.array([e.max for e in spec.emitters])
    if spec.objective == "least_squares":
        return _least_squares(spec, resp)
    items = goal_items(spec, resp)
    res = _lp(cost, items, upper)
    if res.status == 0:
        return Solution("optimal", str(res.message), np.maximum(res.x, 0.0), float(cost @ res.x), [], 1)
    if res.status == 2:
        labels = conflicting(items, upper)
        if len(labels) == 1:
            why = (f"{labels[0]} cannot be met by any intensities on its own (the fixed background light "
                   "alone breaks it, or the emitters cannot reach it)")
        else:
            why = "no intensities meet all goals; these conflict: " + ", ".join(labels)
        return Solution("infeasible", why, None, None, labels, 1 + len(items))
    return Solution("failed", f"linprog (HiGHS) stopped: {res.message}", None, None, [], 1)


def _least_squares(spec: DesignSpec, resp: Response) -> Solution:
    rows, rhs = [], []
    for t, M, a, w in zip(spec.targets, resp.matrix, resp.offset, resp.weight):
        if t.mean is not None:
            g = t.mean if t.mean > 0 else 1.0
            rows.append((w @ M) / g)
            rhs.append((t.mean - w @ a) / g)
    upper = np.array([e.max for e in spec.emitters])
    res = lsq_linear(np.array(rows), np.array(rhs), bounds=(np.zeros(len(upper)), upper), method="bvls")
    s = np.clip(res.x, 0.0, upper)
    r = np.array(rows) @ s - np.array(rhs)
    return Solution("optimal" if res.status > 0 else "failed", str(res.message), s, float(r @ r), [], 0)
