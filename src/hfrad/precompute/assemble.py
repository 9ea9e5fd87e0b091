"""One precompute, two backends: what a column block adds, and the assembly of the solver object.

``hfrad.factorize(scene)`` runs the precompute in this process (:mod:`hfrad.precompute.local`)
or as Dask tasks (:mod:`hfrad.distributed`); the backend only decides where column
blocks, leaves and merges run. Both take a :class:`PrecomputePlan` (validated once,
:func:`~hfrad.precompute.options.plan_precompute`) and end in :func:`assemble`:
low-rank factors + near-field entries + pass statistics + parameters -> the solver object;
the matrix and blocks entry points (:mod:`hfrad.precompute.matrix`) end in its last step,
:func:`solver_object`. Per column block both do the
same (:func:`far_block`: the pass statistics, G and the near-field split in one read of F;
:func:`~hfrad.lowrank.hf.compress_leaf`), so the two give the same class, the
same ``.hfr`` contents (apart from the recorded backend and timings) and the same
error figures.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..errors import InputError
from ..lowrank.hf import ErrorBudget
from ..lowrank.factors import LowRank
from ..lowrank.nearsplit import NearFieldSplit
from ..formfactors.energy import warn_energy
from ..formfactors.farfield import FarFieldOptions
from ..formfactors.hmatrix import HMatrixOptions
from ..scene.scene import Scene
from ..solve.nearfield import NearFieldFactorization
from ..solve.samples import SampledRows
from ..solve.stats import PassStatistics
from ..solve.woodbury import HFactorization

__all__ = ["PrecomputePlan", "assemble", "solver_object", "far_block", "statistics_state", "add_statistics", "near_state",
           "concat_near"]

#: The arrays of the near field's coordinate lists (:meth:`NearFieldSplit.state`).
NEAR_KEYS = ("near_rows", "near_cols", "near_values")


@dataclass(frozen=True, eq=False)
class PrecomputePlan:
    """The precompute's options for one scene, validated and resolved (:func:`plan_precompute`).

    Attributes
    ----------
    n : int
        Patches.
    eps, relative, dtype, reciprocity
        As in :func:`hfrad.factorize` (``reciprocity`` from its backend).
    block_size, samples, leaf_share, one_ray_tol
        As in :class:`~hfrad.precompute.options.PrecomputeOptions` (``block_size`` and ``one_ray_tol`` resolved: never None).
    order : str
        The order's name ("zorder", "hilbert", "random", "input") or "custom".
    perm : (n,) int64
        Internal order: internal index t holds user patch ``perm[t]``.
    near_entries : int
        Facing neighbours per row of the near field (0: no split).
    near_radius : float, metres
        Pairs with centroid distance <= this are near (0.0 without the split).
    form_factors : dict
        The form-factor kernel's and visibility's version and settings.
    far_field : str
        "exact" (every pair) or "sampled" (:mod:`hfrad.formfactors.farfield`).
    far_options : FarFieldOptions
        The sampled far field's knobs (recorded with ``far_field="sampled"``).
    hmatrix_options : HMatrixOptions or None
        The H-matrix's knobs with ``far_field="hierarchical"`` (recorded), else None.
    """

    n: int
    eps: float
    relative: bool
    block_size: int
    dtype: str
    samples: int | None
    order: str
    perm: np.ndarray
    leaf_share: float
    one_ray_tol: float
    near_entries: int
    near_radius: float
    reciprocity: bool
    form_factors: dict
    far_field: str = "exact"
    far_options: FarFieldOptions = dataclasses.field(default_factory=FarFieldOptions)
    hmatrix_options: HMatrixOptions | None = None

    @property
    def n_blocks(self) -> int:
        """Column blocks, m = ceil(n / block_size)."""
        return -(-self.n // self.block_size)

    @property
    def budget(self) -> ErrorBudget:
        """The HF error budget every leaf and merge of either backend draws from."""
        return ErrorBudget(self.eps, self.relative, max(self.n_blocks, 1), self.leaf_share)

    def replace(self, **changes) -> "PrecomputePlan":
        return dataclasses.replace(self, **changes)

    def params(self) -> dict:
        """The parameters recorded in the ``.hfr`` (the backend adds ``backend``, ``workers``)."""
        far = {"far_options": dataclasses.asdict(self.far_options)} if self.far_field == "sampled" else {}
        if self.hmatrix_options is not None:
            far["hmatrix_options"] = dataclasses.asdict(self.hmatrix_options)
        return far | {"eps": self.eps, "relative": self.relative, "block_size": self.block_size, "dtype": self.dtype,
                "samples": self.samples, "order": self.order, "leaf_share": self.leaf_share,
                "one_ray_tol": self.one_ray_tol, "near_field": self.near_entries, "near_radius": self.near_radius,
                "form_factors": self.form_factors, "reciprocity": self.reciprocity, "far_field": self.far_field}

    def key(self, scene: Scene) -> str:
        """A hash of everything the factorization depends on: geometry, reflectance, parameters.

        Checkpoints of either backend carry it and refuse to resume another input. The
        reciprocity copy is not part of it (F is equal to rounding either way).
        """
        h = hashlib.sha256()
        for a in (scene.vertices, scene.faces, scene.occluder_vertices, scene.occluder_faces,
                  scene.patch_of_triangle, scene.reflectance.max(axis=1)):
            h.update(np.ascontiguousarray(a).tobytes())
        params = self.params()
        del params["reciprocity"]
        if self.order == "custom":
            h.update(np.ascontiguousarray(self.perm, np.int64).tobytes())
        h.update(json.dumps(params, sort_keys=True).encode())
        return h.hexdigest()

    def rows_rho(self, scene: Scene) -> np.ndarray:
        """(n, 1) ``rho_max`` in internal order, in the factors' dtype: a block of G is ``rows_rho * F``."""
        return scene.reflectance.max(axis=1)[self.perm][:, None].astype(self.dtype)

    def stats_weights(self, scene: Scene) -> np.ndarray:
        """Patch areas in internal order: the pass statistics' (area-weighted) norm."""
        return np.asarray(scene.areas, np.float64)[self.perm]

    def ray_budget(self, scene: Scene):
        """The form-factor engine's :class:`RayBudget` (None with ``samples=0``: analytic, no rays)."""
        if self.samples == 0:
            return None
        from ..formfactors.budget import ray_budget

        return ray_budget(scene, self.one_ray_tol)



