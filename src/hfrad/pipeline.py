"""The precomputation: scene -> Z-order -> form-factor column blocks -> HF -> Woodbury.

``factorize(scene)`` is what ``hfrad precompute`` runs. Column blocks of
``G = diag(rho_max) F`` are generated one at a time in Z-order, pushed into a
:class:`~hfrad.lowrank.streaming.HFStream` and dropped, so the n x n matrix
never exists. With ``checkpoint=PATH`` the stream state is saved every
``checkpoint_interval`` seconds and a rerun resumes after the last saved block.
"""

from __future__ import annotations

import contextlib
import math
import time
from pathlib import Path
from typing import Callable

import numpy as np

from .defaults import DEFAULT_BLOCK_SIZE
from .errors import InputError
from .lowrank.api import check_method, lowrank_from_blocks, lowrank_from_matrix
from .lowrank.hf import HFStream
from .lowrank.nearfield import DEFAULT_NEAR_ENTRIES, NearFieldSplit
from .lowrank.streaming import load_checkpoint, save_checkpoint
from .formfactors.parallel import default_workers
from .memory import precompute_bytes
from .progress import ProgressCallback, report
from .scene.scene import Scene
from .solve.assemble import PrecomputeOptions, assemble, far_block, precompute_options
from .solve.stats import PassStatistics
from .solve.woodbury import HFactorization
from .validation import check_areas, check_form_factors, check_permutation, check_reflectance

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
#: Prefix of the pass statistics among a checkpoint's extra arrays.
_STATS = "stats_"
#: A checkpoint is written at most once per this many times its last write took, so that
#: writing them costs at most ~2% (1/50) of the run: the state grows with the near field (24
#: bytes an entry, 24 n c bytes for c entries a row) and with the rank (O(n k)), so a fixed
#: interval would spend a growing share of a large run writing.
CHECKPOINT_COST_RATIO = 50.0

StatusCallback = Callable[[dict], None] | None


