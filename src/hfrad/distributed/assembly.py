"""The assembly step on Dask workers: the near-field set-up's pieces as tasks.

:func:`hfrad.precompute.assemble.assemble` builds the solver object; with the near-field
split most of its time is the set-up of :class:`~hfrad.solve.nearfield.NearFieldFactorization`:
per distinct colour channel a sparse LU of ``A_c = I - D_c N`` and ``k`` solves
``Z_c = A_c^{-1} D_c Q``, then ``K_c = I - V^T Z_c``. That set-up is written as pure
functions (:func:`~hfrad.solve.nearfield.channel_solver`,
:func:`~hfrad.solve.nearfield.near_columns`, :func:`~hfrad.solve.nearfield.row_maxima`,
:func:`~hfrad.solve.nearfield.column_products`) driven by a *runner*; the local
backend runs them in its own process (:class:`~hfrad.solve.nearfield.InProcess`),
:class:`DaskRunner` submits them to the cluster. The driver is the same code, so
the object is the same: ``Z`` identical, ``K_c^{-1}`` equal to float32 rounding.

Task graph per distinct channel c (d channels, ``P = ceil(k / columns)`` panels)::

    channel_solver(N, d_c)            one task: SuperLU + L, U copy   (critical path)
      -> near_columns(solver, d_c, Q[:, panel])    P tasks            (parallel)
        -> row_maxima(panel)          P small tasks (n floats back)
        -> column_products(panel, V, scale)        P tasks: codes (n x w int16) and V^T Z (k x w) back

The client then decides the 16-bit storage from the row scales, inverts the d
``k x k`` matrices and builds the object.

With ``neumann=True`` (what runs on 3 or more workers do) there is no LU: one task bounds
N's spectral radius, and each column panel's task applies ``A_c^{-1}`` by the
Chebyshev-accelerated Neumann series over N (:class:`~hfrad.solve.nearfield.NeumannColumns`), so the critical
path is one panel's sweeps, not a channel's factorization; Z then equals the LU path's
to :data:`~hfrad.solve.nearfield.SETUP_TOL` (the float64 LU's to ~1e-8 relative, closer than the float32 panels). The channels are factored at once
(``share_order=False``: the shortest critical path); in one process the later
channels reuse the first one's fill-reducing order instead (less work in all).
"""

from __future__ import annotations

import os
import time

import numpy as np

from ..precompute.assemble import PrecomputePlan, assemble
from ..solve.nearfield import SETUP_TOL, NeumannColumns, channel_solver, neumann_channel
from ..solve.neumann import spectral_bound
from ..solve.sparselu import PANEL
from ..solve.stats import PassStatistics

__all__ = ["DaskRunner", "assemble_on_cluster", "ASSEMBLY_TOPIC", "NeumannColumns", "neumann_channel",
           "SETUP_TOL"]

#: The Dask event topic the pieces log their times under (``client.get_events(ASSEMBLY_TOPIC)``).
ASSEMBLY_TOPIC = "hfrad-assembly"


def _timed(fn, *args):
    """``fn(*args)``, logging its wall and CPU seconds as a Dask event of the worker that ran it."""
    wall, cpu = time.perf_counter(), time.process_time()
    out = fn(*args)
    record = {"piece": fn.__name__, "wall_s": time.perf_counter() - wall, "cpu_s": time.process_time() - cpu,
              "pid": os.getpid()}
    try:
        from distributed import get_worker

        worker = get_worker()
        record["worker"] = worker.address
        worker.log_event(ASSEMBLY_TOPIC, record)
    except ValueError:   # not on a worker (a test calling it directly)
        pass
    return out


class DaskRunner:
    """Runs the near-field set-up's pieces as Dask tasks (the runner interface of
    :class:`~hfrad.solve.nearfield.InProcess`).

    Parameters
    ----------
    client : distributed.Client
    columns : int
        Columns of ``D_c Q`` per task; default :data:`~hfrad.solve.sparselu.PANEL`
        (a panel the triangular solves take at once). Fewer columns: more tasks, each
        reading the channel's L and U once more (and fetching them once per worker).
    share_order : bool
        Factor the first distinct channel, then the others in its order (less CPU,
        a longer critical path); default False.
    neumann : bool
        No sparse LUs: each column panel's task applies ``A_c^{-1}`` by Neumann sweeps over N
        (:class:`NeumannColumns`; one task bounds N's spectral radius first). Z equals the LU
        path's to :data:`~hfrad.solve.nearfield.SETUP_TOL` instead of to rounding. Default False.
    """

    def __init__(self, client, *, columns: int = PANEL, share_order: bool = False, neumann: bool = False) -> None:
        self.client, self.columns, self.share_order = client, int(columns), bool(share_order) and not neumann
        self.neumann = bool(neumann)
        self._rho = None

    def scatter(self, x):
        return self.client.scatter(x, hash=False)

    def submit(self, fn, *args):
        if self.neumann and fn is channel_solver:
            N, d, dtype, channel = args[:4]
            if self._rho is None:    # one bound serves every channel (0 <= D_c <= 1)
                self._rho = self.client.submit(_timed, spectral_bound, N, pure=False)
            return self.client.submit(_timed, neumann_channel, N, d, dtype, channel, self._rho, pure=False)
        return self.client.submit(_timed, fn, *args, pure=False)

    def gather(self, xs):
        return self.client.gather(list(xs))

    def release(self, x) -> None:
        """Nothing to do: a future's data is freed once no task or reference needs it."""


def assemble_on_cluster(client, scene, options: PrecomputePlan, lowrank, stats: PassStatistics,
                        near: dict | None = None, *, backend: dict | None = None, columns: int = PANEL,
                        share_order: bool = False, neumann: bool = False, records: list | None = None):
    """:func:`hfrad.precompute.assemble.assemble` with the near-field set-up's pieces on Dask workers.

    Parameters
    ----------
    client : distributed.Client or hfrad.distributed.Cluster
    scene, options, lowrank, stats, near, backend
        As for :func:`~hfrad.precompute.assemble.assemble`.
    columns, share_order, neumann
        As for :class:`DaskRunner`.
    records : list, optional
        Extended with one dict per piece (``piece``, ``wall_s``, ``cpu_s``, ``worker``):
        the per-task costs a cluster model reads.

    Returns
    -------
    HFactorization or NearFieldFactorization
        The object :func:`~hfrad.precompute.assemble.assemble` returns for the same
        inputs (``time_nearfield_setup`` in ``lowrank.info`` is this call's wall time).
    """
    client = getattr(client, "client", client)   # a hfrad Cluster holds its Client
    runner = DaskRunner(client, columns=columns, share_order=share_order, neumann=neumann)
    start = time.time()
    fac = assemble(scene, options, lowrank, stats, near, backend=backend, runner=runner)
    if records is not None:
        records.extend(msg for when, msg in client.get_events(ASSEMBLY_TOPIC) if when >= start)
    return fac
