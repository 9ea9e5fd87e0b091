"""The form-factor matrix F, streamed in column blocks or assembled densely.

F[i, j] is the fraction of the energy leaving patch i that arrives at patch j,
visibility included: F = F_unoccluded (kernel.py, exact polygon integral,
symmetric quadrature) times V (visibility.py, fraction of unoccluded rays).
Both factors are reciprocity-symmetric, so A_i F_ij = A_j F_ji to rounding.

The hierarchical factorization consumes F one column block at a time
(docs/method.md, section 4): :func:`iter_column_blocks` yields them in an internal order
(Z-order), each computed independently of the others, so a run can be
streamed, cached on disk and resumed, or spread over machines.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
import warnings
from dataclasses import dataclass
from typing import Iterator

import numpy as np

from ..defaults import DEFAULT_BLOCK_SIZE
from ..errors import InputError, MemoryLimitError
from ..memory import available_bytes as available_memory
from ..progress import ProgressCallback, report
from ..resources import cores
from ..validation import check_permutation
from .budget import RayBudget
from .cache import BlockCache, array_hash, scene_hash
from .engine import FormFactorEngine
from .kernel import ADAPTIVE, KERNEL_VERSION, NEAR, TOLERANCE
from .mirror import (MIRROR_LAG, SCRATCH_SHARE, ReciprocityMirror, TileScratch, band_for, mirror_bytes,
                     band_pairs, scratch_bytes, slot_bytes, spill_band_for)
from .parallel import MIN_PARALLEL_PATCHES, ProcessEngine
from .visibility import CLUSTER_VISIBILITY, DEFAULT_SAMPLES, PAIR_TEST, check_samples

__all__ = ["FormFactorEngine", "iter_column_blocks", "Consumer", "form_factor_matrix", "row_sums",
           "available_memory", "DEFAULT_BLOCK_SIZE"]

_MEMORY_FRACTION = 0.5

def _check_common(scene, samples, block_size) -> None:
    if samples != 0:
        check_samples(samples)
    if block_size is not None and (int(block_size) != block_size or block_size < 1):
        raise InputError(f"block_size must be a positive integer, got {block_size}")
    if scene.n_patches and not (scene.areas > 0).all():
        bad = int(np.flatnonzero(~(scene.areas > 0))[0])
        raise InputError(f"{scene.name}: patch {bad} has zero area; "
                         "remove degenerate patches first (hfrad.scene.patches.drop_degenerate)")


def cache_key(scene, *, samples: int, block_size: int, order: np.ndarray, dtype,
              ray_budget: RayBudget | None = None) -> dict:
    """What a cached block depends on (see :mod:`hfrad.formfactors.cache`)."""
    extra = ray_budget.key() if ray_budget is not None else {}
    if CLUSTER_VISIBILITY:  # the same F to Embree's rounding, but not bit for bit
        extra = extra | {"cluster_visibility": int(CLUSTER_VISIBILITY), "pair_test": bool(PAIR_TEST)}
    return extra | {"scene_sha256": scene_hash(scene), "samples": int(samples), "block_size": int(block_size),
            "order_sha256": array_hash(order.astype(np.int64)), "dtype": np.dtype(dtype).str,
            "kernel_version": KERNEL_VERSION, "near": NEAR, "adaptive": ADAPTIVE, "tolerance": TOLERANCE,
            "n": int(scene.n_patches)}


def iter_column_blocks(scene, block_size: int = DEFAULT_BLOCK_SIZE, *, order=None,
                       samples: int = DEFAULT_SAMPLES, dtype=np.float64,
                       progress: ProgressCallback = None, cache=None,
                       engine: FormFactorEngine | None = None,
                       first_block: int = 0, processes: int | None = 1,
                       ray_budget: RayBudget | None = None,
                       reciprocity: bool = True, scratch=None,
                       mirror_stats: dict | None = None,
                       consumer: "Consumer | None" = None) -> Iterator[tuple[int, int, np.ndarray]]:
    """Stream F in column blocks, rows and columns in the internal ``order``.

    Yields ``(start, stop, block)`` with

        block = F[np.ix_(order, order[start:stop])]      (n x (stop - start))

    for start = 0, block_size, 2 block_size, ... Each block is computed
    independently of the others (any subset can be computed anywhere).

    Parameters
    ----------
    scene : Scene
    block_size : int
        Columns per block.
    order : (n,) int permutation, optional
        Internal patch order (e.g. ``zorder_permutation(scene.centroids)``); identity by default.
    samples : int
        Visibility rays per pair (perfect square; 1 = centroid to centroid; 0 = no visibility).
    dtype : numpy dtype
        Of the yielded blocks (computed in float64, then cast).
    progress : callable (done, total), optional
        Called after each block with the number of columns done.
    cache : str, Path or BlockCache, optional
        HDF5 file to read finished blocks from and write new ones to, so an
        interrupted run resumes (see :mod:`hfrad.formfactors.cache`).
    engine : FormFactorEngine, optional
        Reuse per-scene state (and read its timing counters).
    first_block : int
        Start at this block (resuming an interrupted pass); earlier blocks are not computed.
    processes : int or None
        Processes computing blocks (:class:`~hfrad.formfactors.parallel.ProcessEngine`);
        1 = this process (numba threads + one Embree thread); None = one per core
        when the scene has at least ``MIN_PARALLEL_PATCHES`` patches. The blocks
        are the same whatever the count.
    ray_budget : RayBudget, optional
        Fewer rays for weak pairs (see :func:`hfrad.formfactors.budget.ray_budget`); default: off.
    reciprocity : bool
        Take the rows of earlier blocks by reciprocity, ``F_ij = A_j F_ji / A_i``
        (:mod:`hfrad.formfactors.mirror`): about half of the pairs are then copies.
        Holds n^2/4 entries of ``dtype`` at most, and at most ``MIRROR_SHARE`` of the
        available memory (:func:`~hfrad.formfactors.mirror.mirror_bytes`): with less, each
        block copies from fewer earlier blocks.
    scratch : str, Path or False, optional
        Folder of the scratch file that takes the reciprocity tiles the memory band
        cannot hold (:class:`~hfrad.formfactors.mirror.TileScratch`), so every pair is
        computed once; default TMPDIR (``tempfile.gettempdir()``); False: no file,
        the blocks beyond the memory band compute those rows. The file needs at most
        about ``n^2 s / 4`` bytes (the peak of the tiles waiting on disk,
        :func:`~hfrad.formfactors.mirror.scratch_bytes`) and takes at most
        ``SCRATCH_SHARE`` of the folder's free space: with less, the copies cover a
        share of the pairs (a ``RuntimeWarning`` says which). It exists only while
        the pass runs (unlinked at once: nothing is left after an error or Ctrl-C).
    mirror_stats : dict, optional
        Filled when the pass ends: ``band``, ``near`` (blocks copied from, in memory),
        ``copied_pairs``, ``possible_pairs``, ``spilled_pairs``, ``scratch_bytes``,
        ``scratch_written``, ``scratch_seconds`` (this thread: copies, reads, checks),
        ``scratch_write_seconds`` (the writer thread), ``repaired_tiles``.
    consumer : Consumer, optional
        What a caller that streams the blocks into a factorization tells the pass
        (:class:`Consumer`: the memory it needs beside it, whether it may be lent the
        blocks); default: nothing reserved, every block an array of its own.

    Raises
    ------
    ValueError
        Bad ``order``, ``samples`` or ``block_size``; zero-area patches.
    WriteError
        ``scratch`` is missing or not writable, or its disk filled up before the file was reserved.
    CacheMismatchError
        ``cache`` is a complete cache for another scene or other parameters.

    Notes
    -----
    Cost: O(n b) kernel pairs and at most ``samples`` rays per pair per block
    (about half of them with ``reciprocity``); memory O(n b) plus the ray batch, and the
    mirror's tiles.
    """
    n = scene.n_patches
    _check_common(scene, samples, block_size)
    order = check_permutation(order, n)
    dtype = np.dtype(dtype)
    consumer = Consumer() if consumer is None else consumer
    store = _open_store(cache, scene, samples, block_size, order, dtype, ray_budget, n)
    starts = list(range(0, n, block_size))[first_block:]
    # Only flags are read up front: a cached block is read when its turn comes,
    # so a cache of an out-of-core matrix is streamed, not loaded.
    todo = [k for k in range(first_block, first_block + len(starts)) if store is None or not store.has(k)]
    repair = {}

    def recompute(rows: slice, cols: slice) -> np.ndarray:
        # a scratch tile failed its checksum: compute its rows of the block here (rare). A fresh
        # in-process engine: the pass's engine may be casting the next blocks' rays right now.
        if "engine" not in repair:
            repair["engine"] = FormFactorEngine(scene, samples=samples, ray_budget=ray_budget)
        return repair["engine"].block(order[rows], order[cols])

    # the scratch folder is checked (and its file reserved) before any work starts
    copies = None
    if reciprocity and todo:
        with _closing_on_error(store):
            copies = _mirror_for(scene, order, block_size, first_block, dtype, consumer.reserved_bytes, scratch,
                                 recompute)
    own_engine = engine is None
    if todo and engine is None:
        with _closing_on_error(copies):
            engine = make_engine(scene, samples=samples, processes=processes, ray_budget=ray_budget,
                                 block_size=block_size, dtype=dtype)
    skips: dict[int, slice] = {}

    def request(k: int):
        cols = order[k * block_size:(k + 1) * block_size]
        if copies is None:
            return cols
        skips[k] = copies.copied_rows(k)          # decided when the block is handed out
        return cols, skips[k]

    computed = engine.iter_blocks(order, (request(k) for k in todo), lend=consumer.lend) if todo else _empty()
    try:
        for index, start in enumerate(starts, first_block):
            stop = min(n, start + block_size)
            block = store.get(index, start, stop) if store is not None else None
            if block is not None and copies is not None:
                copies.discard(index)                  # read, not computed: its tiles are not needed
            if block is None:
                block = _computed_block(computed, dtype, copies, index, skips)
                if store is not None:
                    store.put(index, start, stop, block)
            if copies is not None:
                copies.keep(index, block)
            report(progress, stop, n)
            yield start, stop, block
            del block
        if store is not None:
            store.finish()
            store = None
    finally:
        computed.close()
        if store is not None:
            store.close()
        if copies is not None:
            if mirror_stats is not None:
                mirror_stats.update(_mirror_report(copies))
            copies.close()
        if "engine" in repair:
            repair["engine"].close()
        if own_engine and engine is not None:
            engine.close()


@dataclass(frozen=True)
class Consumer:
    """What a caller streaming the column blocks into a factorization tells :func:`iter_column_blocks`.

    Attributes
    ----------
    reserved_bytes : int
        Memory the caller needs beside this pass (its estimate): the mirror's tiles
        leave it free.
    lend : bool
        Blocks computed by worker processes come in one array reused for the whole
        pass, valid only until the next block is asked for (no fresh n x b pages per
        block); for a caller that is done with each block before the next. Default
        False: every block is an array of its own.
    """

    reserved_bytes: int = 0
    lend: bool = False


def _open_store(cache, scene, samples, block_size, order, dtype, ray_budget, n) -> BlockCache | None:
    """The pass's block cache, opened for this scene and these parameters (None without ``cache``)."""
    if cache is None:
        return None
    store = cache if isinstance(cache, BlockCache) else BlockCache(cache)
    store.open(cache_key(scene, samples=samples, block_size=block_size, order=order, dtype=dtype,
                         ray_budget=ray_budget),
               n, block_size, dtype)
    return store


