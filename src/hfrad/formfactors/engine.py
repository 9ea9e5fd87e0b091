"""The engine that computes sub-blocks of F in this process: kernel and visibility, pipelined.

:class:`FormFactorEngine` is what :mod:`hfrad.formfactors.blocks` streams
with and what each worker of :mod:`hfrad.formfactors.parallel` (and of the
Dask backend) runs, so it sits below both and imports neither.
"""

from __future__ import annotations

import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from typing import Iterator

import numpy as np

from .budget import RayBudget
from .clustered import kernel_for
from .kernel import NEAR, TOLERANCE
from .mirror import block_request, computed_rows, full_height
from .visibility import DEFAULT_SAMPLES, Visibility

__all__ = ["FormFactorEngine"]

#: Ray batches queued for the Embree thread at once (each holds up to RAY_BATCH rays).
_IN_FLIGHT = 2


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
    :meth:`iter_blocks` overlaps the two halves of the work: Embree casts the
    rays of one batch in a worker thread (packets from numba, no GIL held: see
    :mod:`hfrad.formfactors.raycast`) while the numba kernel computes the next
    block, so the ray casting is mostly hidden behind the kernel.
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

    def block(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """(len(rows), len(cols)) float64 F[rows][:, cols] with visibility."""
        F = self._kernel(rows, cols)
        if self.visibility is not None:
            self.visibility.apply(F, rows, cols)
        return F

    def iter_blocks(self, rows: np.ndarray, col_sets, *, lend: bool = False) -> Iterator[np.ndarray]:
        """F[rows][:, cols] for each ``cols`` of ``col_sets``, in order, pipelined (see Notes).

        An item of ``col_sets`` may be ``(cols, skip)`` with ``skip`` a slice of
        positions in ``rows`` that are not computed (left unspecified in the
        block: the caller fills them, see :mod:`hfrad.formfactors.mirror`).
        ``lend`` is accepted for the process engine's interface: blocks here are
        always fresh arrays.
        """
        if self.visibility is None:
            for item in col_sets:
                cols, skip = block_request(item)
                yield full_height(self._kernel(computed_rows(rows, skip), cols), skip, len(rows))
            return
        if self._executor is None:
            self._executor = ThreadPoolExecutor(1, thread_name_prefix="hfrad-embree")
        vis = self.visibility
        inflight: deque = deque()  # [F, job, future, entry] of the batches Embree is casting, in order
        ready: deque = deque()  # [F, jobs still in flight, skip] in block order

        def submit(F, job, entry):
            entry[1] += 1
            inflight.append((F, job, self._executor.submit(vis.cast, job), entry))

        def drain():
            F, job, fut, entry = inflight.popleft()
            for more in vis.finish(F, job, fut.result()):  # second-round rays go to Embree too
                submit(F, more, entry)
            entry[1] -= 1

        def done(entry):
            return full_height(entry[0], entry[2], len(rows))

        try:
            for item in col_sets:
                cols, skip = block_request(item)
                part = computed_rows(rows, skip)
                F = self._kernel(part, cols)  # runs while Embree works on earlier batches
                entry = [F, 0, skip]
                ready.append(entry)
                for job in vis.jobs(F, part, cols):
                    while len(inflight) >= _IN_FLIGHT:
                        drain()
                    submit(F, job, entry)
                # every block before the newest whose rays are all cast can go
                while len(ready) > 1 and ready[0][1] == 0:
                    yield done(ready.popleft())
            while inflight:
                drain()
            while ready:
                yield done(ready.popleft())
        finally:
            for _, _, fut, _ in inflight:  # consumer stopped early: let Embree finish before reuse
                fut.result()

    def close(self) -> None:
        if self._executor is not None:
            self._executor.shutdown()
            self._executor = None
        if self.visibility is not None:
            self.visibility.close()
