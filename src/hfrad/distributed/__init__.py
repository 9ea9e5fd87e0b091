"""The precomputation on a Dask cluster (``hfrad precompute --scheduler/--workers``).

Sits beside :mod:`hfrad.pipeline`: it uses scene/, formfactors/, lowrank/ and
solve/, and only the CLI and the top-level API import it::

    import hfrad
    from hfrad.distributed import connect
    with connect("tcp://scheduler:8786") as cluster:     # or connect(workers=4)
        print(cluster.dashboard)
        fac = hfrad.factorize(scene, scheduler=cluster, eps=0.02)

``hfrad.factorize`` validates the options once (:mod:`hfrad.solve.assemble`) for both
backends; :func:`factorize_distributed` is this backend's entry behind it.

See docs/cluster.md for running it on a real cluster and the memory each worker needs.
"""

from .cluster import Cluster, SchedulerUnreachableError, WorkerLostError, connect
from .run import factorize_distributed
from .sizing import rank_guess, worker_bytes
from .store import remove_folder as remove_checkpoint

__all__ = ["Cluster", "SchedulerUnreachableError", "WorkerLostError", "connect", "factorize_distributed", "rank_guess",
           "remove_checkpoint", "worker_bytes"]