def factorize(scene: Scene, *, eps: float = 0.02, relative: bool = True,
              block_size: int | None = None, dtype="float32", order=None,
              samples: int | None = None, leaf_share: float = 0.5,
              checkpoint: str | Path | None = None, checkpoint_interval: float = 30.0,
              keep_checkpoint: bool = False,
              blas_threads: int | None = 1, processes: int | None = 1, one_ray_tol: float | None = None,
              near_field: int | str | None = "auto", reciprocity: bool = True,
              progress: ProgressCallback = None, status: StatusCallback = None, scheduler=None,
              workers: int | None = None, task_threads: int | None = None, connect_timeout: float | None = None,
              records: list | None = None) -> HFactorization:
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
    block_size : int, optional
        Column block width; default ``min(DEFAULT_BLOCK_SIZE, n)`` (256).
    dtype : {"float32", "float64"}
        Precision of the factors.
    order : {"zorder", "hilbert", "random", "input"} or (n,) int, optional
        Internal patch order (internal index t holds user patch order[t]);
        default Z-order (the paper's). Only speed and rank depend on it:
        every input and output stays in the user's order.
    samples : int, optional
        Visibility rays per patch pair (default: the engine's).
    leaf_share : float in (0, 1]
        Share of the squared error budget given to the leaf SVDs.
    checkpoint : path, optional
        Save the stream state here while running and resume
        from it if it exists; deleted when the factorization completes
        (see ``keep_checkpoint``). A damaged checkpoint, or one made for
        another input, is refused (FileFormatError / InputError), never resumed.
    checkpoint_interval : float, seconds
        At least this long between checkpoints, and at least
        :data:`CHECKPOINT_COST_RATIO` times the last write's duration
        (0: after every block, whatever it costs).
    keep_checkpoint : bool
        In this process: leave the checkpoint in place when the
        factorization completes, for a caller that deletes it only once the
        result is safely saved (``hfrad precompute`` removes it after the
        ``.hfr`` file is renamed into place, so a crash while saving loses nothing).
    blas_threads : int or None
        BLAS threads while the form-factor engine runs (None:
        leave as is). One is fastest while the engine uses the other cores.
    processes : int or None
        Form-factor worker processes (None: one per core from
        4,000 patches on); the result does not depend on it. Default 1 (this
        process: numba threads plus one Embree thread) so that scripts need no
        ``if __name__ == "__main__":`` guard (workers are spawned); the CLI
        defaults to None. Workers pay off when they get cores of their own;
        on a loaded machine they compete with the other processes.
    one_ray_tol : float or None
        Pairs that together hold at most this share of ``||F||_F``
        get one visibility ray instead of several, and flagged pairs (probes
        disagree) holding ``FEW_RAYS_FACTOR`` (4) times this share get 4 rays
        instead of 16 (:func:`hfrad.formfactors.budget.ray_budget`); None:
        ``eps / 4`` for a relative eps, 0 (both rules off) for an absolute one.
    near_field : "auto", int or None
        The near-field split (docs/method.md; :mod:`hfrad.lowrank.nearfield`):
        pairs within a radius holding about this many neighbours per row go into
        a sparse N, HF factors only ``G - N``, and the solver is Woodbury around a
        sparse LU of ``I - D_c N`` (:class:`~hfrad.solve.nearfield.NearFieldFactorization`).
        "auto" (default): ``DEFAULT_NEAR_ENTRIES`` (120) facing neighbours per row where
        the split pays, off below (:func:`near_field_pays_from`: from 20,000 patches at
        eps 0.02, ``20,000 (0.02 / eps)^1.5`` patches at other relative eps (5,060 at 0.05), never below
        2,000); None or 0: off (plain Woodbury). The split lowers the rank HF needs (the near pairs hold F's
        high-rank part) and, at equal eps, the radiosity error; it costs a sparse LU
        of ``I - D_c N`` (about 12 bytes per entry, ``n * near_field`` entries).
    reciprocity : bool
        A column block copies its pairs with the columns of earlier blocks,
        ``F_ij = A_j F_ji / A_i``, instead of computing them again
        (:mod:`hfrad.formfactors.mirror`; about half the form-factor work, F equal
        to rounding; its tiles take at most a quarter of the available memory).
        False computes every pair, as the Dask backend does (its blocks bit for bit).
    progress : callable (done, total), optional
        Column blocks done.
    status : callable (dict), optional
        Called after each block with ``blocks``, ``rank``, ``elapsed`` (seconds);
        in this process, the first call after resuming from ``checkpoint`` also
        has ``resumed``: the blocks the checkpoint held.
    scheduler : str, distributed.Client or hfrad.distributed.Cluster, optional
        Run the column blocks, leaves and merges as Dask tasks on this
        cluster (docs/cluster.md) instead of in this process. Same options, same
        class, same ``.hfr`` contents and error figures (only ``params["backend"]``,
        ``params["workers"]`` and the timings differ); ``reciprocity`` is not used
        there (every pair is computed), and ``checkpoint`` names a folder of the
        finished subtrees' factors, so a rerun skips them.
    workers : int, optional
        Instead of ``scheduler``: a LocalCluster of this many worker processes.
    task_threads, connect_timeout, records
        Dask only: see :func:`hfrad.distributed.factorize_distributed`.

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
    Memory, b = block_size, k = rank, s = the dtype's itemsize: about
    ``24 n b + (2 n k + 3 k^2) s + 4 n k s`` bytes (three float64 column
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
    """
    if not isinstance(scene, Scene):
        if isinstance(scene, (str, Path)):
            raise InputError(f"factorize takes a Scene; load the file first: hfrad.load_scene({str(scene)!r})")
        raise InputError(f"factorize takes a Scene, not {type(scene).__name__}; for a form-factor "
                         "matrix use hfrad.factorize_matrix(F, reflectance)")
    options = precompute_options(scene, eps=eps, relative=relative, block_size=block_size,
                                 dtype=dtype, samples=samples, order="zorder" if order is None else order,
                                 leaf_share=leaf_share, one_ray_tol=one_ray_tol,
                                 near_entries=near_entries(near_field, scene.n_patches, eps, relative),
                                 reciprocity=reciprocity)
    if scheduler is not None or workers is not None:
        if processes not in (None, 1):
            raise InputError("processes is for the in-process path; on Dask the workers compute the blocks")
        from .distributed import factorize_distributed, remove_checkpoint

        fac = factorize_distributed(scene, options, scheduler=scheduler, workers=workers,
                                    task_threads=task_threads, connect_timeout=connect_timeout,
                                    checkpoint=checkpoint, progress=progress, status=status, records=records)
        if checkpoint is not None and not keep_checkpoint:
            remove_checkpoint(checkpoint)
        return fac
    return _factorize_scene(scene, options, checkpoint=checkpoint,
                            checkpoint_interval=checkpoint_interval, keep_checkpoint=keep_checkpoint,
                            blas_threads=blas_threads,
                            processes=processes, progress=progress, status=status)


def factorize_matrix(F, reflectance, *, areas=None, eps: float = 0.02, relative: bool = True,
                     block_size: int | None = None, dtype="float32", order=None, method: str = "hf",
                     leaf_share: float = 0.5, rng=None, progress: ProgressCallback = None) -> HFactorization:
    """Factor the radiosity system of a form-factor matrix you already have.

    The same factorization and solver object as :func:`factorize`, from a
    dense F instead of a scene (no visibility rays, no near-field split), and
    the only entry to the dense baselines.

    Parameters
    ----------
    F : (n, n) float array
        Form factors in the user's patch order: ``F[i, j]`` is the fraction
        of the energy leaving patch i that reaches patch j (>= 0, rows
        summing to at most 1).
    reflectance : (n, 3) float in [0, 1)
        Diffuse reflectance per patch and colour channel (or (n,) grey).
    areas : (n,) float > 0, m^2, optional
        Patch areas: the error figures are then in the area-weighted norm,
        where reciprocity gives the tight contraction bound; without them
        the plain 2-norm.
    eps : float in (0, 1)
        Target ``||G - Q V^T||_F`` relative to ``||G||_F`` (absolute with
        ``relative=False``), ``G = diag(rho_max) F``.
    block_size : int, optional
        Column block width; default ``DEFAULT_BLOCK_SIZE`` (256).
    dtype : {"float32", "float64"}
        Precision of the factors.
    order : "input" or (n,) int, optional
        Internal patch order (internal index t holds user patch order[t]);
        default the input order. Only speed and rank depend on it.
    method : {"hf", "svd", "rsvd", "sketch"}
        HF (the paper's) or a baseline on the dense matrix: truncated SVD
        (LAPACK), randomized SVD (scikit-learn), or a one-pass sketch.
    leaf_share : float in (0, 1]
        HF: share of the squared error budget given to the leaf SVDs.
    rng : None, int or numpy Generator
        Seed of the randomized baselines ("rsvd", "sketch").
    progress : callable (done, total), optional
        Column blocks done.

    Returns
    -------
    HFactorization

    Raises
    ------
    InputError (a ValueError)
        Bad shapes or values (negative entries, rows summing above 1.05,
        NaN), or options; the message names the argument.

    Notes
    -----
    Memory: F itself (n^2 float64 words) plus the factors (O(nk)).

    Examples
    --------
    >>> import numpy as np, hfrad
    >>> F = np.full((40, 40), 1 / 40)                 # a closed, uniform enclosure
    >>> fac = hfrad.factorize_matrix(F, np.full((40, 3), 0.5), eps=1e-3)
    >>> bool(np.allclose(fac.solve(np.ones(40)), 2.0))   # B = E / (1 - rho)
    True
    """
    if isinstance(F, Scene):
        raise InputError("factorize_matrix takes a form-factor matrix; for a Scene use hfrad.factorize(scene)")
    return _factorize_matrix(F, reflectance, eps=eps, relative=relative,
                             block_size=DEFAULT_BLOCK_SIZE if block_size is None else block_size, dtype=dtype,
                             order=order, method=method, leaf_share=leaf_share, rng=rng, areas=areas,
                             progress=progress)


def _factorize_scene(scene: Scene, options: PrecomputeOptions, *, checkpoint, checkpoint_interval: float,
                     keep_checkpoint: bool = False, blas_threads, processes, progress: ProgressCallback,
                     status: StatusCallback) -> HFactorization:
    """The body of :func:`factorize` in this process (arguments as there): streamed form factors into HF."""
    from .formfactors.blocks import iter_column_blocks

    n, block_size, dt = options.n, options.block_size, np.dtype(options.dtype)
    perm, n_blocks = options.perm, options.n_blocks
    key = options.key(scene)
    stream = _open_stream(checkpoint, key, n, n_blocks, options.eps, options.relative, dt, options.leaf_share)
    stats = _open_stats(stream, n, options.stats_weights(scene), scene.reflectance[perm])
    t0 = time.perf_counter()
    ff_kwargs = {} if options.samples is None else {"samples": options.samples}
    if options.samples != 0:
        ff_kwargs["ray_budget"] = options.ray_budget(scene)
    mirror_stats: dict = {}   # what the reciprocity copy did (pairs copied, scratch I/O), kept in info
    # the reciprocity tiles leave free what the rest of the run is estimated to need; those beyond
    # the memory band spill to a scratch file beside the output (its checkpoint), else in TMPDIR;
    # blocks are lent (no copy): _stream_blocks is done with each before it asks for the next
    blocks = iter_column_blocks(scene, block_size, order=perm, first_block=stream.blocks_done,
                                processes=processes, dtype=dt, reciprocity=options.reciprocity,
                                reserved_bytes=precompute_bytes(n, block_size, itemsize=dt.itemsize),
                                scratch=None if checkpoint is None else Path(checkpoint).parent,
                                mirror_stats=mirror_stats, lend=True, **ff_kwargs)
    rows_rho = options.rows_rho(scene)
    split = None
    if options.near_entries:
        split = NearFieldSplit(scene.centroids[perm], options.near_radius)
        if stream.blocks_done:
            split.restore(stream.extra)
    with _blas_threads(blas_threads):
        time_ff, time_ckpt = _stream_blocks(blocks, stream, stats, rows_rho, n_blocks, checkpoint,
                                            checkpoint_interval, key, progress, status, t0, split)
    # the last merges (the largest: up to the root) once the form-factor engine has stopped,
    # with every BLAS thread
    lowrank = stream.finish()
    lowrank.info.update({"time_formfactors": time_ff, "time_checkpoints": time_ckpt,
                         "time_precompute": time.perf_counter() - t0})
    if mirror_stats:
        lowrank.info["reciprocity"] = mirror_stats
    fac = assemble(scene, options, lowrank, stats, None if split is None else split.state(),
                   backend={"backend": "local"})
    if checkpoint is not None and not keep_checkpoint:
        Path(checkpoint).unlink(missing_ok=True)
    return fac


def _open_stats(stream: HFStream, n: int, weights, reflectance) -> PassStatistics:
    """The pass statistics, resumed from the stream's checkpointed extras when it was resumed."""
    if stream.blocks_done == 0:
        return PassStatistics(n, weights, reflectance=reflectance)
    state = {k[len(_STATS):]: v for k, v in stream.extra.items() if k.startswith(_STATS)}
    if not state:
        raise InputError("the checkpoint comes from an older hfrad (no pass statistics); delete it to start over")
    return PassStatistics.from_state(state)


def near_field_pays_from(eps: float, relative: bool = True) -> int:
    """Patches from which ``near_field="auto"`` splits the near field, at this ``eps``.

    An absolute eps says nothing of the rank before ``||G||_F`` is known: the split
    then starts at ``NEAR_FIELD_MIN_PATCHES``.
    """
    if not relative or not eps > 0:
        return NEAR_FIELD_MIN_PATCHES
    scaled = NEAR_FIELD_PAYS_FROM * (NEAR_FIELD_REFERENCE_EPS / eps) ** NEAR_FIELD_EPS_POWER
    return max(NEAR_FIELD_MIN_PATCHES, int(math.ceil(scaled)))


def near_entries(near_field, n: int, eps: float = NEAR_FIELD_REFERENCE_EPS, relative: bool = True) -> int:
    """Neighbours per row of the near field for ``factorize(near_field=...)`` (0 = no split).

    "auto": ``DEFAULT_NEAR_ENTRIES`` where the split pays (from
    :func:`near_field_pays_from` patches on at this ``eps``), else 0.
    """
    if near_field == "auto":
        return DEFAULT_NEAR_ENTRIES if n >= near_field_pays_from(eps, relative) else 0
    if near_field is None or near_field is False:
        return 0
    if isinstance(near_field, str) or int(near_field) != near_field or near_field < 0:
        raise InputError(f"near_field must be 'auto', None or a number of neighbours per row (e.g. 64); "
                         f"got {near_field!r}")
    return int(near_field)


def _open_stream(checkpoint, key, n, n_blocks, eps, relative, dt, leaf_share) -> HFStream:
    if checkpoint is not None and Path(checkpoint).exists():
        return load_checkpoint(checkpoint, key)
    return HFStream(n, n_blocks, eps=eps, relative=relative, dtype=dt, leaf_share=leaf_share)


@contextlib.contextmanager
def _blas_threads(count: int | None):
    """Limit BLAS/LAPACK threads while the form-factor engine runs beside the factorization.

    The engine keeps the cores busy (numba kernel + Embree); multi-threaded
    OpenBLAS competing with it spin-waits and slows the small SVDs by an order of magnitude.
    """
    if count is None:
        yield
        return
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=count, user_api="blas"):
        yield


#: A push whose merges form a node of at least this share of all column blocks gets every BLAS thread.
_LARGE_MERGE_SHARE = 0.25


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
    return _blas_threads(default_workers())   # the cores this process may use


def _stream_blocks(blocks, stream: HFStream, stats: PassStatistics, rows_rho, n_blocks, checkpoint,
                   checkpoint_interval, key, progress, status, t0, split=None):
    """Push every column block into the stream and the statistics (checkpointing both).

    Returns the form-factor seconds and the checkpoint-writing seconds (``stream.finish()`` is the caller's). With a near-field ``split``, each
    block's near entries are moved out before HF sees it, and the error budget
    stays relative to the block's full norm.
    """
    last_save, save_seconds = time.perf_counter(), 0.0
    resumed = stream.blocks_done      # blocks the checkpoint held (said with the first status)
    time_ff = time_ckpt = 0.0
    G = None    # G's buffer, reused block after block (HF keeps nothing of it)
    t_ff = time.perf_counter()
    for start, stop, block in blocks:
        time_ff += time.perf_counter() - t_ff
        # G = diag(rho_max) F (rows in internal order), less the near field; the budget's norm is G's before the split
        G, norm2, block_norm2 = far_block(stats, start, stop, block, rows_rho, split, out=G)
        del block
        with _every_blas_thread_for_a_large_merge(stream.blocks_done, n_blocks):
            stream.push(G, norm2=norm2, block_norm2=block_norm2)
        report(progress, stream.blocks_done, n_blocks)
        if status is not None:
            info = {"blocks": stream.blocks_done, "rank": stream.current_rank, "elapsed": time.perf_counter() - t0}
            if resumed:
                info["resumed"], resumed = resumed, 0
            status(info)
        due = checkpoint_interval and max(checkpoint_interval, CHECKPOINT_COST_RATIO * save_seconds)
        if checkpoint is not None and time.perf_counter() - last_save > due and stream.blocks_done < n_blocks:
            t_save = time.perf_counter()
            stream.extra = {**({} if split is None else split.state()),
                            **{_STATS + k: np.asarray(v) for k, v in stats.state().items()}}
            save_checkpoint(stream, checkpoint, key)
            last_save = time.perf_counter()
            save_seconds = last_save - t_save
            time_ckpt += save_seconds
        t_ff = time.perf_counter()
    return time_ff, time_ckpt


def _factorize_matrix(F, reflectance, *, eps: float, relative: bool, block_size: int, dtype, order,
                      method: str, leaf_share: float, rng, areas, progress: ProgressCallback) -> HFactorization:
    """The body of :func:`factorize_matrix` (arguments as there): validation, then the factorizer."""
    F = check_form_factors(F)  # real, square, finite, >= 0
    if F.ndim != 2 or F.shape[0] != F.shape[1]:
        raise InputError(f"form factors must be a square (n, n) matrix; got {F.shape}")
    n = F.shape[0]
    rho = check_reflectance(reflectance, n)
    if isinstance(order, str):
        if order != "input":
            raise InputError(f"order {order!r} needs patch positions: pass a Scene, or an (n,) permutation "
                             "with a matrix")
        order = None
    perm = check_permutation(order, n)
    check_method(method)
    dt = np.dtype(dtype)
    if dt not in (np.float32, np.float64):
        raise InputError(f"dtype must be float32 or float64; got {dt}")
    if not (0.0 < eps < 1.0 if relative else eps > 0.0 and math.isfinite(eps)):
        raise InputError(f"eps must be in (0, 1) (relative) or > 0 (absolute); got {eps}")
    if block_size < 1:
        raise InputError(f"block_size must be >= 1; got {block_size}")
    rho_max = rho.max(axis=1)
    if not np.isfinite(F).all():
        i, j = np.argwhere(~np.isfinite(F))[0]
        raise InputError(f"form factors have a NaN or infinite value at F[{i}, {j}]")
    lr = lowrank_from_matrix(F, rho_max, perm, eps=eps, relative=relative, block_size=block_size, dtype=dt,
                             method=method, rng=rng, leaf_share=leaf_share, progress=progress)
    stats = PassStatistics(n, None if areas is None else check_areas(areas, n)[perm], reflectance=rho[perm])
    stats.add(0, n, F[np.ix_(perm, perm)], rho_max[perm][:, None])
    params = {"method": method, "block_size": block_size, "dtype": dt.name,
              "time_factor": lr.info["time_factor"]}
    if method == "hf":
        params["leaf_share"] = leaf_share
    return HFactorization(perm, lr.Q, lr.V, rho_max, rho, lr, params=params, stats=stats)


def factorize_blocks(blocks, n: int, reflectance, perm, *, eps: float = 0.02, relative: bool = True,
                     dtype=np.float32, n_blocks: int | None = None, leaf_share: float = 0.5,
                     block_size: int | None = None, progress: ProgressCallback = None) -> HFactorization:
    """Out-of-core HF: one pass over column blocks of F in internal order.

    Parameters
    ----------
    blocks : iterable of (start, stop, Fblock)
        ``Fblock = F[perm][:, perm[start:stop]]`` (n x b), rows already in
        internal order and not yet multiplied by rho_max; consecutive, left to right.
    n : int
    reflectance : (n, 3) float in [0, 1), user order
    perm : (n,) int, internal order
    eps, relative, dtype, leaf_share, progress : see
        :func:`~hfrad.lowrank.hf.hierarchical_factorization`
    n_blocks : int, optional
        Number of blocks (needed for the error budget when ``blocks`` has no len);
        defaults to ``ceil(n / block_size)`` when ``block_size`` is given.

    Returns
    -------
    HFactorization
    """
    rho = check_reflectance(reflectance, n)
    perm = check_permutation(perm, n)
    rho_max = rho.max(axis=1)
    if n_blocks is None and block_size is not None:
        n_blocks = -(-n // block_size) if n else 0
    if n_blocks is None:
        try:
            n_blocks = len(blocks)
        except TypeError:
            raise InputError("pass n_blocks (or block_size) when blocks is a generator") from None
    stats = PassStatistics(n)
    rows_rho = rho_max[perm][:, None]

    def recorded():
        for start, stop, Fb in blocks:
            yield start, stop, Fb
            stats.add(start, stop, Fb, rows_rho)   # after the factorizer has checked the block

    lr = lowrank_from_blocks(recorded(), n, rho_max, perm, eps=eps, relative=relative, dtype=dtype,
                             n_blocks=n_blocks, leaf_share=leaf_share, progress=progress)
    params = {"method": "hf", "block_size": block_size, "dtype": np.dtype(dtype).name,
              "leaf_share": leaf_share, "time_factor": lr.info["time_factor"]}
    return HFactorization(perm, lr.Q, lr.V, rho_max, rho, lr, params=params, stats=stats)
