"""The engine that computes sub-blocks of F in this process: kernel and visibility, pipelined.

:class:`FormFactorEngine` is what :mod:`hfrad.formfactors.blocks` streams
with and what each worker of :mod:`hfrad.formfactors.parallel` (and of the
Dask backend) runs, so it sits below both and imports neither.
"""

from __future__ import annotations

import queue
import threading
import time
from collections import deque
from dataclasses import dataclass
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait
from typing import Iterator

import numba
import numpy as np

from ..resources import numba_loops_at_once
from .budget import RayBudget
from .clustered import kernel_for
from .kernel import NEAR, TOLERANCE
from .mirror import block_request, computed_rows, full_height
from .visibility import DEFAULT_SAMPLES, Visibility

__all__ = ["FormFactorEngine"]

#: Ray batches queued for an Embree thread at once (each holds up to RAY_BATCH rays).
_IN_FLIGHT = 2

#: Seconds of kernel work the pipeline does between looks at the ray queue (one chunk of columns).
_KERNEL_STEP_SECONDS = 0.04


class FormFactorEngine:
    """Computes sub-blocks F[rows][:, cols] of one scene.

    Holds the per-scene state (kernel geometry, sample points, Embree scene),
    so computing many blocks pays for it once, and keeps counters
    (``kernel_seconds``, ``embree_seconds``, ``pairs``, ``rays``).

    Parameters
    ----------
    scene : Scene
    samples : int
        Visibility rays per pair (1, 4, 9, ...); 0 disables visibility (F unoccluded).
    near, tolerance : see :mod:`hfrad.formfactors.kernel` (adaptive-path threshold and its
        relative tolerance).
    ray_budget : RayBudget, optional
        Fewer rays for weak pairs (one, or ``samples`` instead of 16 where probes
        disagree, no second round or 64 rays in it instead of 256; see
        :func:`hfrad.formfactors.budget.ray_budget`); default: off.
    cluster_size : int, optional
        Patches per cluster for visibility decided once per cluster pair where it is
        all or nothing (:mod:`hfrad.formfactors.clustervis`); 0 = off; default
        :data:`~hfrad.formfactors.visibility.CLUSTER_VISIBILITY`.
    ray_threads : int or None
        Threads casting a batch of rays (:class:`~hfrad.formfactors.visibility.Visibility`):
        1 for :meth:`iter_blocks`' pipeline (default), None (every core) for callers of :meth:`block`.

    Notes
    -----
    :meth:`iter_blocks` keeps both halves of the work going at once: Embree casts
    the queued ray batches in a thread (packets from numba, no GIL held: see
    :mod:`hfrad.formfactors.raycast`) while the pipeline computes kernel columns
    of the next block (a chunk at a time, on the cores Embree leaves), and once
    no kernel is left a second Embree thread takes batches too (``_Pipeline``).
    Where numba allows it the pipeline runs one block ahead of the caller in its
    own thread, so HF's work on a block overlaps the next blocks' form factors.
    """

    def __init__(self, scene, *, samples: int = DEFAULT_SAMPLES, near: float = NEAR,
                 tolerance: float = TOLERANCE, ray_budget: RayBudget | None = None,
                 cluster_size: int | None = None, ray_threads: int | None = 1) -> None:
        # patches that are clusters of triangles (hfrad.scene.cluster) have their own kernel
        self.geometry, self._unoccluded = kernel_for(scene, near=near, tolerance=tolerance)
        self.samples = int(samples)
        self.visibility = (Visibility(scene, samples=samples, ray_budget=ray_budget, cluster_size=cluster_size,
                                      ray_threads=ray_threads) if samples else None)
        self.kernel_seconds = 0.0
        self.pairs = 0
        self._executor = None
        self._tail_executor = None

    @property
    def rays(self) -> int:
        return self.visibility.rays_cast if self.visibility is not None else 0

    @property
    def embree_seconds(self) -> float:
        return self.visibility.embree_seconds if self.visibility is not None else 0.0

    def _kernel(self, rows, cols) -> np.ndarray:
        t0 = time.perf_counter()
        F = self._unoccluded(self.geometry, rows, cols)
        self.kernel_seconds += time.perf_counter() - t0
        self.pairs += F.size
        return F

    def unoccluded(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """(len(rows), len(cols)) float64 F[rows][:, cols] without visibility (counted in ``pairs``)."""
        return self._kernel(rows, cols)

    def block(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """(len(rows), len(cols)) float64 F[rows][:, cols] with visibility."""
        F = self._kernel(rows, cols)
        if self.visibility is not None:
            self.visibility.apply(F, rows, cols)
        return F

    def iter_blocks(self, rows: np.ndarray, col_sets, *, lend: bool = False,
                    ahead: bool = True) -> Iterator[np.ndarray]:
        """F[rows][:, cols] for each ``cols`` of ``col_sets``, in order, pipelined (see Notes).

        An item of ``col_sets`` may be ``(cols, skip)`` with ``skip`` a slice of
        positions in ``rows`` that are not computed (left unspecified in the
        block: the caller fills them, see :mod:`hfrad.formfactors.mirror`).
        ``lend`` is accepted for the process engine's interface: blocks here are
        always fresh arrays. ``ahead`` (default): the pipeline runs in a thread of
        its own and has the next block ready (one more n x b block in memory) while
        the caller works on this one; ``col_sets`` is then read from that thread.
        """
        if self.visibility is None:
            for item in col_sets:
                cols, skip = block_request(item)
                yield full_height(self._kernel(computed_rows(rows, skip), cols), skip, len(rows))
            return
        if self._executor is None:
            self._executor = ThreadPoolExecutor(1, thread_name_prefix="hfrad-embree")
        if self._tail_executor is None:
            self._tail_executor = ThreadPoolExecutor(1, thread_name_prefix="hfrad-embree-tail")
        blocks = _Pipeline(self, rows, col_sets).run()
        # the caller's work on a block (HF, the pass statistics) overlaps the next blocks' when this
        # thread and the pipeline's may both run numba's parallel loops (see numba_loops_at_once)
        yield from _ahead(blocks) if ahead and numba_loops_at_once() else blocks

    def close(self) -> None:
        for pool in (self._executor, self._tail_executor):
            if pool is not None:
                pool.shutdown()
        self._executor = self._tail_executor = None
        if self.visibility is not None:
            self.visibility.close()


class _KernelAhead:
    """The unoccluded kernel of the coming blocks, a chunk of columns at a time.

    The pipeline computes one chunk whenever it has nothing else to do, so the
    kernel of block k + 1 runs while Embree casts the rays of block k; at most one
    whole block is computed ahead (memory: one more n x b float64 block).
    """

    def __init__(self, engine: FormFactorEngine, rows: np.ndarray, col_sets) -> None:
        self.engine = engine
        self.rows = rows
        self.items = iter(col_sets)
        self.partial = None          # [F, part, cols, skip, columns done] of the block being computed
        self.ready: deque = deque()  # (F, part, cols, skip) of whole blocks, in order
        self.exhausted = False       # every block's kernel is computed
        self.per_column = 0.0        # wall seconds a column, last chunk
        self.threads = numba.get_num_threads()

    def has_work(self) -> bool:
        return not self.exhausted and not self.ready

    def step(self, embree_threads: int) -> None:
        """Compute about _KERNEL_STEP_SECONDS of kernel columns (a new block when none is open),
        on the cores that ``embree_threads`` busy Embree threads leave."""
        if self.partial is None:
            item = next(self.items, None)
            if item is None:
                self.exhausted = True
                return
            cols, skip = block_request(item)
            part = computed_rows(self.rows, skip)
            if not (len(part) and len(cols)):
                self.ready.append((self.engine._kernel(part, cols), part, cols, skip))
                return
            self.partial = [np.empty((len(part), len(cols))), part, cols, skip, 0]
        F, part, cols, skip, done = self.partial
        width = 8 if self.per_column <= 0 else int(np.clip(_KERNEL_STEP_SECONDS / self.per_column, 1, len(cols)))
        stop = min(len(cols), done + width)
        t0 = time.perf_counter()
        # numba's threads share the cores with the Embree threads casting now: more threads than cores
        # would make the kernel's threads wait for each other at the end of each chunk
        numba.set_num_threads(max(1, self.threads - embree_threads))
        try:
            F[:, done:stop] = self.engine._kernel(part, cols[done:stop])  # each entry alone: the same bits
        finally:
            numba.set_num_threads(self.threads)
        self.per_column = (time.perf_counter() - t0) / (stop - done)
        self.partial[4] = stop
        if stop == len(cols):
            self.ready.append((F, part, cols, skip))
            self.partial = None


class _Pipeline:
    """One pass of :meth:`FormFactorEngine.iter_blocks`: kernel chunks on this thread, rays on Embree's.

    This thread generates each block's ray batches (at most ``_IN_FLIGHT`` queued for
    the Embree thread), finishes the cast ones (their second rounds go back to the
    queue) and, whenever the queue is full, computes kernel columns of the next
    block. When it has no kernel left to compute (the pass's last block, or the next
    block is done before this one's rays are queued) a second Embree thread takes
    batches too, so neither core waits for the other (Sponza, 3,129 patches: the
    kernel took 17 s of CPU and the rays 15 s; computed one after the other per
    block they overlapped for 9 s of the pass's 25).
    """

    def __init__(self, engine: FormFactorEngine, rows: np.ndarray, col_sets) -> None:
        self.vis = engine.visibility
        self.n = len(rows)
        self.kernel = _KernelAhead(engine, rows, col_sets)
        self.pools = (engine._executor, engine._tail_executor)
        self.inflight: list = []     # (block, job, future, pool index) of the batches queued or being cast
        self.blocks: deque = deque()  # _Block of every block whose rays are not all cast, in order
        self.jobs = None             # batch generator of the block whose rays are being queued
        self.current = None          # that block

    def run(self) -> Iterator[np.ndarray]:
        try:
            while True:
                self._finish(block=False)     # cast batches free their Embree thread at once
                yield from self._done_blocks()
                if self.jobs is None and self.kernel.ready:
                    self._start_block()
                if self.jobs is not None and self._room():
                    self._queue_next()
                elif self.kernel.has_work():
                    self.kernel.step(sum(q > 0 for q in self._queued()))
                elif self.inflight:
                    self._finish(block=True)
                elif self.jobs is None and not self.kernel.ready:
                    break
            yield from self._done_blocks()
        finally:
            for item in self.inflight:  # consumer stopped early: let Embree finish before reuse
                item[2].result()

    def _queued(self) -> list[int]:
        """Batches queued on (or being cast by) each Embree thread."""
        counts = [0, 0]
        for item in self.inflight:
            counts[item[3]] += 1
        return counts

    def _room(self) -> bool:
        queued = self._queued()
        helping = not self.kernel.has_work()   # nothing else for this thread: the second Embree thread
        return queued[0] < _IN_FLIGHT or (helping and queued[1] < _IN_FLIGHT)

    def _start_block(self) -> None:
        F, part, cols, skip = self.kernel.ready.popleft()
        self.current = _Block(F, skip)
        self.blocks.append(self.current)
        self.jobs = self.vis.jobs(F, part, cols)

    def _queue_next(self) -> None:
        job = next(self.jobs, None)
        if job is None:
            self.current.queuing = False
            self.jobs = self.current = None
            return
        self._submit(self.current, job)

    def _submit(self, block: "_Block", job) -> None:
        queued = self._queued()
        k = 0 if queued[0] < _IN_FLIGHT or queued[0] <= queued[1] else 1
        block.in_flight += 1
        self.inflight.append((block, job, self.pools[k].submit(self.vis.cast, job), k))

    def _finish(self, block: bool) -> None:
        """Finish every batch cast so far (``block``: waiting for one if none is); second rounds are queued."""
        if not self.inflight:
            return
        if block:
            wait([item[2] for item in self.inflight], return_when=FIRST_COMPLETED)
        finished = [item[2].done() for item in self.inflight]
        done = [item for item, f in zip(self.inflight, finished) if f]
        self.inflight = [item for item, f in zip(self.inflight, finished) if not f]
        for owner, job, future, _ in done:
            for more in self.vis.finish(owner.F, job, future.result()):
                self._submit(owner, more)
            owner.in_flight -= 1

    def _done_blocks(self) -> Iterator[np.ndarray]:
        """The leading blocks whose rays are all cast, in order."""
        while self.blocks and not self.blocks[0].queuing and self.blocks[0].in_flight == 0:
            done = self.blocks.popleft()
            yield full_height(done.F, done.skip, self.n)


@dataclass
class _Block:
    """A block of the pipeline from its kernel to its last ray: F, the rows left to the caller, its batches
    queued or being cast, and whether more are still to be queued."""

    F: np.ndarray
    skip: slice | None
    in_flight: int = 0
    queuing: bool = True


def _ahead(blocks: Iterator[np.ndarray]) -> Iterator[np.ndarray]:
    """The items of ``blocks``, computed in a thread of its own one item ahead of the caller.

    An exception there is raised here; a caller that stops early (or is interrupted) stops
    the thread, which finishes the step it is in (a kernel chunk, a wait for Embree) first.
    """
    handoff: queue.Queue = queue.Queue(maxsize=1)
    stop = threading.Event()

    def put(item) -> bool:
        while not stop.is_set():
            try:
                handoff.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def produce() -> None:
        try:
            for block in blocks:
                if not put(("block", block)):
                    return
            put(("end", None))
        except BaseException as error:  # noqa: BLE001 - handed to the caller's thread
            put(("error", error))
        finally:
            blocks.close()

    worker = threading.Thread(target=produce, name="hfrad-formfactors", daemon=True)
    worker.start()
    try:
        while True:
            kind, item = handoff.get()
            if kind == "end":
                return
            if kind == "error":
                raise item
            yield item
            del item
    finally:
        stop.set()
        worker.join()

