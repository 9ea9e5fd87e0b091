"""Primary rays against the patch mesh, seeing only the front of each patch.

The rays are cast on the detail triangles (``scene.vertices``/``faces``,
not the occluder mesh), so the face id of a hit is a triangle id; its patch is
``scene.patch_of_triangle[face]`` (the same id unless the scene is clustered). Embree
does not cull back faces, so a hit on a patch whose normal points away from the
ray is treated as transparent: the ray is re-cast from just past it, until it
hits a front face or escapes. This is what lets a camera outside the closed
Cornell box look in through the back of its front wall, the usual convention
for one-sided radiosity patches (their back side has no radiosity).
"""

from __future__ import annotations

import numpy as np

from ..formfactors.raycast import RayCaster
from ..resources import spare_cores_now

#: Most back faces a ray may pass through before it is given up as escaped.
MAX_LAYERS = 64


def patch_caster(scene, threads: int | None = None) -> RayCaster:
    """A :class:`RayCaster` over the scene's detail triangles (face id = triangle id); ``threads``
    by default the cores other processes leave free (:func:`~hfrad.resources.spare_cores_now`:
    threads that compete for busy cores cost more than they add; 512 x 512 Sponza at load 12:
    4.3 s with one thread, 7.2 s with two)."""
    return RayCaster(scene.vertices, scene.faces, threads=spare_cores_now() if threads is None else threads)


def trace_front(scene, origins: np.ndarray, directions: np.ndarray, *,
                caster: RayCaster | None = None, max_layers: int = MAX_LAYERS
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """First front-facing patch along each ray.

    Parameters
    ----------
    scene : Scene
    origins, directions : (r, 3) float
        Directions need not be unit; distances are in units of their length.
    caster : RayCaster, optional
        Built with :func:`patch_caster`; reuse it across frames.
    max_layers : int
        Back faces a ray may pass through.

    Returns
    -------
    face : (r,) int, triangle id (row of ``scene.faces``) or -1 where the ray escapes
    distance : (r,) float, ray parameter of the hit (inf where none)
    uv : (r, 2) float, barycentric weights of corners 1 and 2 of the triangle
    """
    caster = caster or patch_caster(scene)
    origins = np.asarray(origins, dtype=np.float64)
    directions = np.asarray(directions, dtype=np.float64)
    r = len(origins)
    face = np.full(r, -1, np.int64)
    dist = np.full(r, np.inf)
    uv = np.zeros((r, 2))
    if r == 0 or scene.n_triangles == 0:
        return face, dist, uv
    # Step past a back face by a length that float32 (Embree's precision) resolves in the caster's
    # frame, centred on the scene, yet far below any patch size: relative to the scene's size and the
    # camera's distance from its centre, not to the coordinates (at 1e6 m off the origin a step of
    # 1e-5 of them crossed the whole room).
    lo, hi = scene.bounds
    centre = 0.5 * (lo + hi)
    size = max(float(np.linalg.norm(hi - lo)), float(np.abs(origins - centre).max()))
    step = 1e-5 * (size or 1.0)
    normals = scene.triangle_normals
    travelled = np.zeros(r)
    active = np.arange(r)
    for _ in range(max_layers):
        if not len(active):
            break
        d = directions[active]
        o = origins[active] + travelled[active, None] * d
        f, t, bary = caster.intersect(o, d)
        hit = f >= 0
        front = np.zeros(len(active), bool)
        front[hit] = np.einsum("ij,ij->i", normals[f[hit]], d[hit]) < 0
        done = active[front]
        face[done] = f[front]
        dist[done] = travelled[done] + t[front]
        uv[done] = bary[front]
        back = hit & ~front
        travelled[active[back]] += t[back] + step
        active = active[back]
    return face, dist, uv


# Sub-pixel offsets tried for a background pixel next to covered ones.
_JITTER = ((0.25, 0.25), (-0.25, -0.25), (0.25, -0.25), (-0.25, 0.25))


def trace_camera(scene, camera, width: int, height: int, *, caster: RayCaster | None = None,
                 offset: tuple[float, float] = (0.5, 0.5)) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Primary hits of a camera's pixels, without cracks.

    A ray through the exact edge between two patches (e.g. along the corner
    line of two walls seen edge-on) can slip between them in floating point.
    Every background pixel with a covered neighbour is therefore re-cast at up
    to four sub-pixel positions and takes the first hit: this closes one-pixel
    cracks and only ever moves a sample within its own pixel.

    Parameters
    ----------
    offset : (2,) float in (0, 1), pixels
        Where in each pixel the ray passes (column, row); the centre by default,
        other positions for the sub-pixel samples of an anti-aliased picture.

    Returns
    -------
    face : (height, width) int, -1 for background
    distance : (height, width) float
    uv : (height, width, 2) float
    """
    caster = caster or patch_caster(scene)
    col, row = np.meshgrid(np.arange(width) + offset[0], np.arange(height) + offset[1])
    origins, directions = camera.rays_at(col.ravel(), row.ravel(), width, height)
    face, dist, uv = trace_front(scene, origins, directions, caster=caster)
    face, dist, uv = face.reshape(height, width), dist.reshape(height, width), uv.reshape(height, width, 2)
    hit = face >= 0
    near = np.zeros_like(hit)
    pad = np.pad(hit, 1)
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            near |= pad[1 + di:1 + di + height, 1 + dj:1 + dj + width]
    rows, cols = np.nonzero(near & ~hit)
    for dc, dr in _JITTER:
        if not len(rows):
            break
        o, d = camera.rays_at(cols + offset[0] + dc, rows + offset[1] + dr, width, height)
        f, t, b = trace_front(scene, o, d, caster=caster)
        got = f >= 0
        face[rows[got], cols[got]] = f[got]
        dist[rows[got], cols[got]] = t[got]
        uv[rows[got], cols[got]] = b[got]
        rows, cols = rows[~got], cols[~got]
    return face, dist, uv
