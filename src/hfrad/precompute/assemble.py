"""One precompute, two backends: what a column block adds, and the assembly of the solver object.

``hfrad.factorize(scene)`` runs the precompute in this process (:mod:`hfrad.precompute.local`)
or as Dask tasks (:mod:`hfrad.distributed`); the backend only decides where column
blocks, leaves and merges run. Both take a :class:`~hfrad.precompute.options.PrecomputePlan`
(validated once, :func:`~hfrad.precompute.options.plan_precompute`) and end in :func:`assemble`:
low-rank factors + near-field entries + pass statistics + parameters -> the solver object;
the matrix and blocks entry points (:mod:`hfrad.precompute.matrix`) end in its last step,
:func:`solver_object`. Per column block both do the
same (:func:`far_block`: the pass statistics, G and the near-field split in one read of F;
:func:`~hfrad.lowrank.hf.compress_leaf`), so the two give the same class, the
same ``.hfr`` contents (apart from the recorded backend and timings) and the same
error figures.
"""

from __future__ import annotations

import time

import numpy as np
import scipy.sparse as sp

from ..errors import InputError
from ..lowrank.factors import LowRank
from ..lowrank.nearfield import NearFieldSplit
from ..formfactors.energy import warn_energy
from ..scene.scene import Scene
from ..solve.nearfield import NearFieldFactorization
from ..solve.stats import PassStatistics
from ..solve.woodbury import HFactorization
from .options import PrecomputePlan

__all__ = ["assemble", "solver_object", "far_block", "statistics_state", "add_statistics", "near_state",
           "concat_near"]

#: The arrays of the near field's coordinate lists (:meth:`NearFieldSplit.state`).
NEAR_KEYS = ("near_rows", "near_cols", "near_values")


# -- What a column block adds: additive over blocks, so a Dask leaf returns its share -------------

def far_block(stats: PassStatistics, start: int, stop: int, F_block: np.ndarray, rows_rho: np.ndarray,
              split: NearFieldSplit | None = None, out: np.ndarray | None = None) -> tuple[np.ndarray, float, float]:
    """What HF gets of columns ``start:stop`` of F, recorded in ``stats`` on the way (both backends' leaves).

    One read of F gives the pass statistics, ``G = rows_rho F`` and ``||G||_F^2``
    (:meth:`PassStatistics.add_scaled`, into ``out`` when it fits: a buffer the caller
    reuses); ``split`` then moves G's near entries out.

    Returns
    -------
    G : (n, b) array, F's dtype
        The block of G, less its near entries with a ``split``.
    norm2 : float
        ``||G||_F^2`` before the split: the norm the leaf's relative budget is taken from.
    block_norm2 : float
        ``||G||_F^2`` of the returned block (``norm2`` less the squares moved out).
    """
    G, norm2 = stats.add_scaled(start, stop, F_block, rows_rho, out)
    if split is None:
        return G, norm2, norm2
    G = split.split(G, start)
    return G, norm2, max(norm2 - split.moved2, 0.0)


def statistics_state(stats: PassStatistics) -> dict:
    """``stats`` as a state that adds to others' (:func:`add_statistics`): without the weights.

    The states of disjoint column ranges add up to the statistics of their union: row
    sums and the probe sketch are sums over columns.
    """
    state = stats.state()
    state.pop("weights", None)
    return state


def add_statistics(a: dict | None, b: dict | None) -> dict | None:
    """The statistics of two disjoint column ranges together (either may be None)."""
    if a is None or b is None:
        return a if b is None else b
    return {**a, "row_sums": a["row_sums"] + b["row_sums"], "col_sums": a["col_sums"] + b["col_sums"],
            "sketch": a["sketch"] + b["sketch"]}


def near_state(rows=(), cols=(), values=()) -> dict:
    """Near-field coordinate lists as :meth:`NearFieldSplit.state` gives them."""
    cat = (lambda xs, dt: np.concatenate(xs).astype(dt, copy=False) if len(xs) else np.zeros(0, dt))
    return {"near_rows": cat(list(rows), np.int64), "near_cols": cat(list(cols), np.int64),
            "near_values": cat(list(values), np.float64)}


