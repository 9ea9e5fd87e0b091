"""The near-field LUs factored in a background thread while other work of the precompute runs.

The near-field set-up's sparse LUs (:func:`~hfrad.solve.nearfield.channel_solver`, one per
distinct colour channel, single-threaded) need only the near field N, which is known before
the factors are:

- the Dask backend with fewer than :data:`~hfrad.distributed.run.ASSEMBLY_MIN_WORKERS` workers:
  N is complete once every leaf is, before the row-panelled top merges, whose serial steps (the
  small step, the Gram reduction) leave cores idle;
- ``far_field="hierarchical"``: N leaves the H-matrix before the operator factorization, whose
  single-threaded steps (QR, SVD of each block of the basis) leave a core idle.

:class:`NearPrefetch` factors the channels then, in background threads at a lower CPU
priority (``nice``; the first channel, then the others at once on a thread each), so it
takes the cores the rest leaves idle first;
:meth:`NearPrefetch.runner` gives the in-process runner that hands those factors to the assembly.

The assembly is unchanged: the runner returns a prefetched factor only for the very
call it was made for (same N, same channel scale, dtype and order: compared entry by
entry), and computes anything else itself, so the object is the one
:class:`~hfrad.solve.nearfield.InProcess` makes, bit for bit.
"""

from __future__ import annotations

import atexit
import concurrent.futures
import os
import threading

import numpy as np
import scipy.sparse as sp

from .nearfield import InProcess, channel_solver, solver_order
from .woodbury import N_CHANNELS

__all__ = ["NearPrefetch", "PrefetchRunner", "PREFETCH_NICE", "PREFETCH_MAX_SHARE", "PREFETCH_BESIDE_SHARE", "prefetch_fits"]

#: Niceness of the prefetching thread (Linux: per thread): the worker processes on the same
#: cores keep their share while they are busy; the LU takes what they leave idle.
PREFETCH_NICE = 10
#: The channels after the first are prefetched only while their factors (each about the size
#: of the first one's) fit this share of the available memory; the rest are factored by the
#: assembly, one at a time, as without the prefetch.
PREFETCH_MAX_SHARE = 0.25
#: A client starts the prefetch only where the near field's estimated set-up
#: (:func:`hfrad.memory.near_field_bytes`: one channel's LU while it is factored) takes at most this share
#: of the memory available then: the work it runs beside keeps its own memory meanwhile.
PREFETCH_BESIDE_SHARE = 0.5


def prefetch_fits(n: int, entries: int) -> bool:
    """Whether the near field of ``entries`` a row is factored (:func:`hfrad.memory.near_factored`; above
    that the set-up sweeps and there is nothing to prefetch) and its LU fits beside the client's other
    work now (:data:`PREFETCH_BESIDE_SHARE` of the available memory)."""
    from ..memory import available_bytes, near_factored, near_field_bytes

    return near_factored(entries) and near_field_bytes(n, entries) <= PREFETCH_BESIDE_SHARE * available_bytes()


def channel_scales(reflectance: np.ndarray, perm: np.ndarray) -> tuple[list[int], dict[int, np.ndarray]]:
    """The distinct channels and their scales ``d_c = rho_c / rho_max`` (internal order), as the assembly's.

    Returns
    -------
    distinct : list of int
        Channels whose ``d_c`` differs from every earlier channel's.
    d : dict channel -> (n,) float64
    """
    reflectance = np.asarray(reflectance, np.float64)
    rho_max = reflectance.max(axis=1)
    D = np.zeros_like(reflectance)
    np.divide(reflectance, rho_max[:, None], out=D, where=rho_max[:, None] > 0)
    D = D[perm]
    distinct = [c for c in range(N_CHANNELS) if not any(np.array_equal(D[:, s], D[:, c]) for s in range(c))]
    return distinct, {c: np.ascontiguousarray(D[:, c]) for c in distinct}


def near_matrix(near: dict, n: int) -> sp.csr_matrix:
    """N (n x n float64 CSR) from the near entries, as :func:`hfrad.precompute.assemble.assemble` builds it."""
    N = sp.csr_matrix((near["near_values"], (near["near_rows"], near["near_cols"])), shape=(n, n))
    return sp.csr_matrix(N, dtype=np.float64)


def _same_matrix(a, b) -> bool:
    return (a.shape == b.shape and np.array_equal(a.indptr, b.indptr) and np.array_equal(a.indices, b.indices)
            and np.array_equal(a.data, b.data))


