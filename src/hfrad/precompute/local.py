"""The precompute in this process: form-factor column blocks streamed into HF, checkpointed.

Column blocks of ``G = diag(rho_max) F`` are generated one at a time in the plan's
internal order (Z-order by default), pushed into a
:class:`~hfrad.lowrank.hf.HFStream` and dropped, so the n x n matrix never exists.
With a :class:`~hfrad.precompute.backends.Checkpoint` the stream state (with the pass
statistics and the near entries so far) is saved every ``interval`` seconds and a
rerun resumes after the last saved block. The sibling of :mod:`hfrad.distributed`,
which runs the same plan as Dask tasks; both end in
:func:`~hfrad.precompute.assemble.assemble`.
"""

from __future__ import annotations

import contextlib
import time
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..formfactors.blocks import Consumer, iter_column_blocks
from ..formfactors.engine import FormFactorEngine
from ..formfactors.farfield import (FarFieldCertificate, FarFieldStats, SampledFarField,
                                    sampled_column_blocks)
from ..lowrank.hf import HFStream
from ..lowrank.nearsplit import NearFieldSplit
from ..lowrank.streaming import load_checkpoint, save_checkpoint
from ..memory import RANK_ASSUMPTION, near_setup_bytes, precompute_bytes, rank_guess, require
from ..progress import ProgressCallback, report
from ..resources import blas_threads, cores
from ..scene.scene import Scene
from ..solve.stats import PassStatistics
from ..solve.woodbury import HFactorization
from .assemble import PrecomputePlan, assemble, far_block
from .backends import Checkpoint, LocalBackend

__all__ = ["factorize_local", "estimate_form_factor_seconds", "CHECKPOINT_COST_RATIO", "PASS_OVER_KERNEL",
           "PASS_OVER_KERNEL_CLUSTERED", "pass_over_kernel"]

#: Prefix of the pass statistics among a checkpoint's extra arrays.
_STATS = "stats_"
#: A checkpoint is written at most once per this many times its last write took, so that
#: writing them costs at most ~2% (1/50) of the run: the state grows with the near field (24
#: bytes an entry, 24 n c bytes for c entries a row) and with the rank (O(n k)), so a fixed
#: interval would spend a growing share of a large run writing.
CHECKPOINT_COST_RATIO = 50.0
#: A push whose merges form a node of at least this share of all column blocks gets every BLAS thread.
_LARGE_MERGE_SHARE = 0.25