@contextlib.contextmanager
def _closing_on_error(resource):
    """Close ``resource`` (if any) when the body raises, and re-raise."""
    try:
        yield
    except BaseException:
        if resource is not None:
            resource.close()
        raise


def _computed_block(computed, dtype, copies, index: int, skips: dict) -> np.ndarray:
    """The engine's next block in ``dtype``, its copied rows filled in by the mirror."""
    with np.errstate(over="ignore", invalid="ignore"):
        # the rows the mirror fills next are unspecified (np.empty) until then: their
        # garbage must not warn "overflow encountered in cast"
        block = next(computed).astype(dtype, copy=False)
    if copies is not None:
        copies.fill(index, block, skips.pop(index))
    return block


def _mirror_for(scene, order: np.ndarray, block_size: int, first_block: int, dtype,
                reserved: int, scratch=None, recompute=None) -> ReciprocityMirror:
    """The reciprocity mirror of a pass: its memory band sized by :func:`~hfrad.formfactors.mirror.mirror_bytes`,
    the rest of the blocks spilled to a scratch file in ``scratch`` (default TMPDIR) as far as its disk allows."""
    from ..atomic import free_bytes
    from ..errors import InputError, WriteError
    from ..memory import human

    n = scene.n_patches
    starts = np.r_[np.arange(0, n, block_size), n]
    blocks = len(starts) - 1
    itemsize = np.dtype(dtype).itemsize
    budget = mirror_bytes(n, itemsize, available_memory(), reserved)
    near = band_for(blocks, block_size, itemsize, budget)
    full = max(0, blocks - MIRROR_LAG - 1)
    band, tiles = near, None
    if scratch is not None and scratch is not False and not isinstance(scratch, (str, os.PathLike)):
        raise InputError(f"scratch must be a folder (str or Path), None (TMPDIR) or False (no file); "
                         f"got {type(scratch).__name__}")
    if near < full and scratch is not False:
        folder = tempfile.gettempdir() if scratch is None else os.fspath(scratch)
        if not os.path.isdir(folder):
            raise WriteError(f"scratch folder {folder} does not exist; create it or choose another "
                             "(scratch=, or TMPDIR)")
        free = free_bytes(folder)
        band = spill_band_for(blocks, block_size, itemsize, near, int(SCRATCH_SHARE * free))
        need = scratch_bytes(blocks, block_size, itemsize, near, full)
        if band < full:
            warnings.warn(f"the reciprocity copies need {human(need)} of scratch space in {folder} for every "
                          f"pair, which has {human(free)} free (at most {SCRATCH_SHARE:.0%} of it is used); "
                          f"each block copies from {band} of up to {full} earlier blocks, "
                          f"{band_pairs(starts, band, first_block) / max(1, band_pairs(starts, full, first_block)):.0%} "
                          "of the pairs it could copy. For all of them, "
                          "choose a folder with more room (scratch=, TMPDIR, or the output's folder)",
                          RuntimeWarning, stacklevel=3)
        if band > near:
            slot = slot_bytes(block_size, itemsize)
            slots = scratch_bytes(blocks, block_size, itemsize, near, band) // slot
            tiles = TileScratch(folder, slots, slot)
    try:
        return ReciprocityMirror(np.asarray(scene.areas, np.float64)[order], starts, band=band, first=first_block,
                                 near=near, scratch=tiles, recompute=recompute)
    except BaseException:
        if tiles is not None:
            tiles.close()
        raise