class NearPrefetch:
    """Factors ``A_c = I - D_c N`` of each distinct channel in background threads, with the arguments
    :class:`~hfrad.solve.nearfield.InProcess` would use (the first channel, then the others in its
    fill-reducing order, all at once).

    Parameters
    ----------
    near : dict
        The near entries of all n columns (``near_rows``, ``near_cols``, ``near_values``).
    n : int
    reflectance : (n, 3) array
        The scene's reflectances (user order).
    perm : (n,) int
        The internal order.
    dtype : numpy dtype
        The factors' dtype (the solvers' panels).
    nice : int
        Niceness added to the prefetching thread (0: none).
    """

    def __init__(self, near: dict, n: int, reflectance, perm, dtype, *, nice: int = PREFETCH_NICE) -> None:
        self.N = near_matrix(near, n)
        self.distinct, self.d = channel_scales(reflectance, perm)
        self.dtype = np.dtype(dtype)
        self.nice = int(nice)
        self._solvers = {c: concurrent.futures.Future() for c in self.distinct}
        self._order = None
        self._tids: list[int] = []
        self._stop = False
        self._hurried = False
        self.hits = 0
        self._thread = threading.Thread(target=self._work, name="hfrad-near-prefetch", daemon=True)
        self._thread.start()

    def _work(self) -> None:
        """The first channel, then the others at once, each on a thread of its own (SciPy's SuperLU holds
        no GIL): they share the first one's order and are independent, and the set-up, which takes them
        one after the other, would otherwise wait for each in turn with a core idle."""
        from ..memory import available_bytes

        self._lower_priority()
        first, rest = self.distinct[0], self.distinct[1:]
        solver = self._factor(first)
        if solver is None or not rest:
            return
        self._order = solver_order(solver)
        bytes_each = sum(x.nbytes for x in (*getattr(solver, "_L", ()), *getattr(solver, "_U", ())))
        if bytes_each * len(rest) > PREFETCH_MAX_SHARE * available_bytes():
            self._stop = True
        helpers = [threading.Thread(target=self._helper, args=(c,), name="hfrad-near-prefetch", daemon=True)
                   for c in rest[1:]]
        for helper in helpers:
            helper.start()
        self._factor(rest[0])
        for helper in helpers:
            helper.join()

    def _helper(self, channel: int) -> None:
        self._lower_priority()
        self._factor(channel)

    def _lower_priority(self) -> None:
        tid = threading.get_native_id()
        self._tids.append(tid)
        if self.nice and not self._hurried and hasattr(os, "setpriority"):
            try:
                os.setpriority(os.PRIO_PROCESS, tid, os.getpriority(os.PRIO_PROCESS, tid) + self.nice)
            except OSError:
                pass

    def _factor(self, c: int):
        """Channel c's solver into its future (None where it is stopped, cancelled or fails: its taker
        computes it, and raises there)."""
        future = self._solvers.get(c)
        if future is not None and self._stop:
            future.cancel()       # its taker computes it (take sees it cancelled)
        if future is None or self._stop or not future.set_running_or_notify_cancel():
            return None
        try:
            solver = channel_solver(self.N, self.d[c], self.dtype, c, self._order)
        except BaseException as exc:   # the assembly computes it again and raises there
            future.set_exception(exc)
            return None
        future.set_result(solver)
        return solver

    def _hurry(self) -> None:
        """Back to the process's niceness: the client now waits for the thread (fails quietly where
        raising the priority again needs privileges)."""
        self._hurried = True
        if self.nice and hasattr(os, "setpriority"):
            for tid in list(self._tids):
                try:
                    os.setpriority(os.PRIO_PROCESS, tid, os.getpriority(os.PRIO_PROCESS, 0))
                except OSError:
                    pass

    def take(self, N, d, dtype, channel: int, order):
        """The prefetched solver for exactly these arguments of :func:`channel_solver`, or None."""
        future = self._solvers.get(channel)
        if future is None:
            return None
        expected = None if channel == self.distinct[0] else self._order
        if (np.dtype(dtype) != self.dtype or not np.array_equal(np.asarray(d), self.d[channel])
                or (order is None) != (expected is None)
                or (order is not None and not np.array_equal(np.asarray(order), expected))
                or not _same_matrix(N, self.N)):
            return None
        self._hurry()
        try:
            # the thread takes the channels in the assembly's order: a pending one is next, or cancelled
            solver = future.result()
        except (Exception, concurrent.futures.CancelledError):  # noqa: BLE001 - the caller computes it
            return None
        self._solvers[channel] = None   # the assembly holds it now (and drops it when done)
        self.hits += 1
        return solver

    def close(self, wait: bool = True) -> None:
        """Stop after the current factorization and drop the unused solvers.

        ``wait=False`` (a run given up: Ctrl-C, an error) returns at once: the factorization in
        flight (SuperLU, which cannot be interrupted: 25-35 s a channel at 161,808 Cornell-box
        patches) finishes on its daemon thread and its result is dropped, so a caller in Python (a
        notebook) has control back at once. The interpreter's exit still waits for it (an ``atexit``
        join): exiting while the thread was inside SuperLU failed the exit's flush of stdout (status
        120 instead of the CLI's 130)."""
        self._stop = True
        for future in self._solvers.values():
            if future is not None:
                future.cancel()
        self._hurry()
        if wait:
            self._thread.join()     # it joins its helpers
        else:                       # the interpreter's exit may not race a thread inside SuperLU
            atexit.register(self._thread.join)
        self._solvers.clear()

    def runner(self) -> "PrefetchRunner":
        return PrefetchRunner(self)


class PrefetchRunner(InProcess):
    """:class:`~hfrad.solve.nearfield.InProcess` that takes a :class:`NearPrefetch`'s factors when the
    assembly asks for exactly them."""

    def __init__(self, prefetch: NearPrefetch) -> None:
        super().__init__()
        self.prefetch = prefetch

    def submit(self, fn, *args):
        if fn is channel_solver:
            solver = self.prefetch.take(*args)
            if solver is not None:
                return solver
        return fn(*args)