def concat_near(a: dict | None, b: dict | None) -> dict | None:
    """The near entries of two column ranges together (``a``'s first; either may be None)."""
    if a is None or b is None:
        return a if b is None else b
    return near_state(*([a[k], b[k]] for k in NEAR_KEYS))


# -- The one assembly step ---------------------------------------------------------------------------

def assemble(scene: Scene, options: PrecomputePlan, lowrank: LowRank, stats: PassStatistics,
             near: dict | None = None, *, backend: dict | None = None, runner=None) -> HFactorization:
    """Low-rank factors + near field + pass statistics + parameters -> the solver object.

    Parameters
    ----------
    scene : Scene
    options : PrecomputePlan
    lowrank : LowRank
        ``G_int - N ~= Q V^T`` (internal order) with its achieved error; its ``info``
        gets ``near_radius``, ``near_nnz``, ``time_nearfield_setup`` and ``solver``.
    stats : PassStatistics
        Of all n columns (internal order, area-weighted).
    near : dict, optional
        The near entries (``near_rows``, ``near_cols`` internal order, ``near_values``
        of G); required when ``options.near_entries`` > 0.
    backend : dict, optional
        Recorded in ``params`` beside the options (``backend``, ``workers``).
    runner : optional
        Where the near-field set-up's pieces run: this process by default
        (:class:`~hfrad.solve.nearfield.InProcess`), Dask workers with
        :func:`hfrad.distributed.assembly.assemble_on_cluster`. The same object either way.

    Returns
    -------
    HFactorization or NearFieldFactorization
        The latter with the near-field split.

    Raises
    ------
    InputError
        ``options.near_entries`` > 0 and ``near`` is None.
    """
    perm = options.perm
    warn_energy(scene, stats.row_sums[np.argsort(perm)])
    params = {**options.params(), **(backend or {})}
    N = None
    if options.near_entries:
        if near is None:
            raise InputError(f"options.near_entries is {options.near_entries} (the near-field split) but no "
                             "near entries were passed: assemble(..., near=near_state(rows, cols, values))")
        N = sp.csr_matrix((near["near_values"], (near["near_rows"], near["near_cols"])),
                          shape=(options.n, options.n))
        lowrank.info.update({"near_radius": options.near_radius, "near_nnz": int(N.nnz)})
    return solver_object(perm, lowrank, scene.reflectance, params, stats, scene=scene, near=N, runner=runner)


def solver_object(perm: np.ndarray, lowrank: LowRank, reflectance: np.ndarray, params: dict,
                  stats: PassStatistics, *, scene: Scene | None = None, near=None, runner=None) -> HFactorization:
    """The solver object of factors in internal order: the last step of every entry point.

    Parameters
    ----------
    perm : (n,) int
        Internal order (internal index t holds user patch ``perm[t]``).
    lowrank : LowRank
        ``G_int (- N) ~= Q V^T``; its ``info`` gets ``solver`` (and ``time_nearfield_setup``).
    reflectance : (n, 3) float in [0, 1), user order
    params : dict
        Recorded with the factorization (``.hfr``).
    stats : PassStatistics
    scene : Scene, optional
    near : (n, n) sparse, optional
        N in internal order: the near-field solver (Woodbury around ``I - D_c N``).
    runner : optional
        Where the near-field set-up runs (see :func:`assemble`).

    Returns
    -------
    HFactorization or NearFieldFactorization
    """
    rho_max = reflectance.max(axis=1)
    if near is None:
        fac = HFactorization(perm, lowrank.Q, lowrank.V, rho_max, reflectance, lowrank,
                             params=params, scene=scene, stats=stats)
    else:
        t1 = time.perf_counter()
        fac = NearFieldFactorization(perm, lowrank.Q, lowrank.V, near, rho_max, reflectance, lowrank,
                                     params=params, scene=scene, stats=stats, runner=runner)
        lowrank.info["time_nearfield_setup"] = time.perf_counter() - t1
    lowrank.info["solver"] = fac.solver
    return fac