def factorize_local(scene: Scene, plan: PrecomputePlan, backend: LocalBackend | None = None,
                    checkpoint: Checkpoint | None = None, progress: ProgressCallback = None,
                    status=None) -> HFactorization:
    """Run ``plan`` in this process: streamed form factors into HF, then the solver object.

    Parameters
    ----------
    scene : Scene
    plan : PrecomputePlan
        From :func:`~hfrad.precompute.options.plan_precompute`.
    backend : LocalBackend, optional
        Form-factor processes and BLAS threads (default ``LocalBackend()``); its
        ``reciprocity`` is the plan's.
    checkpoint : Checkpoint, optional
        Resume from ``checkpoint.path`` if it exists, save there while running.
    progress, status
        As in :func:`hfrad.factorize`.

    Returns
    -------
    HFactorization or NearFieldFactorization

    Raises
    ------
    MemoryLimitError
        With the near field: its set-up (:func:`hfrad.memory.near_setup_bytes`, the sparse LUs
        included) is estimated above 80% of the available memory. The pass itself adapts: its
        reciprocity tiles take what the rest leaves.
    """
    backend = LocalBackend() if backend is None else backend
    n, block_size, dt = plan.n, plan.block_size, np.dtype(plan.dtype)
    if plan.near_entries:
        require(near_setup_bytes(n, plan.near_entries, itemsize=dt.itemsize),
                f"the near field's set-up for {n:,} patches ({plan.near_entries} entries a row)",
                f"use fewer patches, a larger eps or fewer near-field entries (near_field=...; the estimate "
                f"assumes a rank of {rank_guess(n):,}: {RANK_ASSUMPTION})")
    perm, n_blocks = plan.perm, plan.n_blocks
    key = plan.key(scene)
    path = None if checkpoint is None else checkpoint.path
    stream = _open_stream(path, key, plan)
    stats = _open_stats(stream, n, plan.stats_weights(scene), scene.reflectance[perm])
    t0 = time.perf_counter()
    ff_kwargs = {} if plan.samples is None else {"samples": plan.samples}
    if plan.samples != 0:
        ff_kwargs["ray_budget"] = plan.ray_budget(scene)
    time_budget = time.perf_counter() - t0
    if status is not None and not stream.blocks_done and plan.far_field != "sampled":   # every pair's kernel
        t = time.perf_counter()
        estimate = estimate_form_factor_seconds(scene, plan)
        time_budget += time.perf_counter() - t
        status({"blocks": 0, "rank": 0, "elapsed": time.perf_counter() - t0, "estimate": estimate,
                "pass_over_kernel": pass_over_kernel(scene)})
    mirror_stats: dict = {}   # what the reciprocity copy did (pairs copied, scratch I/O), kept in info
    # the reciprocity tiles leave free what the rest of the run is estimated to need; those beyond
    # the memory band spill to a scratch file beside the output (its checkpoint), else in TMPDIR;
    # blocks are lent (no copy): _stream_blocks is done with each before it asks for the next
    consumer = Consumer(reserved_bytes=precompute_bytes(n, block_size, itemsize=dt.itemsize), lend=True)
    rows_rho = plan.rows_rho(scene)
    producer = None
    if plan.far_field == "sampled":
        producer = _sampled_far_field(scene, plan, stats, ff_kwargs)
        blocks = sampled_column_blocks(producer, dt, first_block=stream.blocks_done)
    else:
        blocks = iter_column_blocks(scene, block_size, order=perm, first_block=stream.blocks_done,
                                    processes=backend.processes, dtype=dt, reciprocity=plan.reciprocity,
                                    scratch=None if path is None else Path(path).parent,
                                    mirror_stats=mirror_stats, consumer=consumer, **ff_kwargs)
    split = None
    if plan.near_entries:
        split = NearFieldSplit(scene.centroids[perm], plan.near_radius)
        if stream.blocks_done:
            split.restore(stream.extra)
    with blas_threads(backend.blas_threads):
        times = _stream_blocks(blocks, stream, stats, rows_rho, checkpoint, key, progress, status, t0, split)
    # the last merges (the largest: up to the root) once the form-factor engine has stopped,
    # with every BLAS thread
    t_finish = time.perf_counter()
    lowrank = stream.finish()
    times["time_hf"] += time.perf_counter() - t_finish
    lowrank.info.update({**times, "time_setup": time_budget, "time_precompute": time.perf_counter() - t0})
    if mirror_stats:
        lowrank.info["reciprocity"] = mirror_stats
    if producer is not None:
        lowrank.info["far_field"] = _far_field_report(producer)
        producer.close()
    t_assemble = time.perf_counter()
    fac = assemble(scene, plan, lowrank, stats, None if split is None else split.state(),
                   backend={"backend": "local"})
    fac.lowrank.info["time_assemble"] = time.perf_counter() - t_assemble
    if checkpoint is not None and not checkpoint.keep:
        Path(checkpoint.path).unlink(missing_ok=True)
    return fac


#: The form-factor pass's wall time over what its kernel's time per pair on the sample predicts (the
#: rays, their set-up, the pipeline around them), for :func:`estimate_form_factor_seconds`. Measured
#: on the project's shared 2-core machine (load 13-16), eps 0.02: the Cornell box at 2,974 patches
#: 14.3 s against 3.5 s (4.1), clustered Sponza at 3,129 patches 384 s against 86 s (4.5).
PASS_OVER_KERNEL = 4.0
#: The same for clustered patches (real meshes: the kernel is most of the pass since the second
#: visibility round picks its rays by weight and the pipeline overlaps kernel and rays). Measured on the
#: idle 2-core machine, eps 0.02, ~3,100 patches: Sponza 14.0 s against 7.3 s (1.9), the conference
#: room 19.2 s against 11.0 s (1.75), Sibenik 14.3 s against 4.5 s (3.2); the Cornell box at 2,974
#: patches 1.7-2.1 s against 0.5 s (about 4, as above).
PASS_OVER_KERNEL_CLUSTERED = 2.5