def _mirror_report(m: ReciprocityMirror) -> dict:
    """What the mirror of a pass did (``iter_column_blocks(mirror_stats=...)``)."""
    t = m.scratch
    return {"band": m.band, "near": m.near, "copied_pairs": m.copied_pairs, "possible_pairs": m.possible_pairs(),
            "spilled_pairs": m.spilled_pairs, "repaired_tiles": m.repaired_tiles,
            "scratch_bytes": 0 if t is None else t.slots * t.slot_bytes,
            "scratch_written": 0 if t is None else t.written,
            "scratch_seconds": 0.0 if t is None else t.seconds,
            "scratch_write_seconds": 0.0 if t is None else t.write_seconds}


def make_engine(scene, *, samples: int = DEFAULT_SAMPLES, processes: int | None = 1,
                ray_budget: RayBudget | None = None, block_size: int = DEFAULT_BLOCK_SIZE, dtype=np.float64):
    """A FormFactorEngine (this process), or a ProcessEngine when ``processes`` > 1.

    ``processes=None`` picks one per core for scenes of at least
    ``MIN_PARALLEL_PATCHES`` patches and this process otherwise.
    """
    if processes is None:
        processes = cores() if scene.n_patches >= MIN_PARALLEL_PATCHES else 1
    if int(processes) != processes or int(processes) < 1:
        raise InputError(f"processes must be a positive integer (or None for one per core), got {processes}")
    if int(processes) > 1:
        return ProcessEngine(scene, workers=int(processes), samples=samples, ray_budget=ray_budget,
                             block_size=block_size, dtype=dtype)
    return FormFactorEngine(scene, samples=samples, ray_budget=ray_budget)


