"""Where and how the precompute runs: the backend objects and the checkpoint policy of :func:`hfrad.factorize`.

Small objects in the style of Mitsuba's integrators and SciPy's ``splu(options=)``:
``hfrad.factorize(scene, backend=LocalBackend(processes=4))`` or
``backend=DaskBackend(workers=4)``, ``checkpoint=Checkpoint("run.partial", interval=60)``.
None of them changes the factorization (the same F, rank and radiosity, up to the
rounding of the reciprocity copy); they decide where the column blocks, leaves and
merges run, with which threads, and how a run is saved while it goes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import InputError

__all__ = ["LocalBackend", "DaskBackend", "Checkpoint", "as_checkpoint"]


@dataclass(frozen=True)
class LocalBackend:
    """The precompute in this process (and its form-factor worker processes).

    Attributes
    ----------
    processes : int or None
        Form-factor worker processes (:class:`~hfrad.formfactors.parallel.ProcessEngine`;
        None: one per core from 4,000 patches on); the result does not depend on it.
        Default 1 (this process: numba threads plus one Embree thread) so that scripts
        need no ``if __name__ == "__main__":`` guard (workers are spawned); the CLI
        defaults to None. Workers pay off when they get cores of their own; on a
        loaded machine they compete with the other processes.
    blas_threads : int or None
        BLAS threads while the form-factor engine runs (None: leave as is). One is
        fastest while the engine uses the other cores; the last, largest merges get
        every thread (:mod:`hfrad.resources`).
    reciprocity : bool
        A column block copies its pairs with the columns of earlier blocks,
        ``F_ij = A_j F_ji / A_i``, instead of computing them again
        (:mod:`hfrad.formfactors.mirror`; about half the form-factor work, F equal to
        rounding; its tiles take at most a quarter of the available memory). False
        computes every pair (the Dask backend without its copy gives these blocks bit for bit).
    """

    processes: int | None = 1
    blas_threads: int | None = 1
    reciprocity: bool = True

    def __post_init__(self):   # processes are checked by the engine that starts them
        if self.blas_threads is not None and (isinstance(self.blas_threads, bool)
                                              or int(self.blas_threads) != self.blas_threads or self.blas_threads < 1):
            raise InputError(f"LocalBackend.blas_threads must be a whole number >= 1 or None; got {self.blas_threads!r}")


@dataclass(frozen=True)
class DaskBackend:
    """The precompute as Dask tasks: leaves and merges of HF's tree on a cluster (docs/cluster.md).

    The same options, class, ``.hfr`` contents and error figures as :class:`LocalBackend`
    (only ``params["backend"]``, ``params["workers"]`` and the timings differ).

    Attributes
    ----------
    scheduler : str, distributed.Client or hfrad.distributed.Cluster, optional
        ``tcp://HOST:PORT`` of a running scheduler, a connected Client, or a
        :class:`~hfrad.distributed.connection.Cluster` from :func:`hfrad.distributed.connect`.
    workers : int, optional
        Instead of ``scheduler``: a LocalCluster of this many worker processes.
    task_threads : int, optional
        Numba threads of the form-factor kernel per task (default: this machine's
        cores shared among a LocalCluster's workers; the workers' own setting,
        NUMBA_NUM_THREADS, on a scheduler). BLAS runs one thread per task.
    connect_timeout : float, seconds, optional
        Default: Dask's ``distributed.comm.timeouts.connect``.
    reciprocity : bool
        Each pair of groups of blocks within a band is computed once and copied by
        reciprocity (:mod:`hfrad.distributed.tiles`); False computes every pair.
    records : list, optional
        Filled with one dict per task (kind, node, rank, seconds, worker, ...): the
        measured costs behind docs/cluster.md's model
        (:func:`hfrad.distributed.factorize_distributed`).
    """

    scheduler: object = None
    workers: int | None = None
    task_threads: int | None = None
    connect_timeout: float | None = None
    reciprocity: bool = True
    records: list | None = field(default=None, compare=False, repr=False)


@dataclass(frozen=True)
class Checkpoint:
    """Save a running precompute so that a rerun resumes it.

    In this process, the stream state is written to ``path`` (one HDF5 file); on
    Dask, ``path`` names a folder of the finished subtrees' factors, reachable at
    this path from every worker, so a rerun skips them. A damaged checkpoint, or
    one made for another input, is refused (FileFormatError / InputError), never resumed.

    Attributes
    ----------
    path : str or Path
        The checkpoint; resumed from when it exists.
    interval : float, seconds
        In this process: at least this long between writes, and at least
        ``CHECKPOINT_COST_RATIO`` (50) times the last write's duration (0: after every
        block, whatever it costs).
    keep : bool
        Leave the checkpoint in place when the factorization completes, for a caller
        that deletes it only once the result is safely saved (``hfrad precompute``
        removes it after the ``.hfr`` file is renamed into place, so a crash while
        saving loses nothing). Default: deleted on completion.
    """

    path: str | Path
    interval: float = 30.0
    keep: bool = False

    def __post_init__(self):
        if not (self.interval >= 0 and math.isfinite(self.interval)):
            raise InputError(f"Checkpoint.interval must be a number of seconds >= 0; got {self.interval!r}")


def as_checkpoint(checkpoint) -> Checkpoint | None:
    """``factorize(checkpoint=...)``: None, a path (the default interval, deleted on completion) or a Checkpoint."""
    if checkpoint is None or isinstance(checkpoint, Checkpoint):
        return checkpoint
    if isinstance(checkpoint, (str, Path)):
        return Checkpoint(checkpoint)
    raise InputError(f"checkpoint must be a path or an hfrad.Checkpoint; got {type(checkpoint).__name__}")

