"""The precompute's options: the expert knobs a user may set, and the plan they resolve to for one scene.

:class:`PrecomputeOptions` holds the knobs besides the front door's arguments
(block width, visibility rays, the leaves' share of the error budget, the one-ray
rule), in the style of SciPy's ``splu(options=)``. :func:`plan_precompute`
validates everything once, ``eps`` first, then resolves the near-field policy
(``near_field="auto"``: :func:`near_entries`, which reads ``eps``) and the rest
for one scene into a :class:`~hfrad.precompute.assemble.PrecomputePlan`, which both
backends (this process, :mod:`hfrad.precompute.local`; Dask, :mod:`hfrad.distributed`)
run and record.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from ..defaults import DEFAULT_BLOCK_SIZE
from ..errors import InputError, SceneError
from ..formfactors.budget import default_one_ray_tol
from ..formfactors.farfield import FAR_FIELD_CHOICES, FarFieldOptions
from ..formfactors.hmatrix import HMatrixOptions, default_values
from ..lowrank.nearsplit import DEFAULT_NEAR_ENTRIES, near_radius
from ..scene.scene import Scene
from ..scene.zorder import patch_order
from ..validation import check_eps, check_factorize_options, check_permutation
from .assemble import PrecomputePlan

__all__ = ["PrecomputeOptions", "plan_precompute", "near_entries", "near_field_pays_from", "clustered_near_entries",
           "NEAR_FIELD_MIN_PATCHES", "NEAR_FIELD_PAYS_FROM", "NEAR_FIELD_REFERENCE_EPS", "NEAR_FIELD_EPS_POWER"]

# -- the near-field policy ---------------------------------------------------------------------------
#: ``near_field="auto"`` never splits the near field below this many patches.
NEAR_FIELD_MIN_PATCHES = 2000
#: ... and from this many patches on at a relative eps of ``NEAR_FIELD_REFERENCE_EPS``:
#: there the split's set-up (a sparse LU and k right-hand sides per colour channel) costs
#: what its lower rank saves HF (Cornell box, eps 0.02: about even at 20K patches,
#: 1.26x slower with the split at 10K; benchmarks/README.md, "Where the near field pays").
NEAR_FIELD_PAYS_FROM = 20000
NEAR_FIELD_REFERENCE_EPS = 0.02
#: ... scaled by ``(NEAR_FIELD_REFERENCE_EPS / eps) ** NEAR_FIELD_EPS_POWER``: a looser eps
#: leaves the far field a lower rank, so the near pairs' high rank is the larger share of
#: it sooner (eps 0.05: about even at 5K patches, 1.42x faster with the split at 10K).
NEAR_FIELD_EPS_POWER = 1.5
#: A clustered scene's "auto" near field holds more neighbours a row as it has more patches:
#: ``DEFAULT_NEAR_ENTRIES`` up to ``CLUSTERED_NEAR_FROM`` patches, then growing as
#: ``(n / CLUSTERED_NEAR_FROM) ** CLUSTERED_NEAR_POWER``, to at most ``CLUSTERED_NEAR_MOST``.
#: At a fixed count the near radius shrinks with the patches, and a real mesh's far part then
#: keeps a rank that grows faster than n; HF's cost grows as n k^2. Sponza at eps 0.02 with
#: 120 a row: rank 477 at 3,129 patches, 4,518 at 20,102 (HF 634 of 770 s on the idle 2-core
#: machine); with 400 a row at 20,102: rank 1,876, and a solve 135 ms instead of 173 ms
#: (benchmarks/README.md, "Sponza at 20K patches"). The near field's own costs (its
#: collection, the set-up's sparse LU, each solve's sweeps over N) grow as n c, hence the cap.
CLUSTERED_NEAR_FROM = 4000
CLUSTERED_NEAR_POWER = 0.75
CLUSTERED_NEAR_MOST = 400


def near_field_pays_from(eps: float, relative: bool = True, clustered: bool = False) -> int:
    """Patches from which ``near_field="auto"`` splits the near field, at this ``eps``.

    An absolute eps says nothing of the rank before ``||G||_F`` is known: the split
    then starts at ``NEAR_FIELD_MIN_PATCHES``; so does a ``clustered`` scene (patches made of
    many triangles of a real mesh): its near pairs (contact, folds, small parts) hold far more
    of the rank than a box's. Measured at ~3,100 patches, eps 0.02 (benchmarks/README.md,
    "Where the near field pays"): ranks with the split 748 against 1,961 (Sponza), 236 against
    1,949 (the conference room), 423 against 2,153 (Sibenik), HF and the solver's set-up 6-9x faster.
    """
    if not relative or not eps > 0 or clustered:
        return NEAR_FIELD_MIN_PATCHES
    scaled = NEAR_FIELD_PAYS_FROM * (NEAR_FIELD_REFERENCE_EPS / eps) ** NEAR_FIELD_EPS_POWER
    return max(NEAR_FIELD_MIN_PATCHES, int(math.ceil(scaled)))


def clustered_near_entries(n: int) -> int:
    """Neighbours a row of a clustered scene's "auto" near field at ``n`` patches (see
    ``CLUSTERED_NEAR_POWER``): 120 up to 4,000 patches, 239 at 10,000, 400 from about 20,000."""
    grown = DEFAULT_NEAR_ENTRIES * max(1.0, n / CLUSTERED_NEAR_FROM) ** CLUSTERED_NEAR_POWER
    return int(min(CLUSTERED_NEAR_MOST, round(grown)))


def near_entries(near_field, n: int, eps: float = NEAR_FIELD_REFERENCE_EPS, relative: bool = True,
                 clustered: bool = False, far_field: str = "exact") -> int:
    """Neighbours per row of the near field for ``factorize(near_field=...)`` (0 = no split).

    "auto": ``DEFAULT_NEAR_ENTRIES`` where the split pays (from
    :func:`near_field_pays_from` patches on at this ``eps``, for a scene ``clustered`` or not), else 0;
    a clustered scene's count grows with n from ``CLUSTERED_NEAR_FROM`` patches on
    (:func:`clustered_near_entries`). With ``far_field="hierarchical"`` (resolved) the split is
    made at every size.
    """
    if near_field == "auto":
        # the H-matrix holds the near pairs already: the split costs nothing there and lowers the
        # rank at every size (1,898 -> 214 at 9,986 patches, eps 0.05)
        if n < near_field_pays_from(eps, relative, clustered) and far_field != "hierarchical":
            return 0
        return clustered_near_entries(n) if clustered else DEFAULT_NEAR_ENTRIES
    if near_field is None or near_field is False:
        return 0
    if isinstance(near_field, str) or int(near_field) != near_field or near_field < 0:
        raise InputError(f"near_field must be 'auto', None or a number of neighbours per row (e.g. 64); "
                         f"got {near_field!r}")
    return int(near_field)


#: ``far_field="auto"`` chooses the hierarchical far field from this many patches ...
AUTO_HIERARCHICAL_FROM = 20000
#: ... at a relative eps of at least this (where it was measured faster: benchmarks/README.md, "Where
#: the hierarchical far field pays"). The Cornell box, one run each, this process, the same day:
#: eps 0.05, 9,986 patches 14.8 s against the exact pass's 13.3 s, 19,596 patches 28.4 s against 32.3 s,
#: 161,808 patches about 3x faster; eps 0.02, 19,596 patches 58 s against 97 s but 39,482 patches 289 s
#: against 188 s (rank 1,882: the range finder's basis of 3,136 columns, O(n l^2), is most of it).
AUTO_HIERARCHICAL_EPS = 0.05


def far_field_mode(far_field, n: int, relative: bool, *, eps: float = 0.0, local: bool = True,
                   clustered: bool = False) -> str:
    """``"exact"``, ``"sampled"`` or ``"hierarchical"`` for ``factorize(far_field=...)``.

    "auto" is the hierarchical far field where it was measured faster than the exact pass: in this
    process (``local``), on a scene of plain patches (not ``clustered``), from
    ``AUTO_HIERARCHICAL_FROM`` patches at a relative eps of at least ``AUTO_HIERARCHICAL_EPS``; the
    exact pass elsewhere (smaller scenes, a smaller or absolute eps, a Dask cluster, and clustered
    real scenes: Šibenik, 10,181 patches, 40.2 s against the exact pass's 35.0 s; at 60,568 patches,
    with the near field's set-up by sweeps, 437 s against the exact pass's 719 s, of which about
    290 s were the LUs that the sweeps now save it too: not measured faster). The sampled far field is never
    chosen: it evaluates 4-5 times fewer pairs than the exact pass but costs more wall time
    (benchmarks/README.md, "The sampled far field").
    """
    if far_field == "auto":
        hierarchical = (local and relative and not clustered and n >= AUTO_HIERARCHICAL_FROM
                        and eps >= AUTO_HIERARCHICAL_EPS)
        return "hierarchical" if hierarchical else "exact"
    if far_field not in FAR_FIELD_CHOICES:
        raise InputError(f"far_field must be one of {', '.join(map(repr, FAR_FIELD_CHOICES))}; got {far_field!r}")
    if far_field == "sampled" and not relative:
        raise InputError("far_field='sampled' needs a relative eps (its tolerance is a share of each "
                         "block's norm); use far_field='exact' with relative=False")
    return far_field


#: ``far_field="hierarchical"``: each far block's cross approximation may be off by this share of
#: eps (relative Frobenius), as the sampled far field's parts (``FarFieldOptions.share``).
HMATRIX_EPS_SHARE = 0.2


def hmatrix_options(hmatrix, eps: float, relative: bool, n: int) -> HMatrixOptions:
    """The H-matrix's options: the user's, else the defaults with the block tolerance
    ``HMATRIX_EPS_SHARE * eps`` (a relative eps; an absolute one keeps the default 0.01) and the
    values held as :func:`~hfrad.formfactors.hmatrix.default_values` says for n patches."""
    if hmatrix is not None:
        if not isinstance(hmatrix, HMatrixOptions):
            raise InputError(f"options.hmatrix must be an hfrad.formfactors.hmatrix.HMatrixOptions; "
                             f"got {type(hmatrix).__name__}")
        return hmatrix
    values = default_values(n)
    return (HMatrixOptions(tolerance=HMATRIX_EPS_SHARE * eps, values=values) if relative
            else HMatrixOptions(values=values))


def _far_options(far) -> FarFieldOptions:
    if far is None:
        return FarFieldOptions()
    if not isinstance(far, FarFieldOptions):
        raise InputError(f"options.far must be an hfrad.formfactors.farfield.FarFieldOptions; got {type(far).__name__}")
    return far


# -- the knobs -------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class PrecomputeOptions:
    """Expert options of the precompute (``hfrad.factorize(scene, options=PrecomputeOptions(...))``).

    Validated with the rest of the front door's arguments, for the scene they are used on
    (:func:`plan_precompute`). None of them is needed for a first run.

    Attributes
    ----------
    block_size : int, optional
        Column block width; default ``min(DEFAULT_BLOCK_SIZE, n)`` (256).
    samples : int, optional
        Visibility rays per patch pair (default: the engine's; 0: no visibility).
    leaf_share : float in (0, 1]
        Share of the squared error budget given to the leaf SVDs.
    one_ray_tol : float or None
        Pairs that together hold at most this share of ``||F||_F`` get one visibility
        ray instead of several, and flagged pairs (probes disagree) holding
        ``FEW_RAYS_FACTOR`` (4) times this share get 4 rays instead of 16, pairs holding
        ``REFINE_FACTOR`` (8) times it no second visibility round and ``LARGE_FACTOR`` (16)
        times it 64 rays there instead of 256
        (:func:`hfrad.formfactors.budget.ray_budget`); None: ``eps / 4`` for a
        relative eps, 0 (every rule off) for an absolute one.
    far : FarFieldOptions, optional
        The sampled far field's knobs (admissibility ``eta``, its share of eps, sample
        sizes; :class:`hfrad.formfactors.farfield.FarFieldOptions`); used with
        ``far_field="sampled"``.
    hmatrix : HMatrixOptions, optional
        The H-matrix's knobs (leaf size, admissibility, each far block's tolerance;
        :class:`hfrad.formfactors.hmatrix.HMatrixOptions`), used with ``far_field="hierarchical"``;
        default: its defaults with the tolerance ``HMATRIX_EPS_SHARE`` (0.2) times a relative eps,
        and its values held as bfloat16 from ``BFLOAT16_FROM`` (100,000) patches
        (:func:`hfrad.formfactors.hmatrix.default_values`).
    """

    block_size: int | None = None
    samples: int | None = None
    leaf_share: float = 0.5
    one_ray_tol: float | None = None
    far: FarFieldOptions | None = None
    hmatrix: HMatrixOptions | None = None

    def replace(self, **changes) -> "PrecomputeOptions":
        return dataclasses.replace(self, **changes)


def plan_precompute(scene: Scene, eps: float = 0.02, *, relative: bool = True, dtype="float32", order="zorder",
                    near_field=None, options: PrecomputeOptions | None = None,
                    reciprocity: bool = True, far_field: str = "exact", local: bool = True) -> PrecomputePlan:
    """Validate the precompute's options for ``scene`` at the API boundary (both backends), once.

    Parameters
    ----------
    scene : Scene
    eps, relative, dtype, order
        As in :func:`hfrad.factorize`.
    near_field : "auto", int or None
        As in :func:`hfrad.factorize` (default None: no split); "auto" is resolved
        (:func:`near_entries`) after ``eps`` is validated.
    options : PrecomputeOptions, optional
        The expert knobs (default: ``PrecomputeOptions()``).
    reciprocity : bool
        The backend's reciprocity copy (recorded; not part of the checkpoint key).
    far_field : {"exact", "sampled", "hierarchical", "auto"}
        As in :func:`hfrad.factorize` (resolved by :func:`far_field_mode`); "hierarchical" orders the
        patches by the H-matrix's cluster tree (``order`` then must be a name, and is not used).
    local : bool
        The precompute runs in this process (a ``LocalBackend``), not on Dask: "auto" may then
        choose the hierarchical far field.

    Returns
    -------
    PrecomputePlan

    Raises
    ------
    InputError
        A bad option (names it).
    SceneError
        A scene without patches.
    """
    if not isinstance(scene, Scene):
        raise TypeError(f"scene must be a hfrad Scene (see hfrad.load_scene); got {type(scene).__name__}")
    if options is None:
        options = PrecomputeOptions()
    elif not isinstance(options, PrecomputeOptions):
        raise InputError(f"options must be an hfrad.PrecomputeOptions; got {type(options).__name__}")
    n = scene.n_patches
    if n == 0:
        raise SceneError(f"{scene.name}: the scene has no patches")
    eps = check_eps(eps, relative)
    block_size = min(DEFAULT_BLOCK_SIZE, n) if options.block_size is None else options.block_size
    dt = check_factorize_options(n, eps, block_size, dtype, relative)
    leaf_share, samples, one_ray_tol = options.leaf_share, options.samples, options.one_ray_tol
    if not (0.0 < leaf_share <= 1.0):
        raise InputError(f"leaf_share must be in (0, 1]; got {leaf_share!r}")
    if samples is not None and (int(samples) != samples or samples < 0):
        raise InputError(f"samples must be a number of rays >= 0; got {samples!r}")
    if one_ray_tol is None:
        one_ray_tol = default_one_ray_tol(eps, relative)
    elif not (one_ray_tol >= 0 and np.isfinite(one_ray_tol)):
        raise InputError(f"one_ray_tol must be a share >= 0 of ||F||_F; got {one_ray_tol!r}")
    if far_field == "auto" and not isinstance(order, str):
        far_field = "exact"        # a custom order: only the column pass keeps it
    far_field = far_field_mode(far_field, n, bool(relative), eps=eps, local=local, clustered=scene.is_clustered)
    hm_options = hmatrix_options(options.hmatrix, eps, relative, n) if far_field == "hierarchical" else None
    if hm_options is not None:
        if not isinstance(order, str):
            raise InputError("far_field='hierarchical' orders the patches by its cluster tree; a custom "
                             "order cannot be used with it")
        from .hierarchical import tree_order

        perm, order = tree_order(scene, hm_options), "tree"
    elif isinstance(order, str):
        perm = patch_order(scene.centroids, order)
    else:
        perm = check_permutation(order, n)
        order = "custom"
    entries = near_entries(near_field, n, eps, relative, clustered=scene.is_clustered, far_field=far_field)
    from ..formfactors.kernel import settings as kernel_settings
    from ..formfactors.visibility import settings as visibility_settings

    return PrecomputePlan(
        n=n, eps=float(eps), relative=bool(relative), block_size=int(block_size), dtype=dt.name,
        samples=None if samples is None else int(samples), order=order, perm=np.asarray(perm, np.int64),
        leaf_share=float(leaf_share), one_ray_tol=float(one_ray_tol), near_entries=entries,
        # the radius, not only the count, is part of the checkpoint key
        near_radius=near_radius(scene.centroids, entries, scene.normals) if entries else 0.0,
        reciprocity=bool(reciprocity), far_field=far_field,
        far_options=_far_options(options.far), hmatrix_options=hm_options,
        # kernel version and tolerance: recorded in the .hfr, part of the checkpoint key
        form_factors={**kernel_settings(), **visibility_settings()})
