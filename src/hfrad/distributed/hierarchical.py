"""``far_field="hierarchical"`` on a Dask cluster: the workers build the H-matrix's blocks.

One precompute, two backends: the H-matrix build (:mod:`hfrad.formfactors.hmatrix`), nearly all
of whose time is rays and kernel evaluations, is split into parts of its node pairs
(:func:`~hfrad.formfactors.hmatrix.split_into_parts`), each built by a worker with the same
builder as in this process (:func:`~hfrad.formfactors.hmatrix.build_part`); a block depends on
its own pair alone, so the joined H-matrix holds the blocks of the in-process build, value for
value. The client then does what the in-process path does after its build
(:func:`~hfrad.precompute.hierarchical.factorize_hmatrix`: the factors from products, the pass
statistics, the certificate's exact rows, the solver's set-up), holding the whole H-matrix.
"""

from __future__ import annotations

import dataclasses
import time
import uuid
from pathlib import Path

from ..formfactors.hmatrix import (FormFactorHMatrix, HMatrixPairs, build_part, hmatrix_pairs, join_parts,
                                   split_into_parts)
from ..formfactors.parallel import cached_engine
from ..precompute.assemble import PrecomputePlan
from ..precompute.backends import Checkpoint, DaskBackend
from ..precompute.hierarchical import run_hierarchical
from ..progress import ProgressCallback, report
from ..solve.woodbury import HFactorization
from .connection import Cluster, connect
from .run import make_job
from .store import remove_folder
from ..resources import numba_threads
from .tasks import Job

__all__ = ["factorize_hierarchical_distributed", "hmatrix_part_task", "PARTS_PER_WORKER"]

#: The H-matrix checkpoint's file in a Dask run's checkpoint folder.
HMATRIX_FILE = "hmatrix.h5"
#: Parts of the build per worker: more parts than workers even out parts of unequal cost (Dask
#: hands the next part to the first worker free), at one Embree scene build per worker, not per part.
PARTS_PER_WORKER = 4


def hmatrix_part_task(job: Job, pairs: HMatrixPairs) -> tuple:
    """One part of the build on a worker: ``(BlockList, counters)`` of ``pairs``
    (:func:`~hfrad.formfactors.hmatrix.build_part`), with the worker's engine (built once a process)."""
    plan = job.options
    engine = cached_engine(job.scene, job.samples, job.ray_budget if job.samples else None)
    with numba_threads(job.task_threads):
        return build_part(job.scene, engine, pairs, plan.hmatrix_options)


def factorize_hierarchical_distributed(scene, plan: PrecomputePlan, backend: DaskBackend, *,
                                       checkpoint: Checkpoint | None = None, progress: ProgressCallback = None,
                                       status=None) -> HFactorization:
    """:func:`hfrad.precompute.hierarchical.factorize_hierarchical` with the H-matrix built on ``backend``'s
    cluster (see the module docstring); the same checkpoint (the built H-matrix, on the client).

    Parameters
    ----------
    scene : Scene
    plan : PrecomputePlan
        With ``far_field="hierarchical"``.
    backend : DaskBackend
        ``scheduler`` or ``workers``, ``task_threads``, ``connect_timeout`` as for the column pass.
    checkpoint : Checkpoint, optional
        Its ``path`` names a folder (as a Dask run's does) reachable from the client: the built
        H-matrix is saved there as ``HMATRIX_FILE`` (when the build took at least the interval) and a
        rerun loads it; the folder is deleted on completion unless ``keep``.
    progress, status
        As in :func:`~hfrad.precompute.hierarchical.factorize_hierarchical`; ``progress`` counts the
        build's parts, then the basis columns.

    Returns
    -------
    HFactorization
        ``params["backend"]`` is "dask" and ``params["workers"]`` the cluster's workers;
        ``lowrank.info["hierarchical"]`` has ``parts`` and ``time_build_wall`` beside the build's
        counters (its ``time_*`` are then seconds of work summed over the parts).

    Raises
    ------
    MemoryLimitError
        As the in-process path: the client holds the H-matrix and runs the rest.
    SchedulerUnreachableError
        The scheduler cannot be reached.
    """
    folder = None
    if checkpoint is not None:      # a Dask run's checkpoint names a folder: here it holds the H-matrix's file
        folder = Path(checkpoint.path)
        checkpoint = dataclasses.replace(checkpoint, path=folder / HMATRIX_FILE)
    record = {"backend": "dask", "workers": 0}      # 0 when the H-matrix was resumed

    def build(engine) -> FormFactorHMatrix:
        if folder is not None:      # after the memory check: a refused run leaves no folder behind
            folder.mkdir(parents=True, exist_ok=True)
        if isinstance(backend.scheduler, Cluster):
            hm, record["workers"] = _build_on(backend.scheduler, scene, plan, backend.task_threads, progress)
        else:
            with connect(backend.scheduler, workers=backend.workers, timeout=backend.connect_timeout) as cluster:
                hm, record["workers"] = _build_on(cluster, scene, plan, backend.task_threads, progress)
        return hm

    return run_hierarchical(scene, plan, build, progress, status, checkpoint=checkpoint, backend=record,
                            remove_checkpoint=None if folder is None else (lambda: remove_folder(folder)))


def _build_on(cluster: Cluster, scene, plan: PrecomputePlan, task_threads, progress) -> tuple[FormFactorHMatrix, int]:
    """The H-matrix built as ``PARTS_PER_WORKER`` parts a worker on ``cluster``; (hm, workers)."""
    from distributed import as_completed

    client = cluster.client
    t0 = time.perf_counter()
    options = plan.hmatrix_options
    pairs = hmatrix_pairs(scene, options)
    parts = split_into_parts(pairs, PARTS_PER_WORKER * max(1, cluster.n_workers))
    token = uuid.uuid4().hex[:12]
    job = make_job(scene, plan, task_threads if task_threads is not None else cluster.task_threads, token)
    [job_future] = client.scatter([job], broadcast=True, hash=False)     # the scene travels once a worker
    futures = {client.submit(hmatrix_part_task, job_future, part, key=f"hfrad-hpart-{k}-{token}", pure=False): k
               for k, part in enumerate(parts)}
    built: dict[int, tuple] = {}
    report(progress, 0, len(parts))
    for future in as_completed(futures):
        built[futures[future]] = future.result()
        future.release()
        report(progress, len(built), len(parts))
    blocks = [built[k][0] for k in range(len(parts))]
    infos = [built[k][1] for k in range(len(parts))]
    del built
    hm = join_parts(pairs, blocks, infos, options, time.perf_counter() - t0)
    hm.info.update({"parts": len(parts), "time_build_wall": time.perf_counter() - t0})
    return hm, cluster.n_workers