def _empty() -> Iterator[np.ndarray]:
    yield from ()


def dense_bytes(n: int, dtype=np.float64, block_size: int = DEFAULT_BLOCK_SIZE) -> int:
    """Estimated peak bytes of :func:`form_factor_matrix`: the matrix, one float64 block, rays."""
    return n * n * np.dtype(dtype).itemsize + 3 * n * block_size * 8 + 28 * (1 << 21)


def check_dense_memory(n: int, dtype=np.float64, max_bytes: int | None = None) -> int:
    """Raise MemoryLimitError if a dense n x n F would exceed ``max_bytes``; returns the estimate."""
    need = dense_bytes(n, dtype)
    limit = int(_MEMORY_FRACTION * available_memory()) if max_bytes is None else int(max_bytes)
    if need > limit:
        raise MemoryLimitError(
            f"a dense {n} x {n} form-factor matrix needs about {need / 2**30:.2f} GiB, more than the "
            f"{limit / 2**30:.2f} GiB allowed ({'max_bytes' if max_bytes is not None else '50% of available memory'}); "
            "stream it instead with hfrad.formfactors.iter_column_blocks (out of core, one column "
            "block at a time) or factor it directly with `hfrad precompute`")
    return need


def form_factor_matrix(scene, *, samples: int = DEFAULT_SAMPLES, dtype=np.float64,
                       progress: ProgressCallback = None, max_bytes: int | None = None,
                       block_size: int = DEFAULT_BLOCK_SIZE) -> np.ndarray:
    """Dense F (n x n) in the user's patch order, for scenes that fit in memory.

    F[i, j] = fraction of the energy leaving patch i that arrives at patch j,
    visibility included; A_i F[i, j] == A_j F[j, i] to rounding, F >= 0, and
    rows of a closed scene sum to ~1.

    Parameters
    ----------
    scene : Scene
    samples : int
        Visibility rays per pair (1, 4, 9, ...; 0 = no visibility).
    dtype : numpy dtype
    progress : callable (done, total), optional
    max_bytes : int, optional
        Memory allowed; default 50% of the available memory.

    Returns
    -------
    (n, n) ndarray of ``dtype``

    Raises
    ------
    MemoryLimitError
        If the estimated size exceeds the limit; the message names the
        out-of-core path (``iter_column_blocks`` / ``hfrad precompute``).

    Examples
    --------
    >>> from hfrad.scene.builtin import furnace
    >>> from hfrad.scene.patches import subdivide
    >>> scene = subdivide(furnace(), max_edge=0.5)
    >>> F = form_factor_matrix(scene)
    >>> bool(np.allclose(scene.areas[:, None] * F, (scene.areas[:, None] * F).T, rtol=1e-12, atol=0))
    True
    """
    n = scene.n_patches
    check_dense_memory(n, dtype, max_bytes)
    _check_common(scene, samples, block_size)
    F = np.empty((n, n), dtype=dtype)
    for start, stop, block in iter_column_blocks(scene, block_size, samples=samples, dtype=dtype,
                                                 progress=progress):
        F[:, start:stop] = block
    return F


def row_sums(scene, *, samples: int = DEFAULT_SAMPLES, block_size: int = DEFAULT_BLOCK_SIZE,
             progress: ProgressCallback = None) -> np.ndarray:
    """(n,) sum_j F[i, j], streamed (O(n b) memory); ~1 for every patch of a closed scene."""
    n = scene.n_patches
    total = np.zeros(n)
    for _, _, block in iter_column_blocks(scene, block_size, samples=samples, progress=progress):
        total += block.sum(axis=1)
    return total

