"""Form-factor column blocks in worker processes.

Embree casts without the GIL (raycast.py), but the kernel and the ray
preparation around the casts are not all GIL-free, so worker *processes*, not
threads, use every core. Here each worker *process* receives the scene once (pickled
at start-up), builds its own kernel geometry and Embree scene, and computes
whole column blocks ``F[order][:, cols]`` into a slot of shared memory; the
parent yields them in block order. A block depends only on (scene, engine
parameters, its column indices), never on which process computed it or in
which order, so multi-process blocks equal single-process ones bit for bit
(``tests/test_parallel.py``).

:func:`column_block` is the same computation as a plain function for any
process (the Dask backend calls it from its workers): it keeps one engine per
process and scene, so a worker pays the per-scene set-up once.

The ray budget (fewer rays for weak pairs) is chosen in
:mod:`hfrad.formfactors.budget`.

Faults: a worker dies with its parent. On Linux it asks the kernel for
SIGKILL when the parent exits (``prctl(PR_SET_PDEATHSIG)``; the pool is driven
from the thread that created it, as ``iter_blocks`` does), and on every system
a thread checks ``os.getppid()`` twice a second, so ``kill -9`` of the parent
leaves no orphaned worker computing blocks nobody will read. Workers ignore
SIGINT: Ctrl-C reaches the whole process group, and the parent alone stops the
pool (its workers terminated, not waited for). Shared-memory segments are named
``hfrad_<parent pid>_<random>``; Python's resource tracker unlinks those of a
killed parent once its workers are gone, and a new pool removes any such
segment whose creator is no longer running (:func:`remove_stale_segments`), in
case the tracker was killed too.
"""

from __future__ import annotations

import os
import pickle
import re
import secrets
import signal
import sys
import threading
import time
from concurrent.futures import ProcessPoolExecutor, TimeoutError as FutureTimeout
from concurrent.futures.process import BrokenProcessPool
from multiprocessing import get_context
from multiprocessing.shared_memory import SharedMemory
from typing import Iterator

import numpy as np

from ..errors import WorkerError
from .cache import scene_hash
from .engine import FormFactorEngine
from .mirror import block_request, computed_rows, put_computed_rows
from .budget import RayBudget
from .visibility import DEFAULT_SAMPLES

__all__ = ["ProcessEngine", "column_block",
           "MIN_PARALLEL_PATCHES", "remove_stale_segments", "SEGMENT_PREFIX"]

#: Below this many patches the workers' start-up (each a spawned interpreter that imports numpy,
#: numba and Embree and builds the scene's ray-casting structure) costs more than it saves.
MIN_PARALLEL_PATCHES = 4000

# Environment of worker processes: one BLAS and one numba thread each, so that
# ``workers`` processes fill ``workers`` cores without oversubscription.
_WORKER_ENV = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
               "NUMBA_NUM_THREADS": "1"}


# -- one engine per process (workers, Dask) ---------------------------------------------

_ENGINES: dict = {}


def cached_engine(scene, samples: int, ray_budget: RayBudget | None):
    key = (scene_hash(scene), int(samples), ray_budget or RayBudget())
    engine = _ENGINES.get(key)
    if engine is None:
        for old in _ENGINES.values():
            old.close()
        _ENGINES.clear()
        engine = FormFactorEngine(scene, samples=samples, ray_budget=ray_budget)
        _ENGINES[key] = engine
    return engine


def column_block(scene, cols, *, order=None, samples: int = DEFAULT_SAMPLES,
                 ray_budget: RayBudget | None = None, dtype=np.float32) -> np.ndarray:
    """``F[order][:, cols]`` (n x len(cols)) computed in this process, visibility included.

    A pure function of its arguments: the same call gives the same array in
    any process. The per-scene state (kernel geometry, Embree scene, culling
    masks) is built on the first call in a process and reused while ``scene``
    and the parameters stay the same, so a long-lived worker (a Dask worker,
    a pool process) pays for it once.

    Parameters
    ----------
    scene : Scene
    cols : (b,) int
        Column patch indices in the scene's (user) order, e.g. ``order[start:stop]``.
    order : (n,) int permutation, optional
        Row order (default: the scene's order).
    samples : int
        Visibility rays per pair (perfect square; 0 = no visibility).
    ray_budget : RayBudget, optional
        From :func:`ray_budget` (default: off, every pair gets all its rays).
    dtype : numpy dtype
        Of the returned block (computed in float64).

    Returns
    -------
    (n, b) ndarray of ``dtype``
    """
    engine = cached_engine(scene, samples, ray_budget)
    rows = np.arange(scene.n_patches) if order is None else np.asarray(order, np.int64)
    return engine.block(rows, np.asarray(cols, np.int64)).astype(dtype, copy=False)


