"""The precompute from an H-matrix of F: ``far_field="hierarchical"`` (issue 43; docs/method.md, section 4c).

Instead of streaming column blocks of F into HF, F is built once as an H-matrix
(:func:`hfrad.formfactors.hmatrix.build_hmatrix`: near leaf pairs exact, far cluster pairs
of low rank, O(n log n) pairs evaluated), and the global factors ``G_H = diag(rho_max) F_H
~= Q V^T`` come from products with it alone (:func:`hfrad.lowrank.operator_factorization`,
stopped by the exact ``||G_H||_F^2``). The internal order is the cluster tree's, so the
H-matrix's products need no permutation.

The pass statistics (row and column sums, the probe sketch, the per-solve sampled rows) are
linear in F or column sums of its squares, so they come from products and from the blocks
too (:meth:`~hfrad.solve.stats.PassStatistics.record_operator`); the sampled rows themselves
are exact rows of F, computed with the engine. What the H-matrix itself is off by,
``||A^1/2 (G - G_H) A^-1/2||_F``, is certified by exact rows drawn by importance (their
H-matrix norms; :class:`~hfrad.formfactors.certify.RowCertificate`) and added to
``fac.error_estimate()`` as the sampled far field's certificate is.
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Callable

import numpy as np

from ..formfactors.bfloat16 import value_dtype
from ..formfactors.certify import RowCertificate, row_errors
from ..formfactors.engine import FormFactorEngine
from ..formfactors.farfield import FarFieldCertificate, patch_boxes
from ..formfactors.hmatrix import FormFactorHMatrix, HMatrixOptions, build_hmatrix, cluster_tree
from ..lowrank.operator import operator_factorization
from ..errors import InputError
from ..memory import (HIERARCHICAL_RANK_ASSUMPTION, hierarchical_rank_guess, near_setup_bytes, operator_bytes,
                      precompute_peak_bytes, require)
from .. import resources
from ..progress import ProgressCallback
from ..scene.scene import Scene
from ..solve.prefetch import NearPrefetch, prefetch_fits
from ..solve.stats import PassStatistics
from ..solve.woodbury import HFactorization
from .assemble import PrecomputePlan, assemble, near_state
from .backends import Checkpoint
from .hmatrix_checkpoint import load_hmatrix_checkpoint, save_hmatrix_checkpoint

__all__ = ["factorize_hierarchical", "factorize_hmatrix", "engine_for", "tree_order", "check_hierarchical_memory",
           "hierarchical_peak_bytes",
           "resumed_hmatrix", "save_if_worth", "run_hierarchical", "CERTIFICATE_ROWS", "CERTIFICATE_SEED"]

#: Exact rows drawn (with replacement, by importance) to certify ``||G - G_H||``.
CERTIFICATE_ROWS = 256
CERTIFICATE_SEED = 4343
#: The operator factorization's random draws (the same seed: the same factors).
FACTORIZATION_SEED = 4344
#: The share of the factorization's error budget its range finder may leave (``range_share``): a
#: shallower range finder needs fewer products, and the truncation of B's SVD still finds a rank near
#: the optimal one. Cornell box, 39,482 patches, eps 0.05, the same H-matrix (before the near split
#: took the low-rank blocks' entries): 0.5 -> basis 512, rank 276, 25.4 s; 0.7 -> 448, 278, 20.8 s;
#: 0.85 -> 384, 282, 17.0 s; 0.95 -> 320, 292, 14.5 s (blocks of 32 vectors were slower: 32.0 and
#: 25.2 s). But a shallower range finder leaves error in directions a solve meets: Šibenik, 10,181
#: patches, rank 28 each time, the per-solve figure 7.4-7.6% at 0.5, 7.6-7.8% at 0.7, 9.6-9.8% at 0.85.
#: (An earlier note blamed F_H's own error for the large bases: it is far smaller, 0.3-0.9% of
#: ||G||_F on the Cornell box, and the same split of the exact F gives the same rank; the rank came
#: from the near split, see :meth:`FormFactorHMatrix.take_near`.)
RANGE_SHARE = 0.7
#: How the range finder draws its blocks (:func:`hfrad.lowrank.operator_factorization`, ``method``):
#: block Lanczos, two products a block instead of four. The same H-matrix each time (2-core AVX2 VM):
#: Cornell box, 161,808 patches, eps 0.05, from the checkpoint: after the build 192.2 s with "power"
#: (20 products, basis 320, rank 164, factorization 113.3 s), 175.2 s with "lanczos" (12, 384, 163,
#: 96.7 s), the per-solve figure 22.1-28.9% both; 39,482 patches, eps 0.02: 224.7 s against 202.2 s
#: for the factorization, rank 1,883 against 1,819; eps 0.05 end to end 74.1 s against 73.7 s, the
#: figure 10.1-11.7% against 10.2-12.1%. Šibenik, 10,181 patches: 53.9 s against 52.4 s, rank 31 both.
RANGE_METHOD = "lanczos"
#: Entries of exact rows computed by one engine call (float64: 32 MB).
EXACT_CHUNK = 1 << 22


def tree_order(scene: Scene, options: HMatrixOptions) -> np.ndarray:
    """(n,) the H-matrix's tree order of ``scene`` (what :func:`build_hmatrix` will build; deterministic)."""
    lo, hi = patch_boxes(scene)
    return cluster_tree(scene.centroids, lo, hi, options.leaf_size).perm