def pass_over_kernel(scene: Scene) -> float:
    """:data:`PASS_OVER_KERNEL`, or :data:`PASS_OVER_KERNEL_CLUSTERED` for patches that are clusters."""
    return PASS_OVER_KERNEL_CLUSTERED if getattr(scene, "is_clustered", False) else PASS_OVER_KERNEL

#: Columns of the unoccluded kernel timed for the estimate (spread over the internal order).
ESTIMATE_COLUMNS = 16


def estimate_form_factor_seconds(scene: Scene, plan: PrecomputePlan) -> float:
    """Wall seconds the form-factor pass will take here, from the kernel timed on a sample.

    The unoccluded kernel (clustered or not, as the scene's patches are) is timed on
    ``ESTIMATE_COLUMNS`` columns spread over the scene, with every row, in this process's
    threads; its time per pair times the pairs the pass computes (about n^2 / 2 with the
    reciprocity copy, n^2 without), times :func:`pass_over_kernel` for the rays (1 without
    visibility). Costs about ``ESTIMATE_COLUMNS / n`` of the kernel's work.
    """
    from ..formfactors.clustered import kernel_for

    n = plan.n
    if n == 0:
        return 0.0
    geom, block = kernel_for(scene)
    cols = np.unique(np.linspace(0, n - 1, min(n, ESTIMATE_COLUMNS)).astype(np.int64))
    rows = np.arange(n)
    block(geom, rows[:1], cols[:1])   # compiled (or loaded from numba's cache) before the clock starts
    t = time.perf_counter()
    block(geom, rows, cols)
    per_pair = (time.perf_counter() - t) / (n * len(cols))
    pairs = n * (n + 1) / 2 if plan.reciprocity else float(n) * n
    return per_pair * pairs * (pass_over_kernel(scene) if plan.samples != 0 else 1.0)


def sampled_far_field(scene: Scene, plan: PrecomputePlan, stats: PassStatistics, ff_kwargs: dict,
                      ray_threads: int | None = None) -> SampledFarField:
    """The sampled far field's block producer (both backends'): the plan's engine settings, and the
    exact rows the pass statistics' per-solve samples want beside each block."""
    engine = FormFactorEngine(scene, ray_threads=ray_threads, **ff_kwargs)
    rows = stats.samples.row_patches if stats.samples is not None else ()
    return SampledFarField(scene, engine, plan.perm, plan.block_size, plan.rows_rho(scene)[:, 0], plan.eps,
                           weights=stats.weights, exact_rows=rows, near_radius=plan.near_radius,
                           options=plan.far_options)


def _sampled_far_field(scene: Scene, plan: PrecomputePlan, stats: PassStatistics, ff_kwargs: dict):
    """The in-process producer (blocks one at a time: every core casts); its certificate joins the
    pass statistics (resumed from them after a checkpoint)."""
    producer = sampled_far_field(scene, plan, stats, ff_kwargs)
    if stats.far_field is not None:        # resumed: the certificate's sums so far (its draws: the design's seed)
        producer.certificate.q = np.array(stats.far_field.q, np.float64)
    stats.far_field = producer.certificate
    return producer


def far_field_report(stats: FarFieldStats, certificate: FarFieldCertificate, holdout: FarFieldCertificate | None,
                     n: int) -> dict:
    """What the sampled far field did, and its certified error, for ``info["far_field"]``."""
    estimate, upper = certificate.frobenius()
    out = {**stats.as_dict(n), "certificate_rows": int(certificate.index.size),
           "error_estimate": estimate, "error_upper": upper}
    if holdout is not None:
        out["holdout_rows"] = int(holdout.index.size)
        out["holdout_estimate"] = holdout.frobenius()[0]
    return out


def _far_field_report(producer: SampledFarField) -> dict:
    return far_field_report(producer.stats, producer.certificate, producer.holdout, producer.n)


