"""The ray budget: fewer visibility rays for pairs too weak to matter.

A pair whose area-weighted form factor ``A_i F_ij`` is so small that even a
wrong visibility could not move ``||F||_F`` by more than a share of the error
budget gets one ray instead of ``samples`` (:func:`one_ray_threshold`). The
threshold is a single number per scene, chosen from a fixed sample of columns
of the unoccluded kernel, so it is the same in every block and every process
(local, worker processes, Dask), and it is applied to the symmetric quantity
``A_i F_ij = A_j F_ji``, so reciprocity survives. A second threshold, for
``FEW_RAYS_FACTOR`` times that share, gives the pairs whose probe rays disagree
with their neighbours' 4 rays instead of 16 (:func:`ray_budget`,
:class:`RayBudget`). Two more, for ``REFINE_FACTOR`` and ``LARGE_FACTOR`` times the share, give
the pairs whose 16 rays disagree no second round (their 16-ray estimate stands), or 64 rays in it
instead of 256 (with visibility.py's importance picks, the default: 32 picks instead of 64). By default the one-ray rule
spends ``ONE_RAY_SHARE`` of a relative eps (:func:`default_one_ray_tol`) and is
off for an absolute eps.

This policy sits apart from the engines (:mod:`hfrad.formfactors.blocks`,
:mod:`hfrad.formfactors.parallel`), which only apply the
:class:`RayBudget` they are given.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .clustered import block_function, kernel_for
from .kernel import PatchGeometry

__all__ = ["RayBudget", "ray_budget", "one_ray_threshold", "default_one_ray_tol", "FEW_RAYS_FACTOR", "ONE_RAY_SHARE",
           "REFINE_FACTOR", "LARGE_FACTOR", "THRESHOLD_SAMPLE_COLUMNS"]


@dataclass(frozen=True)
class RayBudget:
    """Fewer rays for pairs too weak to matter at the error budget (thresholds on ``A_i F_ij``, m^2).

    ``A_i F_ij`` is the same number for (i, j) and (j, i), so both rules decide
    alike from either side and V_ij == V_ji still holds. The thresholds come
    from :func:`ray_budget` (a share of ``||F||_F``).

    Attributes
    ----------
    one_ray_below : float
        Pairs below this get one ray (the probe's, with probing); 0 = off.
    few_rays_below : float
        Flagged pairs (neighbouring probes disagree) below this get
        ``samples`` rays (4 by default) instead of ``BOUNDARY_SAMPLES`` (16); 0 = off.
    refine_below : float
        Pairs below this get no second visibility round (visibility.py: their first
        rays' estimate stands where those rays disagree or the patches are close); 0 = off.
    large_below : float
        Pairs below this whose second round would be ``REFINE_LARGE_SAMPLES`` (256)
        rays get ``REFINE_SAMPLES`` (64); 0 = off.
    """

    one_ray_below: float = 0.0
    few_rays_below: float = 0.0
    refine_below: float = 0.0
    large_below: float = 0.0

    def key(self) -> dict:
        """The nonzero thresholds, for cache keys (empty when every rule is off)."""
        return {k: float(v) for k, v in (("one_ray_below", self.one_ray_below),
                                         ("few_rays_below", self.few_rays_below),
                                         ("refine_below", self.refine_below),
                                         ("large_below", self.large_below)) if v}


#: Columns sampled (spread over the scene) to pick the one-ray threshold.
THRESHOLD_SAMPLE_COLUMNS = 128


#: Share of the factorization's error budget eps that the one-ray rule may spend by default.
ONE_RAY_SHARE = 0.25


def default_one_ray_tol(eps: float, relative: bool) -> float:
    """The one-ray rule's tolerance when the user gives none: ``ONE_RAY_SHARE * eps``.

    Only for a relative eps (a share of ``||F||_F``); with an absolute eps the
    rule is off (0), since the threshold is relative to ``||F||_F``.
    """
    return ONE_RAY_SHARE * eps if relative else 0.0


#: Flagged pairs (probes disagree) that together hold FEW_RAYS_FACTOR times the one-ray rule's
#: share of ||F||_F get 4 rays instead of 16. Conference room, 20,463 clustered patches, eps 0.05
#: (one-ray share 0.0125, so 0.05 here), kernel v8: rays 232 M -> 120 M on six blocks, F moved
#: 0.58% from the every-ray F in the Frobenius norm (0.30% by the one-ray rule alone).
FEW_RAYS_FACTOR = 4.0

#: Pairs that together hold REFINE_FACTOR times the one-ray rule's share of ||F||_F get no second
#: visibility round, and those holding LARGE_FACTOR times it 64 rays there instead of 256
#: (benchmarks/README.md, "Form-factor accuracy and its cost", records what they save and cost).
REFINE_FACTOR = 8.0
LARGE_FACTOR = 16.0


def ray_budget(scene, one_ray_tol: float, *, few_rays_factor: float = FEW_RAYS_FACTOR,
               refine_factor: float = REFINE_FACTOR, large_factor: float = LARGE_FACTOR,
               geometry: PatchGeometry | None = None) -> RayBudget:
    """The :class:`RayBudget` for a Frobenius share ``one_ray_tol`` of ``||F||_F``.

    ``one_ray_below = one_ray_threshold(scene, one_ray_tol)``; ``few_rays_below``,
    ``refine_below`` and ``large_below`` are the same rule for ``few_rays_factor``,
    ``refine_factor`` and ``large_factor`` times ``one_ray_tol`` (a factor of 0 turns
    its rule off). All 0 when ``one_ray_tol`` is 0.
    """
    factors = (1.0, few_rays_factor, refine_factor, large_factor)
    thresholds = _thresholds(scene, tuple(f * one_ray_tol for f in factors), geometry, THRESHOLD_SAMPLE_COLUMNS)
    return RayBudget(*thresholds)


def one_ray_threshold(scene, tol: float, *, geometry: PatchGeometry | None = None,
                      sample_columns: int = THRESHOLD_SAMPLE_COLUMNS) -> float:
    """Largest ``tau`` such that pairs with ``A_i F_ij < tau`` hold at most ``tol^2`` of ``||F||_F^2``.

    Estimated on the unoccluded kernel of ``sample_columns`` columns evenly
    spread over the user's patch order (deterministic). Giving those pairs one
    ray instead of several changes each of their entries by at most
    ``F_ij`` (visibility is a fraction in [0, 1]), so the change of F is at most
    about ``tol ||F_unoccluded||_F`` in the Frobenius norm, and far less in
    practice (one ray still sees a wall).

    Parameters
    ----------
    scene : Scene
    tol : float >= 0
        Relative Frobenius share, e.g. a quarter of the factorization's eps.

    Returns
    -------
    float
        Threshold on ``A_i F_ij`` (m^2); 0 when ``tol`` is 0.
    """
    return _thresholds(scene, (tol,), geometry, sample_columns)[0]


def _thresholds(scene, tols, geometry, sample_columns: int) -> list[float]:
    """:func:`one_ray_threshold` for each of ``tols``, from one pass over the sample columns."""
    if max(tols) <= 0 or scene.n_patches == 0:
        return [0.0] * len(tols)
    geom, block = (geometry, block_function(geometry)) if geometry is not None else kernel_for(scene)
    n = scene.n_patches
    cols = np.unique(np.linspace(0, n - 1, min(n, sample_columns)).astype(np.int64))
    F = block(geom, np.arange(n), cols)
    a = (geom.areas[:, None] * F).ravel()
    f2 = np.square(F).ravel()
    total = f2.sum()
    if total <= 0:
        return [0.0] * len(tols)
    order = np.argsort(a, kind="stable")
    cum = np.cumsum(f2[order])
    out = []
    for tol in tols:
        k = int(np.searchsorted(cum, tol * tol * total, side="right"))
        out.append(0.0 if tol <= 0 else float(a[order[k]]) * _BELOW if k < len(a) else float(a.max()))
    return out


#: A threshold is set a little below the sampled pair's A_i F_ij it falls on: A_i F_ij and A_j F_ji
#: agree only to rounding, and a threshold equal to one of them would decide (i, j) and (j, i)
#: apart (V_ij != V_ji; seen with the second-round rules on a 700-patch Cornell box).
_BELOW = 1 - 1e-6