def factorize_hierarchical(scene: Scene, plan: PrecomputePlan, progress: ProgressCallback = None,
                           status=None, *, blas_threads: int | None = 1,
                           checkpoint: Checkpoint | None = None) -> HFactorization:
    """Run ``plan`` (``far_field="hierarchical"``) in this process: H-matrix, operator factorization,
    statistics and certificate, then the solver object (:func:`~hfrad.precompute.assemble.assemble`).

    Parameters
    ----------
    scene : Scene
    plan : PrecomputePlan
        With ``far_field="hierarchical"`` (its ``perm`` the tree order, no near-field split).
    progress : callable, optional
        ``progress(done, total)``: the H-matrix's exact blocks, then the basis columns.
    status : callable, optional
        Called once, after the factorization, with ``blocks`` (0), ``rank`` and ``elapsed``.
    blas_threads : int or None
        BLAS threads throughout (``LocalBackend.blas_threads``, default 1): numba's parallel products
        and multi-threaded OpenBLAS spin against each other; on the 2-core machine the operator
        factorization of 1,508 patches took 79 s with the default BLAS threads and 4.1 s with one.
    checkpoint : Checkpoint, optional
        The built H-matrix is saved at ``checkpoint.path`` (once, when it is built: most of the run's
        time; only when the build took at least ``checkpoint.interval``), and a rerun that finds it
        there loads it instead of building it (:mod:`~hfrad.precompute.hmatrix_checkpoint`; ``status``
        is then called with ``resumed``, the blocks loaded, and ``resumed_unit``). Deleted on
        completion unless ``checkpoint.keep``.

    Returns
    -------
    HFactorization

    Raises
    ------
    MemoryLimitError
        The estimate (:func:`hfrad.memory.precompute_peak_bytes`: the H-matrix and its factorization, or
        the near field's set-up with its sparse LUs where that is larger) exceeds 80% of the available memory.
    """
    def build(engine: FormFactorEngine) -> FormFactorHMatrix:
        with resources.blas_threads(blas_threads):
            return build_hmatrix(scene, engine, plan.hmatrix_options, progress)

    return run_hierarchical(scene, plan, build, progress, status, checkpoint=checkpoint, blas_threads=blas_threads)


def run_hierarchical(scene: Scene, plan: PrecomputePlan, build: Callable[[FormFactorEngine], FormFactorHMatrix],
                     progress: ProgressCallback = None, status=None, *, checkpoint: Checkpoint | None = None,
                     blas_threads: int | None = 1, backend: dict | None = None,
                     remove_checkpoint: Callable[[], None] | None = None) -> HFactorization:
    """The hierarchical path's steps in their order, whichever backend builds the H-matrix: the memory
    check; the H-matrix resumed from ``checkpoint`` or built (``build(engine)``) and saved; the rest
    (:func:`factorize_hmatrix`); the checkpoint removed on completion unless ``checkpoint.keep``
    (``remove_checkpoint()``, default: its file deleted). ``backend`` (recorded in ``params``) is read
    after the build, which may fill it in."""
    check_hierarchical_memory(plan, scene.is_clustered)
    t0 = time.perf_counter()
    engine = engine_for(scene, plan)
    try:
        hm = resumed_hmatrix(scene, plan, checkpoint, status)
        if hm is None:
            hm = build(engine)
            save_if_worth(hm, scene, plan, checkpoint, time.perf_counter() - t0)
        fac = factorize_hmatrix(scene, plan, engine, hm, progress, status, t0=t0, blas_threads=blas_threads,
                                backend=backend)
    finally:
        engine.close()
    if checkpoint is not None and not checkpoint.keep:
        if remove_checkpoint is None:
            Path(checkpoint.path).unlink(missing_ok=True)
        else:
            remove_checkpoint()
    return fac