def _open_stats(stream: HFStream, n: int, weights, reflectance) -> PassStatistics:
    """The pass statistics, resumed from the stream's checkpointed extras when it was resumed."""
    if stream.blocks_done == 0:
        return PassStatistics(n, weights, reflectance=reflectance)
    state = {k[len(_STATS):]: v for k, v in stream.extra.items() if k.startswith(_STATS)}
    if not state:
        raise InputError("the checkpoint comes from an older hfrad (no pass statistics); delete it to start over")
    return PassStatistics.from_state(state)


def _open_stream(path, key: str, plan: PrecomputePlan) -> HFStream:
    if path is not None and Path(path).exists():
        return load_checkpoint(path, key)
    return HFStream(plan.n, plan.n_blocks, eps=plan.eps, relative=plan.relative, dtype=np.dtype(plan.dtype),
                    leaf_share=plan.leaf_share)


def _every_blas_thread_for_a_large_merge(blocks_done: int, n_blocks: int):
    """Every BLAS thread for the push of block ``blocks_done`` when it merges a quarter of the blocks or more.

    Such a merge (binary counter: the push of the c-th block forms a node of
    ``c & -c`` blocks) costs O(n k^2) flops at rank k, the most of the run, and
    the form-factor workers, which are at most a few blocks ahead, stop soon
    after its start; a single BLAS thread would leave the other cores idle for
    the rest of it.
    """
    c = blocks_done + 1
    if (c & -c) < max(_LARGE_MERGE_SHARE * n_blocks, 4):
        return contextlib.nullcontext()
    return blas_threads(cores())   # the cores this process may use


def _stream_blocks(blocks, stream: HFStream, stats: PassStatistics, rows_rho, checkpoint: Checkpoint | None,
                   key, progress, status, t0, split=None):
    """Push every column block into the stream and the statistics (checkpointing both).

    Returns the wall seconds of each part of the loop (``time_formfactors``: waiting for the next
    block; ``time_statistics``: the pass statistics and the near-field split of each block;
    ``time_hf``: HF's pushes; ``time_checkpoints``), which add up to the loop's time
    (``stream.finish()`` is the caller's). With a near-field ``split``, each
    block's near entries are moved out before HF sees it, and the error budget
    stays relative to the block's full norm.
    """
    n_blocks = stream.n_blocks
    last_save, save_seconds = time.perf_counter(), 0.0
    resumed = stream.blocks_done      # blocks the checkpoint held (said with the first status)
    time_ff = time_ckpt = time_stats = time_hf = 0.0
    G = None    # G's buffer, reused block after block (HF keeps nothing of it)
    t_ff = time.perf_counter()
    for start, stop, block, *exact in blocks:    # the sampled far field adds the exact sampled rows
        t = time.perf_counter()
        time_ff += t - t_ff
        # G = diag(rho_max) F (rows in internal order), less the near field; the budget's norm is G's before the split
        G, norm2, block_norm2 = far_block(stats, start, stop, block, rows_rho, split, out=G,
                                          exact_rows=exact[0] if exact else None)
        del block
        t_push = time.perf_counter()
        time_stats += t_push - t
        with _every_blas_thread_for_a_large_merge(stream.blocks_done, n_blocks):
            stream.push(G, norm2=norm2, block_norm2=block_norm2)
        time_hf += time.perf_counter() - t_push
        report(progress, stream.blocks_done, n_blocks)
        if status is not None:
            info = {"blocks": stream.blocks_done, "rank": stream.current_rank, "elapsed": time.perf_counter() - t0}
            if resumed:
                info["resumed"], resumed = resumed, 0
            status(info)
        if checkpoint is not None:
            due = checkpoint.interval and max(checkpoint.interval, CHECKPOINT_COST_RATIO * save_seconds)
            if time.perf_counter() - last_save > due and stream.blocks_done < n_blocks:
                t_save = time.perf_counter()
                stream.extra = {**({} if split is None else split.state()),
                                **{_STATS + k: np.asarray(v) for k, v in stats.state().items()}}
                save_checkpoint(stream, checkpoint.path, key)
                last_save = time.perf_counter()
                save_seconds = last_save - t_save
                time_ckpt += save_seconds
        t_ff = time.perf_counter()
    time_ff += time.perf_counter() - t_ff   # the generator's end (the engine closing)
    return {"time_formfactors": time_ff, "time_statistics": time_stats, "time_hf": time_hf,
            "time_checkpoints": time_ckpt}
