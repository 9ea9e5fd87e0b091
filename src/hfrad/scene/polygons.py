"""Planar polygons to triangles, and the turn of Z-up building models to hfrad's y-up frame.

Radiance ``polygon`` primitives may be concave (an L-shaped floor) and may
carry holes joined to the outline by a seam (two coincident edges), so a fan
from the first corner is not enough: :func:`triangulate_polygon` clips ears
in the polygon's own plane. Building models (Radiance, IFC) are Z-up;
:func:`z_up_to_y_up` turns them into hfrad's y-up frame.
"""

from __future__ import annotations

import numpy as np

__all__ = ["triangulate_polygon", "z_up_to_y_up", "Z_UP_NOTE"]

#: What the readers of Z-up formats say they did (``hfrad info`` lists it).
Z_UP_NOTE = "turned from Z-up to hfrad's y-up frame: (x, y, z) -> (x, z, -y)"


def z_up_to_y_up(vertices: np.ndarray) -> np.ndarray:
    """(v, 3) float: Z-up coordinates turned to y-up, ``(x, y, z) -> (x, z, -y)``.

    A rotation by -90 degrees about x (determinant +1), so faces keep their
    winding and their front side; heights (z) become y, plans (x, y) become (x, -z).
    """
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    return np.stack([v[:, 0], v[:, 2], -v[:, 1]], axis=1)


def _newell_normal(p: np.ndarray) -> np.ndarray:
    """Area vector x 2 of a closed polygon (k, 3) (Newell's method: exact for planar polygons)."""
    q = np.roll(p, -1, axis=0)
    return np.array([((p[:, 1] - q[:, 1]) * (p[:, 2] + q[:, 2])).sum(),
                     ((p[:, 2] - q[:, 2]) * (p[:, 0] + q[:, 0])).sum(),
                     ((p[:, 0] - q[:, 0]) * (p[:, 1] + q[:, 1])).sum()])


def _is_convex(uv: np.ndarray) -> bool:
    d = np.roll(uv, -1, axis=0) - uv
    cross = d[:, 0] * np.roll(d, -1, axis=0)[:, 1] - d[:, 1] * np.roll(d, -1, axis=0)[:, 0]
    return bool((cross >= 0).all())


def _cross2(o: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    return float((a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]))


def _ear_clip(uv: np.ndarray) -> list[tuple[int, int, int]]:
    """Triangles (indices into uv) of a counter-clockwise simple polygon (k, 2), O(k^2) per ear."""
    idx = list(range(len(uv)))
    out: list[tuple[int, int, int]] = []
    scale = float(np.abs(uv).max()) or 1.0
    tol = 1e-12 * scale * scale
    guard = 0
    while len(idx) > 3 and guard < 4 * len(uv) ** 2:
        guard += 1
        for k in range(len(idx)):
            a, b, c = idx[k - 1], idx[k], idx[(k + 1) % len(idx)]
            if _cross2(uv[a], uv[b], uv[c]) <= tol:
                continue  # reflex or flat corner: not an ear
            others = [j for j in idx if j not in (a, b, c)]
            inside = False
            for j in others:  # an ear holds no other corner (points on its edges count: seams)
                p = uv[j]
                if (_cross2(uv[a], uv[b], p) >= -tol and _cross2(uv[b], uv[c], p) >= -tol
                        and _cross2(uv[c], uv[a], p) >= -tol) and not any(np.array_equal(p, uv[q]) for q in (a, b, c)):
                    inside = True
                    break
            if not inside:
                out.append((a, b, c))
                idx.pop(k)
                break
        else:  # no ear (self-intersecting or numerically flat): fan what is left
            break
    out += [(idx[0], idx[k], idx[k + 1]) for k in range(1, len(idx) - 1)]
    return out


def triangulate_polygon(points: np.ndarray) -> np.ndarray:
    """Triangles of a planar polygon, counter-clockwise seen from its front like the polygon.

    Parameters
    ----------
    points : (k, 3) float
        The corners in order (the last joins the first); the front side is
        the one they turn counter-clockwise around (Radiance and OBJ agree).

    Returns
    -------
    (k - 2, 3) int
        Corner indices. Convex polygons are fanned from corner 0; concave ones
        (and outlines with holes joined by a seam) are cut by ear clipping in
        the polygon's plane. A polygon of zero area gives the fan (its
        triangles are degenerate and the loader drops them, counted).
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    k = len(p)
    fan = np.array([(0, j, j + 1) for j in range(1, k - 1)], dtype=np.int64).reshape(-1, 3)
    if k <= 3:
        return fan
    n = _newell_normal(p)
    if not np.any(n):
        return fan
    axis = int(np.argmax(np.abs(n)))  # drop the dominant axis: a projection that keeps the polygon simple
    uv = p[:, [(axis + 1) % 3, (axis + 2) % 3]]
    if n[axis] < 0:
        uv = uv[:, ::-1]  # seen from the front, counter-clockwise
    if _is_convex(uv):
        return fan
    return np.array(_ear_clip(uv), dtype=np.int64).reshape(-1, 3)
