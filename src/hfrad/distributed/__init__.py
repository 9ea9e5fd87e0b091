"""The precomputation on a Dask cluster (``hfrad precompute --scheduler/--workers``).

The sibling of :mod:`hfrad.precompute.local` (the in-process loop): it runs the same
plan (:mod:`hfrad.precompute`) as Dask tasks, and only the public facade
(:mod:`hfrad.pipeline`), the CLI and the top-level API import it::

    import hfrad
    from hfrad.distributed import connect
    with connect("tcp://scheduler:8786") as cluster:     # or connect(workers=4)
        print(cluster.dashboard)
        fac = hfrad.factorize(scene, eps=0.02, backend=hfrad.DaskBackend(scheduler=cluster))

``hfrad.factorize`` validates the options once (:mod:`hfrad.precompute.options`) for both
backends; :func:`factorize_distributed` is this backend's entry behind it.

See docs/cluster.md for running it on a real cluster and the memory each worker needs.
"""

from .connection import Cluster, SchedulerUnreachableError, WorkerLostError, connect
from .run import DaskTuning, factorize_distributed
from .sizing import rank_guess, worker_bytes
from .store import remove_folder as remove_checkpoint

__all__ = ["Cluster", "DaskTuning", "SchedulerUnreachableError", "WorkerLostError", "connect", "factorize_distributed", "rank_guess",
           "remove_checkpoint", "worker_bytes"]