# -- the process pool ------------------------------------------------------------------

_W: dict = {}  # per worker process: scene, order, engine, shared-memory view

#: Shared-memory segments of the pool are named ``SEGMENT_PREFIX<creator pid>_<random hex>``.
SEGMENT_PREFIX = "hfrad_"
_SEGMENT_NAME = re.compile(re.escape(SEGMENT_PREFIX) + r"(\d+)_[0-9a-f]+$")
#: Where POSIX shared memory appears as files (Linux); elsewhere nothing is swept.
_SHM_DIR = "/dev/shm"
#: A segment of a dead creator is removed only when older than this (seconds): a process of another
#: PID namespace sharing /dev/shm (a container) may look dead while its segment is in use.
STALE_SEGMENT_AGE = 60.0
#: Seconds between a worker's checks that its parent is alive.
_PARENT_CHECK = 0.5
_PR_SET_PDEATHSIG = 1


def _new_segment(size: int) -> SharedMemory:
    """A new shared-memory segment named after this process (see :func:`remove_stale_segments`)."""
    while True:
        try:
            return SharedMemory(name=f"{SEGMENT_PREFIX}{os.getpid()}_{secrets.token_hex(6)}", create=True,
                                size=max(1, int(size)))
        except FileExistsError:  # pragma: no cover - 48 random bits collided
            continue


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # PermissionError: someone else's live process
        return True
    return True


def remove_stale_segments(shm_dir: str = _SHM_DIR, min_age: float = STALE_SEGMENT_AGE) -> list[str]:
    """Unlink the pool segments left by processes that no longer run; returns their names.

    A parent killed with SIGKILL cannot unlink its segments; Python's resource
    tracker does once the parent's workers have exited, unless it was killed
    too (``kill -9`` of the whole process group). A segment is removed when
    its name carries :data:`SEGMENT_PREFIX`, its creator's PID is not a running
    process, and it is older than ``min_age`` seconds. Segments of other users
    are left alone (they cannot be unlinked).
    """
    try:
        names = os.listdir(shm_dir)
    except OSError:  # no /dev/shm (macOS, Windows): nothing to sweep
        return []
    removed, now = [], time.time()
    for name in names:
        m = _SEGMENT_NAME.match(name)
        if m is None or _pid_alive(int(m.group(1))):
            continue
        path = os.path.join(shm_dir, name)
        try:
            if now - os.stat(path).st_mtime < min_age:
                continue
            os.unlink(path)
        except OSError:
            continue
        removed.append(name)
    return removed