def hierarchical_peak_bytes(plan: PrecomputePlan, clustered: bool = False) -> int:
    """The plan's estimated peak, bytes (:func:`hfrad.memory.precompute_peak_bytes` with its near field,
    dtype and H-matrix values; ``clustered``: the scene's patches are clusters of triangles)."""
    return precompute_peak_bytes(plan.n, plan.block_size, far_field="hierarchical", near_entries=plan.near_entries,
                                 itemsize=np.dtype(plan.dtype).itemsize, clustered=clustered,
                                 hmatrix_value_bytes=value_dtype(plan.hmatrix_options.values).itemsize)


def check_hierarchical_memory(plan: PrecomputePlan, clustered: bool = False) -> None:
    """Refuse a plan whose estimate (:func:`hierarchical_peak_bytes`) exceeds 80% of the available memory."""
    n = plan.n
    require(hierarchical_peak_bytes(plan, clustered),
            f"precomputing {n:,} patches with far_field='hierarchical'"
            + (f" and {plan.near_entries} near-field entries a row" if plan.near_entries else ""),
            f"use fewer patches, a larger eps or fewer near-field entries (the estimate assumes a rank of "
            f"{hierarchical_rank_guess(n):,}: {HIERARCHICAL_RANK_ASSUMPTION})")


def basis_guard(n: int, plan: PrecomputePlan, held: int) -> Callable[[int, int], None]:
    """The memory check of the operator factorization as its basis grows from l to ``l + more`` columns
    (the rank is at most that): what the rest of the run adds to what the process holds now, the larger
    of the factorization's growth (:func:`hfrad.memory.operator_bytes`) and the solver set-up at that
    rank (:func:`hfrad.memory.near_setup_bytes`, less the H-matrix's ``held`` bytes and the basis, both
    released before it), refused with the number. The check before the run assumed a rank
    (:func:`hfrad.memory.hierarchical_rank_guess`); this one sees the rank the scene and eps need."""
    s = np.dtype(plan.dtype).itemsize

    def guard(columns: int, more: int) -> None:
        k = columns + more
        now = operator_bytes(n, columns, s)
        grow = operator_bytes(n, k, s) - now
        setup = near_setup_bytes(n, plan.near_entries, k, s) - held - now
        require(max(grow, setup), f"the operator factorization of {n:,} patches at a basis of {k:,} columns "
                f"(eps {plan.eps:g})", "a larger eps needs a smaller rank; or use fewer patches")
    return guard


def save_if_worth(hm: FormFactorHMatrix, scene: Scene, plan: PrecomputePlan, checkpoint: Checkpoint | None,
                  seconds: float) -> None:
    """Save the built ``hm`` at ``checkpoint.path`` when its build took at least the checkpoint's interval:
    one write, as the column pass writes (39,482 patches: 2.5 s for a 46 s build, 600 MB; about 5.5
    float32 bytes a stored float)."""
    if checkpoint is not None and seconds >= checkpoint.interval:
        save_hmatrix_checkpoint(hm, checkpoint.path, plan.key(scene))


def resumed_hmatrix(scene: Scene, plan: PrecomputePlan, checkpoint: Checkpoint | None, status):
    """The H-matrix saved at ``checkpoint.path`` by an earlier run, or None (no checkpoint, or none yet)."""
    if checkpoint is None or not Path(checkpoint.path).exists():
        return None
    hm = load_hmatrix_checkpoint(checkpoint.path, plan.key(scene), plan.perm)
    hm.info["resumed"] = True
    if status is not None:
        status({"blocks": 0, "rank": 0, "elapsed": 0.0, "resumed": hm.blocks.count,
                "resumed_unit": "H-matrix blocks were built"})
    return hm