# -- What a column block adds: additive over blocks, so a Dask leaf returns its share -------------

def far_block(stats: PassStatistics, start: int, stop: int, F_block: np.ndarray, rows_rho: np.ndarray,
              split: NearFieldSplit | None = None, out: np.ndarray | None = None,
              exact_rows: np.ndarray | None = None) -> tuple[np.ndarray, float, float]:
    """What HF gets of columns ``start:stop`` of F, recorded in ``stats`` on the way (both backends' leaves).

    One read of F gives the pass statistics, ``G = rows_rho F`` and ``||G||_F^2``
    (:meth:`PassStatistics.add_scaled`, into ``out`` when it fits: a buffer the caller
    reuses); ``split`` then moves G's near entries out. ``exact_rows``: the exact rows at the
    sampled rows' patches where ``F_block`` comes from the sampled far field.

    Returns
    -------
    G : (n, b) array, F's dtype
        The block of G, less its near entries with a ``split``.
    norm2 : float
        ``||G||_F^2`` before the split: the norm the leaf's relative budget is taken from.
    block_norm2 : float
        ``||G||_F^2`` of the returned block (``norm2`` less the squares moved out).
    """
    G, norm2 = stats.add_scaled(start, stop, F_block, rows_rho, out, exact_rows)
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
    out = {**a, "row_sums": a["row_sums"] + b["row_sums"], "col_sums": a["col_sums"] + b["col_sums"],
           "sketch": a["sketch"] + b["sketch"]}
    for name in ("far_q", "far_holdout_q"):      # the sampled far field's certificate and held-out check
        if name in a and name in b:
            out[name] = a[name] + b[name]
    if "sample_rows" in a and "sample_rows" in b:
        out.update(SampledRows.add_states(a, b))
    else:   # a part saved before the rows were kept: no figure rather than one from missing columns
        out = {k: v for k, v in out.items() if not k.startswith(("sample_", "smooth_"))}
    return out


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
        lowrank.info["near_setup"] = fac.near_setup
    lowrank.info["solver"] = fac.solver
    return fac