def _die_with_parent(parent_pid: int) -> None:
    """End this worker when ``parent_pid`` exits: SIGKILL from the kernel (Linux), and a watching thread."""
    if sys.platform.startswith("linux"):
        try:
            import ctypes
            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(_PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
        except (OSError, AttributeError):  # pragma: no cover - no prctl: the thread below remains
            pass
    if os.getppid() != parent_pid:  # the parent died before the request above
        os._exit(1)

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(_PARENT_CHECK)
        os._exit(1)  # orphaned: nobody reads our blocks

    threading.Thread(target=watch, name="hfrad-parent-watch", daemon=True).start()


def _init_worker(parent_pid: int, setup_name: str, setup_bytes: int, shm_name, shape, dtype) -> None:
    # Ctrl-C goes to the whole process group: the parent alone decides (it stops the pool)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _die_with_parent(parent_pid)
    try:
        import numba
        numba.set_num_threads(1)
    except Exception:  # noqa: BLE001 - only a performance setting
        pass
    setup = SharedMemory(name=setup_name)
    try:
        scene, order, samples, budget = pickle.loads(setup.buf[:setup_bytes])
    finally:
        setup.close()
    shm = SharedMemory(name=shm_name)
    _W.update(scene=scene, order=order, samples=samples, ray_budget=budget, shm=shm,
              out=np.ndarray(shape, dtype=dtype, buffer=shm.buf))


def _work(slot: int, cols: np.ndarray, skip: slice) -> dict:
    engine = cached_engine(_W["scene"], _W["samples"], _W["ray_budget"])
    k0, e0, p0, r0 = engine.kernel_seconds, engine.embree_seconds, engine.pairs, engine.rays
    t0 = time.perf_counter()
    block = engine.block(computed_rows(_W["order"], skip), cols)
    # rows ``skip`` are left for the parent to fill (reciprocity mirror)
    put_computed_rows(_W["out"][slot, :, :len(cols)], block, skip)
    return {"kernel_seconds": engine.kernel_seconds - k0, "embree_seconds": engine.embree_seconds - e0,
            "pairs": engine.pairs - p0, "rays": engine.rays - r0, "seconds": time.perf_counter() - t0}


#: Seconds between checks that the workers are alive while waiting for a block.
_ALIVE_CHECK = 1.0


def _result(pool: ProcessPoolExecutor, fut):
    """The future's result; WorkerError (saying what to do) if a worker process died.

    The pool reports a dead worker as BrokenProcessPool; the wait is also cut
    into short ones that check the workers' exit codes, in case a death goes
    unreported.
    """
    while True:
        try:
            return fut.result(timeout=_ALIVE_CHECK)
        except BrokenProcessPool:
            raise WorkerError(_DEAD_WORKER.format(code="unknown")) from None
        except FutureTimeout:
            # the pool's own process table (stable across CPython 3.8-3.13)
            dead = [p for p in getattr(pool, "_processes", {}).values() if p.exitcode is not None]
            if dead:
                raise WorkerError(_DEAD_WORKER.format(code=dead[0].exitcode)) from None


def _submit(pool: ProcessPoolExecutor, slot: int, cols: np.ndarray, skip: slice):
    """A future for one block; WorkerError if a worker already died (the pool is broken).

    A worker killed between two blocks breaks the pool before the next submit: that is
    the same dead worker as one seen while waiting (:func:`_result`), not a bug.
    """
    try:
        return pool.submit(_work, slot, cols, skip)
    except BrokenProcessPool:
        raise WorkerError(_DEAD_WORKER.format(code="unknown")) from None


_DEAD_WORKER = ("a form-factor worker process exited (exit code {code}) before finishing its block. If this "
                "runs from a script, put the script's code under `if __name__ == \"__main__\":` (workers are "
                "spawned and import the script again); otherwise it was killed (out of memory?): retry with "
                "processes=1")


class ProcessEngine:
    """Column blocks of one scene computed by ``workers`` processes (see module docstring).

    Same interface as :class:`~hfrad.formfactors.engine.FormFactorEngine`'s
    ``iter_blocks`` and counters (``kernel_seconds``, ``embree_seconds`` summed
    over workers, ``pairs``, ``rays``).

    Parameters
    ----------
    scene : Scene
    workers : int
        Processes (each uses one core: one numba and one BLAS thread).
    samples, ray_budget : see :func:`column_block`
    block_size : int
        Widest column block that will be asked for (sizes the shared slots).
    dtype : numpy dtype
        Of the blocks handed back (float32 halves the shared memory).
    """

    def __init__(self, scene, *, workers: int, samples: int = DEFAULT_SAMPLES, ray_budget: RayBudget | None = None,
                 block_size: int = 256, dtype=np.float64) -> None:
        self.scene, self.workers = scene, max(1, int(workers))
        self.samples, self.ray_budget = int(samples), ray_budget
        self.block_size, self.dtype = int(block_size), np.dtype(dtype)
        self.kernel_seconds = self.embree_seconds = 0.0
        self.pairs = self.rays = 0
        self.worker_seconds = 0.0

    def iter_blocks(self, rows: np.ndarray, col_sets, *, lend: bool = False) -> Iterator[np.ndarray]:
        """F[rows][:, cols] for each ``cols`` (or ``(cols, skip)``, as for
        :meth:`FormFactorEngine.iter_blocks`) of ``col_sets``, in order (``dtype``).

        Each block is a new array by default; ``lend=True`` copies every block into one
        array kept for the whole pass, valid (and the caller's to write) only until the
        next block is asked for: no fresh pages (page faults) for each n x b block. The
        shared slots themselves are never handed out: they are unmapped when the pass ends.
        """

        n = len(rows)
        slots = self.workers + 2
        shape = (slots, n, self.block_size)
        remove_stale_segments()
        # The scene reaches the workers through shared memory, not the spawn pipe: a worker that
        # dies while starting (a script without a __main__ guard) would leave the parent blocked
        # writing a large process object into that pipe, before any check could run.
        payload = pickle.dumps((self.scene, np.asarray(rows, np.int64), self.samples, self.ray_budget),
                               protocol=pickle.HIGHEST_PROTOCOL)
        setup_bytes = len(payload)
        setup = _new_segment(setup_bytes)
        try:
            setup.buf[:setup_bytes] = payload
            del payload
            shm = _new_segment(int(np.prod(shape)) * self.dtype.itemsize)
        except BaseException:
            _release(setup)
            raise
        saved = {k: os.environ.get(k) for k in _WORKER_ENV}
        os.environ.update(_WORKER_ENV)  # inherited by the spawned workers only
        try:
            pool = ProcessPoolExecutor(self.workers, mp_context=get_context("spawn"), initializer=_init_worker,
                                       initargs=(os.getpid(), setup.name, setup_bytes, shm.name, shape, self.dtype))
        except BaseException:
            _release(shm, setup)
            raise
        finally:
            for k, v in saved.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v
        view = np.ndarray(shape, dtype=self.dtype, buffer=shm.buf)
        free = list(range(slots))
        lent = None  # with lend: the one array every block is copied into
        pending: list = []  # (slot, width, future) in block order
        col_iter = iter(col_sets)
        finished = False
        try:
            exhausted = False
            while True:
                while not exhausted and len(pending) < self.workers + 1 and free:
                    item = next(col_iter, None)
                    if item is None:
                        exhausted = True
                        break
                    cols, skip = block_request(item)
                    if len(cols) > self.block_size:
                        raise ValueError(f"column block of {len(cols)} > block_size {self.block_size}")
                    slot = free.pop(0)
                    pending.append((slot, len(cols), _submit(pool, slot, cols, skip)))
                if not pending:
                    break
                slot, width, fut = pending.pop(0)
                stats = _result(pool, fut)
                self.kernel_seconds += stats["kernel_seconds"]
                self.embree_seconds += stats["embree_seconds"]
                self.pairs += stats["pairs"]
                self.rays += stats["rays"]
                self.worker_seconds += stats["seconds"]
                if lend:
                    if lent is None:
                        lent = np.empty((n, self.block_size), self.dtype)
                    block = lent[:, :width]
                    np.copyto(block, view[slot, :, :width])
                else:
                    block = view[slot, :, :width].copy()
                free.append(slot)
                yield block
            finished = True
        finally:
            for _, _, fut in pending:
                fut.cancel()
            if not finished:
                # an error, Ctrl-C or an abandoned generator: the blocks in flight are not wanted,
                # so the workers are stopped now rather than waited for
                for p in list((getattr(pool, "_processes", None) or {}).values()):
                    p.terminate()
            pool.shutdown(wait=True, cancel_futures=True)
            del view
            _release(shm, setup)

    def close(self) -> None:
        """Nothing to release between runs: the pool lives only while ``iter_blocks`` runs."""


def _release(*segments: SharedMemory) -> None:
    """Close and unlink shared-memory segments (one already removed is skipped)."""
    for segment in segments:
        segment.close()
        try:
            segment.unlink()
        except FileNotFoundError:
            pass

