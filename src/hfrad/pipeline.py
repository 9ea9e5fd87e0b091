"""The precomputation's public facade: ``hfrad.factorize`` and its siblings.

``factorize(scene)`` is what ``hfrad precompute`` runs: it validates the options once
(:func:`~hfrad.precompute.options.plan_precompute`) and hands the plan to a backend,
this process (:mod:`hfrad.precompute.local`) or a Dask cluster (:mod:`hfrad.distributed`).
``factorize_matrix`` and ``factorize_blocks`` (:mod:`hfrad.precompute.matrix`) take a
form-factor matrix you already have. The objects of the front door, :class:`LocalBackend`,
:class:`DaskBackend`, :class:`Checkpoint` and :class:`PrecomputeOptions`, live in
:mod:`hfrad.precompute` and are re-exported here and as ``hfrad.*``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

from .errors import InputError
from .precompute.backends import Checkpoint, DaskBackend, LocalBackend, as_checkpoint
from .precompute.local import factorize_local
from .precompute.matrix import factorize_blocks, factorize_matrix
from .precompute.options import PrecomputeOptions, plan_precompute
from .progress import ProgressCallback
from .scene.scene import Scene
from .solve.woodbury import HFactorization

__all__ = ["factorize", "factorize_matrix", "factorize_blocks", "LocalBackend", "DaskBackend", "Checkpoint",
           "PrecomputeOptions"]

StatusCallback = Callable[[dict], None] | None


def factorize(scene: Scene, eps: float = 0.02, *, relative: bool = True, dtype="float32", order=None,
              near_field: int | str | None = "auto", backend: LocalBackend | DaskBackend | None = None,
              checkpoint: str | Path | Checkpoint | None = None, options: PrecomputeOptions | None = None,
              far_field: str = "auto", progress: ProgressCallback = None,
              status: StatusCallback = None) -> HFactorization:
    """Factor a radiosity system once: ``diag(rho_max) F ~= Q V^T``, then solve it for any light in O(nk).

    Parameters
    ----------
    scene : Scene
        Patches, materials and lights (:func:`hfrad.load_scene`). Form factors
        with visibility are computed and streamed in column blocks; the n x n
        matrix is never formed. For a matrix you already have, use
        :func:`factorize_matrix`.
    eps : float in (0, 1)
        Target ``||G - Q V^T||_F`` relative to ``||G||_F`` (absolute with
        ``relative=False``), ``G = diag(rho_max) F``.
    relative : bool
        ``eps`` relative to ``||G||_F`` (default) or absolute.
    dtype : {"float32", "float64"}
        Precision of the factors.
    order : {"zorder", "hilbert", "random", "input"} or (n,) int, optional
        Internal patch order (internal index t holds user patch order[t]);
        default Z-order (the paper's). Only speed and rank depend on it:
        every input and output stays in the user's order.
    near_field : "auto", int or None
        The near-field split (docs/method.md; :mod:`hfrad.lowrank.nearsplit`):
        pairs within a radius holding about this many neighbours per row go into
        a sparse N, HF factors only ``G - N``, and the solver is Woodbury around a
        sparse LU of ``I - D_c N`` (:class:`~hfrad.solve.nearfield.NearFieldFactorization`).
        "auto" (default): ``DEFAULT_NEAR_ENTRIES`` (120) facing neighbours per row where
        the split pays, off below (:func:`~hfrad.precompute.options.near_field_pays_from`: from 20,000 patches at
        eps 0.02, ``20,000 (0.02 / eps)^1.5`` patches at other relative eps (5,060 at 0.05), never below
        2,000; a clustered scene from 2,000 on, with more neighbours from 4,000 patches:
        :func:`~hfrad.precompute.options.clustered_near_entries`, 400 at most); None or 0: off (plain Woodbury). The split lowers the rank HF needs (the near pairs hold F's
        high-rank part) and, at equal eps, the radiosity error; it costs a sparse LU
        of ``I - D_c N`` (about 12 bytes per entry, ``n * near_field`` entries).
    backend : LocalBackend or DaskBackend, optional
        Where the column blocks, leaves and merges run: this process (default
        ``LocalBackend()``: one process, one BLAS thread while the form-factor engine
        runs, the reciprocity copy) or a Dask cluster (``DaskBackend(scheduler=...)`` or
        ``DaskBackend(workers=4)``, docs/cluster.md). Same class, same ``.hfr`` contents
        and error figures either way (only ``params["backend"]``, ``params["workers"]``
        and the timings differ). See :mod:`hfrad.precompute.backends`.
    checkpoint : path or Checkpoint, optional
        Save the run while it goes and resume from it if it exists; deleted when the
        factorization completes (``Checkpoint(path, interval=30.0, keep=False)``; a
        path is ``Checkpoint(path)``). In this process, the stream state is written at
        least ``interval`` seconds apart, and at least ``CHECKPOINT_COST_RATIO`` (50)
        times the last write's duration apart; on Dask, the path names a folder of the
        finished subtrees' factors, so a rerun skips them. A damaged checkpoint, or
        one made for another input, is refused (FileFormatError / InputError), never resumed.
    options : PrecomputeOptions, optional
        Expert knobs: ``block_size`` (column block width, default ``min(256, n)``),
        ``samples`` (visibility rays per patch pair), ``leaf_share`` (the leaf SVDs'
        share of the squared error budget, 0.5), ``one_ray_tol`` (the ray budget's
        share of ``||F||_F``; default ``eps / 4`` for a relative eps, off for an absolute one).
    far_field : {"auto", "exact", "sampled", "hierarchical"}
        How the form factors of well-separated pairs are found. "exact": every pair is
        computed (half of them copied by reciprocity). "sampled": near rows of each column
        block exactly, far rows from a few sampled rows and skeleton columns, checked on
        held-out rows and computed exactly where they do not compress; visibility of far
        pairs from cluster-pair tests and probe rays (:mod:`hfrad.formfactors.farfield`,
        docs/method.md section 4b). Its error is certified by exact rows of a separate
        sample (added to ``fac.error_estimate()``). "auto" (default): the one measured faster
        (:func:`~hfrad.precompute.options.far_field_mode`): "hierarchical" in this process from
        20,000 patches at a relative eps of 0.05 or more on a scene that is not clustered, else
        "exact" (a smaller or absolute eps, fewer patches, a clustered scene, a custom ``order``,
        a ``DaskBackend``); "sampled" is never chosen
        (it evaluates 4-5 times fewer pairs than the exact pass but costs more wall time per
        block). "sampled" runs on both backends: a ``DaskBackend``'s leaves run the same block producer
        (the same factorization, certificate and counters as this process's).
        "hierarchical": F as an H-matrix (near leaf pairs exact, far cluster pairs of low
        rank by cross approximation; :mod:`hfrad.formfactors.hmatrix`), the factors from
        products with it (:func:`hfrad.lowrank.operator_factorization`), its error certified
        by exact rows drawn by importance (added to ``fac.error_estimate()``); docs/method.md
        section 4c. With a ``DaskBackend`` the workers build the H-matrix in parts and this
        process factors it (:mod:`hfrad.distributed.hierarchical`; the same blocks). The internal
        order is the cluster tree's (``order`` is not used); with ``near_field="auto"`` the near
        pairs leave the H-matrix (the split costs nothing there); a ``checkpoint`` saves the
        built H-matrix once (when the build took at least its interval; on Dask, a file in the
        checkpoint's folder) and a rerun loads it instead of building it; memory
        :func:`hfrad.memory.precompute_peak_bytes` (this process holds the whole H-matrix).
    progress : callable (done, total), optional
        Column blocks done.
    status : callable (dict), optional
        Called after each block with ``blocks``, ``rank``, ``elapsed`` (seconds);
        in this process, the first call after resuming from a ``checkpoint`` also
        has ``resumed``: the blocks the checkpoint held, and a fresh run's first call,
        before any block (``blocks`` 0, ``rank`` 0), has ``estimate``: the form-factor
        pass's wall seconds estimated from the kernel timed on a sample
        (:func:`~hfrad.precompute.local.estimate_form_factor_seconds`).

    Returns
    -------
    HFactorization
        ``fac.solve(E)`` gives the radiosity for any exitance E, in O(nk).

    Raises
    ------
    InputError (a ValueError)
        Bad shapes, values or options (names the argument).
    SceneError
        A scene without patches.

    Notes
    -----
    Memory, b = ``options.block_size``, k = rank, s = the dtype's itemsize: about
    ``40 n b + (2 n k + 3 k^2) s + 4 n k s`` bytes (five float64 column
    blocks, the factors, a merge: :func:`hfrad.memory.precompute_bytes`), plus
    the reciprocity tiles (at most ``n^2 s / 4``:
    :func:`hfrad.formfactors.mirror.mirror_bytes`) and, with the near field of
    c entries a row, O(n c). Time: for a scene, dominated by the form factors. docs/method.md
    explains the method; Aguerre & Fernández 2016.

    Examples
    --------
    >>> import hfrad
    >>> scene = hfrad.load_scene("furnace", patches=60)     # a closed box, uniform materials
    >>> fac = hfrad.factorize(scene, eps=0.05)
    >>> B = fac.solve(scene.emission)                        # (60, 3) W/m^2, user order
    >>> B.shape
    (60, 3)
    >>> fac = hfrad.factorize(scene, 0.05, backend=hfrad.LocalBackend(processes=1),
    ...                       options=hfrad.PrecomputeOptions(block_size=32))
    >>> fac.params["block_size"]
    32
    """
    if not isinstance(scene, Scene):
        if isinstance(scene, (str, Path)):
            raise InputError(f"factorize takes a Scene; load the file first: hfrad.load_scene({str(scene)!r})")
        raise InputError(f"factorize takes a Scene, not {type(scene).__name__}; for a form-factor "
                         "matrix use hfrad.factorize_matrix(F, reflectance)")
    if backend is None:
        backend = LocalBackend()
    elif not isinstance(backend, (LocalBackend, DaskBackend)):
        raise InputError(f"backend must be an hfrad.LocalBackend or hfrad.DaskBackend; got {type(backend).__name__}")
    checkpoint = as_checkpoint(checkpoint)
    plan = plan_precompute(scene, eps, relative=relative, dtype=dtype, order="zorder" if order is None else order,
                           near_field=near_field, options=options, reciprocity=backend.reciprocity,
                           far_field=far_field, local=isinstance(backend, LocalBackend))
    if plan.far_field == "hierarchical":
        if not isinstance(backend, LocalBackend):
            from .distributed.hierarchical import factorize_hierarchical_distributed

            return factorize_hierarchical_distributed(scene, plan, backend, checkpoint=checkpoint, progress=progress,
                                                      status=status)
        from .precompute.hierarchical import factorize_hierarchical

        return factorize_hierarchical(scene, plan, progress, status, blas_threads=backend.blas_threads,
                                      checkpoint=checkpoint)
    if isinstance(backend, LocalBackend):
        return factorize_local(scene, plan, backend, checkpoint, progress, status)
    from .distributed import factorize_distributed, remove_checkpoint

    fac = factorize_distributed(scene, plan, backend, checkpoint=None if checkpoint is None else checkpoint.path,
                                progress=progress, status=status)
    if checkpoint is not None and not checkpoint.keep:
        remove_checkpoint(checkpoint.path)
    return fac
