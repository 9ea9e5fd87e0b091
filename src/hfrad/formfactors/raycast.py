"""Ray casting with Intel Embree (through ``embreex``), batched.

``embreex``'s ``run`` holds the GIL for most of a batch, so splitting a batch
across threads gains little; the form-factor
engine gets its parallelism by overlapping Embree with the numba kernel,
which does release the GIL. ``embreex`` is imported at first use so that a missing
install gives a clear message with the pip command, not an import failure of
hfrad itself.

Embree works in float32 and silently misses every hit when coordinates are
very large or very small (a 2-unit triangle is hit up to coordinates of
1e12 and missed from 1e13 on, and missed below 1e-20), and
float32 cannot resolve a 1 m room 1e13 m from the origin at all. So the
caster works in its own frame: the triangles are moved to the centre of their
bounding box and divided by its size (metres per unit) before they reach
Embree; the ray origins and lengths of each query are mapped the same way in
float64, and the distances of hits mapped back. Directions are unchanged.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np

_MIN_CHUNK = 65536  # below this, thread hand-off costs more than it saves


def _embree():
    try:
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise ImportError("ray casting needs Intel Embree's Python binding: "
                          "pip install embreex") from exc
    return rtcore_scene, TriangleMesh


def default_threads() -> int:
    """Threads for ray casting: the cores this process may use."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - non-Linux
        return max(1, os.cpu_count() or 1)


class RayCaster:
    """An Embree scene over triangles, answering batched ray queries.

    Parameters
    ----------
    vertices : (v, 3) float
    faces : (m, 3) int
    threads : int, optional
        Worker threads per batch; default: all cores available.
    normalise : bool
        Cast in the triangles' own frame (centred on their bounding box, in
        units of its size; module docstring), whatever the scale and offset
        of the coordinates. False for a caller whose coordinates already are
        centred and of size about 1 (the visibility engine): no per-query mapping.

    Attributes
    ----------
    centre : (3,) float, unit : float
        The frame: Embree sees ``(x - centre) / unit``.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, threads: int | None = None, *,
                 normalise: bool = True) -> None:
        rtcore_scene, TriangleMesh = _embree()
        tri = np.asarray(vertices, dtype=np.float64)[np.asarray(faces, dtype=np.int64)].reshape(-1, 3, 3)
        self.centre, self.unit = np.zeros(3), 1.0
        if normalise and len(tri):
            lo, hi = tri.min(axis=(0, 1)), tri.max(axis=(0, 1))
            size = float((hi - lo).max())
            self.centre, self.unit = 0.5 * (lo + hi), (size if size > 0 else 1.0)
        self._mapped = bool(self.centre.any() or self.unit != 1.0)
        self.triangles = np.ascontiguousarray((tri - self.centre) / self.unit if self._mapped else tri,
                                              dtype=np.float32)
        self._scene = rtcore_scene.EmbreeScene()
        if len(self.triangles):
            TriangleMesh(self._scene, self.triangles)
        self.threads = threads or default_threads()
        self._pool = ThreadPoolExecutor(self.threads) if self.threads > 1 else None

    def _chunks(self, n: int) -> list[slice]:
        if self._pool is None or n < 2 * _MIN_CHUNK:
            return [slice(0, n)]
        step = max(_MIN_CHUNK, -(-n // (4 * self.threads)))
        return [slice(s, min(n, s + step)) for s in range(0, n, step)]

    def _map(self, fn, n: int) -> list:
        chunks = self._chunks(n)
        if len(chunks) == 1:
            return [fn(chunks[0])]
        return list(self._pool.map(fn, chunks))

    def occluded(self, origins: np.ndarray, directions: np.ndarray, distances: np.ndarray) -> np.ndarray:
        """(r,) bool: whether something blocks each ray before its distance.

        Parameters
        ----------
        origins, directions : (r, 3) float
            Directions of unit length; the caller offsets origins off their surfaces.
        distances : (r,) float
            Ray length to test (the segment's end).

        Contiguous float32 arrays are passed to Embree without a copy.
        """
        o = self._in_frame(origins)
        if self._mapped:
            distances = np.asarray(distances, np.float64) / self.unit
        d = np.ascontiguousarray(directions, dtype=np.float32)
        t = np.ascontiguousarray(distances, dtype=np.float32)
        if not len(self.triangles) or not len(o):
            return np.zeros(len(o), dtype=bool)
        if self._pool is None:
            return self._scene.run(o, d, query="OCCLUDED", dists=t) >= 0
        out = np.empty(len(o), dtype=bool)

        def run(s: slice) -> None:
            out[s] = self._scene.run(o[s], d[s], query="OCCLUDED", dists=t[s]) >= 0

        self._map(run, len(o))
        return out

    def intersect(self, origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """First hits of rays.

        Returns
        -------
        face : (r,) int, -1 where the ray escapes
        distance : (r,) float, ray parameter of the hit (inf where none)
        barycentric : (r, 2) float, (u, v) weights of corners 1 and 2 of the hit face
        """
        origins = self._in_frame(origins)
        directions = np.ascontiguousarray(directions, dtype=np.float32)
        r = len(origins)
        face = np.full(r, -1, np.int64)
        dist = np.full(r, np.inf)
        uv = np.zeros((r, 2))
        if not len(self.triangles) or not r:
            return face, dist, uv

        def run(s: slice) -> None:
            res = self._scene.run(origins[s], directions[s], output=1)
            prim = res["primID"].astype(np.int64)
            hit = prim >= 0
            face[s] = np.where(hit, prim, -1)
            dist[s] = np.where(hit, res["tfar"], np.inf)
            uv[s] = np.stack([res["u"], res["v"]], axis=1)

        self._map(run, r)
        if self._mapped:
            dist *= self.unit  # inf stays inf
        return face, dist, uv

    def _in_frame(self, origins) -> np.ndarray:
        """Ray origins as Embree sees them: mapped into the caster's frame in float64, then float32."""
        if self._mapped:
            origins = (np.asarray(origins, np.float64) - self.centre) / self.unit
        return np.ascontiguousarray(origins, dtype=np.float32)

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None

    def __del__(self) -> None:  # pragma: no cover - interpreter shutdown order varies
        try:
            self.close()
        except Exception:
            pass
