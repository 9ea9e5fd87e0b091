"""The precomputation on a Dask cluster (``hfrad precompute --scheduler/--workers``).

Sits beside :mod:`hfrad.pipeline`: it uses scene/, formfactors/, factorize/ and
solve/, and only the CLI and the top-level API import it::

    from hfrad.distributed import connect, factorize_distributed
    with connect("tcp://scheduler:8786") as cluster:     # or connect(workers=4)
        print(cluster.dashboard)
        fac = factorize_distributed(scene, scheduler=cluster, eps=0.02)

See docs/cluster.md for running it on a real cluster and the memory each worker needs.
"""

from .cluster import Cluster, SchedulerUnreachableError, WorkerLostError, connect
from .run import factorize_distributed
from .sizing import rank_guess, worker_bytes

__all__ = ["Cluster", "SchedulerUnreachableError", "WorkerLostError", "connect", "factorize_distributed", "rank_guess",
           "worker_bytes"]