def factorize_hmatrix(scene: Scene, plan: PrecomputePlan, engine: FormFactorEngine, hm: FormFactorHMatrix,
                      progress: ProgressCallback = None, status=None, *, t0: float | None = None,
                      blas_threads: int | None = 1, backend: dict | None = None) -> HFactorization:
    """The rest of :func:`factorize_hierarchical` once the H-matrix ``hm`` of ``scene`` is built with
    ``engine`` (which then computes the exact rows): factors, statistics, certificate, solver object.
    ``hm`` is used up: its near entries leave it and its blocks are released once the factors are found.
    ``t0``: when the run started (``perf_counter``; default now), for the recorded timings; ``backend``:
    recorded in ``params`` (default ``{"backend": "local"}``)."""
    if not np.array_equal(hm.perm, plan.perm):
        raise InputError("the H-matrix's tree order differs from the plan's: build it with plan.hmatrix_options")
    with resources.blas_threads(blas_threads):
        return _factorize_hmatrix(scene, plan, engine, hm, progress, status, time.perf_counter() if t0 is None else t0,
                                  backend or {"backend": "local"})


def _factorize_hmatrix(scene, plan, engine, hm, progress, status, t0, backend) -> HFactorization:
    n, dt = plan.n, np.dtype(plan.dtype)
    t_hm = time.perf_counter()
    rho = plan.rows_rho(scene)[:, 0].astype(np.float64)
    areas = plan.stats_weights(scene)
    rows2 = hm.squares(np.column_stack([np.ones(n), 1.0 / areas]), columns=False)
    norm2 = float(np.dot(rho ** 2, rows2[:, 0]))            # ||G||_F^2, G = diag(rho) F_H
    # the pass statistics and the certificate read the whole F (as the column blocks' pass does) ...
    stats = PassStatistics(n, areas, reflectance=scene.reflectance[plan.perm])
    exact = _RowSource(engine, plan.perm)
    sample_rows = None if stats.samples is None else exact.rows(stats.samples.row_patches, np.float32)
    stats.record_operator(hm.matmat, hm.rmatmat, lambda s: hm.squares(s, columns=True), rho,
                          sample_rows)
    t_stats = time.perf_counter()
    # importance: each row's rho sqrt(A)-weighted norm in F_H, the sampled field's predictor (its errors
    # grew with it); on the Cornell box at 1,508 patches uniform draws did as well (docs/method.md, 4c)
    weights = rho * np.sqrt(areas * np.maximum(rows2[:, 1], 0.0))
    stats.far_field, certificate = _certify(hm, exact, rho, areas, weights)
    t_cert = time.perf_counter()
    # ... then the near field's entries leave the H-matrix (kept sparse and exact, as the split of the
    # column blocks keeps them) and G - N is factored within eps of the whole G (its rank is far lower:
    # 1,898 -> 214 at 9,986 patches, eps 0.05)
    near = prefetch = None
    if plan.near_entries:
        r, c, v = hm.take_near(scene.centroids[plan.perm], plan.near_radius)
        near = near_state([r], [c], [rho[r] * v])
        entries = r.size
        del r, c, v     # near holds its own copies: 24 bytes an entry less through the range finder
        # the solver's sparse LUs need only N: factored beside the range finder, on the core its
        # single-threaded steps leave idle (hfrad.solve.prefetch), where they fit beside the H-matrix
        # (Šibenik, 60,568 patches: 10.3 GB for one channel's factorization, 278 s; the run was killed
        # at 24.3 GB when they were factored beside it)
        # decided on N's own entries a row, as the set-up decides between its LUs and sweeps
        # (near_setup_runner): the plan's 242 a row at 10,181 Šibenik patches are 145 in N, so
        # the set-up factored but nothing was prefetched (eps 0.02: set-up 8.0 s, wall 57.2 s; now 2.9 s, 49.5 s)
        if prefetch_fits(n, round(entries / max(1, n))):
            prefetch = NearPrefetch(near, n, scene.reflectance, plan.perm, dt)
    finished = False
    try:
        target = plan.eps * math.sqrt(norm2) if plan.relative else plan.eps
        rho_dt = rho.astype(dt)[:, None]    # products in the factors' dtype (float32: twice as fast)
        lowrank = operator_factorization(lambda X: rho_dt * hm.matmat(X), lambda X: hm.rmatmat(rho_dt * X),
                                         n, hm.frobenius2(rho), eps=target, relative=False, dtype=dt,
                                         rng=FACTORIZATION_SEED, range_share=RANGE_SHARE, method=RANGE_METHOD,
                                         progress=progress, guard=basis_guard(n, plan, hm.nbytes))
        lowrank.norm, lowrank.eps, lowrank.relative = math.sqrt(norm2), plan.eps, plan.relative
        hm.release()        # not needed by the solver set-up, whose near-field LUs may take gigabytes
        t_fac = time.perf_counter()
        if status is not None:
            status({"blocks": 0, "rank": lowrank.rank, "elapsed": t_fac - t0})
        lowrank.info.update({"time_formfactors": t_hm - t0, "time_statistics": t_stats - t_hm,
                             "time_certificate": t_cert - t_stats, "time_factorization": t_fac - t_cert,
                             "time_precompute": t_fac - t0,
                             "hierarchical": {**hm.info, "factorization": {k: v for k, v in lowrank.info.items()
                                                                           if not k.startswith("time")},
                                              "certificate": certificate, "exact_row_pairs": int(exact.pairs)}})
        fac = assemble(scene, plan, lowrank, stats, near, backend=backend,
                       runner=None if prefetch is None else prefetch.runner())
        fac.lowrank.info["time_assemble"] = time.perf_counter() - t_fac
        if prefetch is not None:
            fac.lowrank.info["near_prefetched"] = prefetch.hits
        finished = True
        return fac
    finally:
        if prefetch is not None:
            prefetch.close(wait=finished)   # Ctrl-C or an error: not after the LU in flight


def engine_for(scene: Scene, plan: PrecomputePlan) -> FormFactorEngine:
    """The form-factor engine with the plan's visibility settings (as the column blocks' pass has them),
    casting each batch of rays on every core: this path calls :meth:`~FormFactorEngine.block` only."""
    kwargs = {"ray_threads": None}
    if plan.samples is not None:
        kwargs["samples"] = plan.samples
    if plan.samples != 0:
        kwargs["ray_budget"] = plan.ray_budget(scene)
    return FormFactorEngine(scene, **kwargs)


class _RowSource:
    """Exact rows of F at internal positions, a few at a time (``EXACT_CHUNK`` entries an engine call)."""

    def __init__(self, engine: FormFactorEngine, perm: np.ndarray) -> None:
        self.engine, self.perm = engine, perm
        self.pairs = 0

    def chunks(self, rows: np.ndarray):
        """``(slice, F[rows[slice]])`` (float64, columns in internal order) over ``rows``."""
        step = max(1, EXACT_CHUNK // max(1, self.perm.size))
        for a in range(0, rows.size, step):
            part = rows[a:a + step]
            self.pairs += part.size * self.perm.size
            yield slice(a, a + part.size), self.engine.block(self.perm[part], self.perm)

    def rows(self, rows: np.ndarray, dtype) -> np.ndarray:
        out = np.empty((rows.size, self.perm.size), dtype)
        for where, F in self.chunks(np.asarray(rows, np.int64)):
            out[where] = F
        return out


def _certify(hm: FormFactorHMatrix, exact: _RowSource, rho, areas, weights) -> tuple[FarFieldCertificate, dict]:
    """The certificate of ``||A^1/2 diag(rho) (F - F_H) A^-1/2||_F`` from ``CERTIFICATE_ROWS`` exact rows
    drawn by ``weights`` (a :class:`RowCertificate`), as the sampled far field's certificate object
    (its slots' totals over n: the solver adds its upper figure to the operator error)."""
    n = hm.n
    draw = RowCertificate.draw(n, CERTIFICATE_ROWS, weights, seed=CERTIFICATE_SEED)
    unique, inverse = np.unique(draw.rows, return_inverse=True)
    approx = hm.rows(unique)
    e = np.empty(unique.size)
    pairs0 = exact.pairs
    for where, F in exact.chunks(unique):
        e[where] = row_errors(F - approx[where], unique[where], rho, areas)
    y = e[inverse] * draw.scale
    certificate = FarFieldCertificate(np.arange(y.size, dtype=np.int64), y / n, n, CERTIFICATE_SEED)
    estimate, upper = certificate.frobenius()
    return certificate, {"rows": int(draw.rows.size), "distinct_rows": int(unique.size),
                         "pairs": int(exact.pairs - pairs0), "weighted": True,
                         "error_estimate": estimate, "error_upper": upper}
