"""Cutting input faces into patches.

:func:`subdivide` makes conforming, well-shaped patches
(:mod:`hfrad.scene.conform`): no T-junctions, minimum angle about 30 degrees,
no edge longer than ``max_edge``. :func:`split_faces` (used by clustering)
splits each triangle uniformly into m x m congruent sub-triangles.
New vertices are shared between neighbouring patches (merged by position), so
rendering can interpolate radiosity smoothly. Both conserve area (up to rounding).
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import InputError, SceneError
from .conform import conforming_subdivide
from .scene import Scene
from .weld import first_index, weld_points


#: Memory budgeted per patch for cutting faces into patches and holding the result, bytes. A cut
#: scene of n one-triangle patches stores 108 n B (faces 24, material, group and parent 8 each,
#: reflectance and emission 24 each, about half a vertex 12) and caches up to 224 n B of geometry
#: (corners 72, cross products, area vectors, normals, triangle normals and centroids 24 each,
#: areas, triangle areas, non-flatness and the patch map 8 each): 332 n B in all. The budget is
#: three times that, for the cut's temporaries (points and their integer keys while welding) and
#: the copies later stages make.
MESH_BYTES_PER_PATCH = 1024

#: Area of an equilateral triangle of unit edge, sqrt(3)/4: the largest triangle with no edge over 1.
EQUILATERAL_AREA = math.sqrt(3) / 4

#: First guess of a conforming mesh's mean patch area, as a fraction of EQUILATERAL_AREA h^2 (its
#: patches are near-equilateral, minimum angle about 30 degrees, and edges up to h long); the
#: count is then met by scaling h by sqrt(count / patches).
MESH_FILL = 0.6


def min_patches_for_edge(total_area: float, max_edge: float) -> float:
    """Fewest triangles of edges at most ``max_edge`` that cover ``total_area``: ``A / (sqrt(3)/4 h^2)``."""
    return float(total_area) / (EQUILATERAL_AREA * float(max_edge) ** 2)


def longest_edges(tri: np.ndarray) -> np.ndarray:
    """(n,) metres: the longest edge of each of the (n, 3, 3) triangles ``tri``."""
    e = np.stack([tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 1], tri[:, 0] - tri[:, 2]], axis=1)
    return np.linalg.norm(e, axis=2).max(axis=1)


def splits_for_edge(scene: Scene, max_edge: float) -> np.ndarray:
    """(n,) int: splits per edge so that no sub-triangle edge exceeds ``max_edge``."""
    return np.maximum(1, np.ceil(longest_edges(scene.triangles) / max_edge - 1e-9)).astype(np.int64)


def max_edge_for_count(scene: Scene, patches: int) -> float:
    """Longest-edge limit giving approximately ``patches`` patches (bisection)."""
    longest = longest_edges(scene.triangles)
    if patches <= len(longest):
        return float(longest.max())
    lo, hi = float(longest.max()) / math.sqrt(patches) / 100, float(longest.max())
    for _ in range(60):
        mid = math.sqrt(lo * hi)
        count = int((np.maximum(1, np.ceil(longest / mid - 1e-9)) ** 2).sum())
        if count > patches:
            lo = mid
        else:
            hi = mid
    # choose whichever bracket is closer to the requested count
    def count(L: float) -> int:
        return int((np.maximum(1, np.ceil(longest / L - 1e-9)) ** 2).sum())
    return lo if abs(count(lo) - patches) < abs(count(hi) - patches) else hi


def _grid_pattern(m: int) -> tuple[np.ndarray, np.ndarray]:
    """Barycentric grid of a triangle split m x m.

    Returns the (p, 2) integer (i, j) lattice coordinates (weights i/m on corner 1,
    j/m on corner 2) and the (m*m, 3) sub-triangles as indices into them.
    """
    ij = np.array([(i, j) for j in range(m + 1) for i in range(m + 1 - j)], dtype=np.int64)
    index = {tuple(p): k for k, p in enumerate(ij)}
    tris = []
    for j in range(m):
        for i in range(m - j):
            tris.append((index[i, j], index[i + 1, j], index[i, j + 1]))
            if i + j + 2 <= m:
                tris.append((index[i + 1, j], index[i + 1, j + 1], index[i, j + 1]))
    return ij, np.array(tris, dtype=np.int64)


def check_cut_options(max_edge, patches, *, one_required: bool = False) -> None:
    """Check a request to cut (or cluster) a scene into patches: a longest edge or a patch count.

    Parameters
    ----------
    max_edge : float, metres, or None
        Must be a finite length > 0.
    patches : int or None
        Must be a whole number >= 1 (an integral float such as ``1e4`` passes).
    one_required : bool
        Refuse neither being given, too (else neither means "leave the faces as they are").

    Raises
    ------
    InputError
        Both given (or neither, with ``one_required``), or a value out of range.
    """
    if max_edge is not None and patches is not None:
        raise InputError(f"give either max_edge or patches, not both (got max_edge={max_edge!r}, "
                         f"patches={patches!r})")
    if one_required and max_edge is None and patches is None:
        raise InputError("give either max_edge (a longest patch edge, metres) or patches (a patch count)")
    if patches is not None and not (_is_real(patches) and float(patches).is_integer() and patches >= 1):
        raise InputError(f"patches must be a whole number >= 1, got {patches!r}")
    if max_edge is not None and not (_is_real(max_edge) and max_edge > 0):
        raise InputError(f"max_edge must be a positive finite length in metres, got {max_edge!r}")


def _is_real(x) -> bool:
    """A finite real number (int or float, numpy's too; not a bool, a string or None)."""
    return isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, bool) and math.isfinite(x)


def subdivide(scene: Scene, *, max_edge: float | None = None, patches: int | None = None) -> Scene:
    """Split the scene's faces into patches no longer than ``max_edge``.

    Parameters
    ----------
    scene : Scene
    max_edge : float, metres, optional
        Longest allowed patch edge.
    patches : int, optional
        Target patch count instead of ``max_edge`` (met approximately).

    Returns
    -------
    Scene
        Same materials and groups; ``parent`` maps each patch to its input face;
        the input faces are kept as the occluder mesh for ray casting.

    Raises
    ------
    InputError
        See :func:`check_cut_options`.
    """
    check_cut_options(max_edge, patches)
    if patches is not None:
        max_edge = max_edge_for_count(scene, patches)
    if max_edge is None:
        return scene
    if patches is not None and patches <= scene.n_patches:
        return scene
    return conforming_subdivide(scene, max_edge) if patches is None else _mesh_for_count(scene, patches)


def _mesh_for_count(scene: Scene, patches: int) -> Scene:
    """Conforming patches, about ``patches`` of them (a few meshings, h scaled by sqrt(count ratio))."""
    # an equilateral patch of edge h has area sqrt(3)/4 h^2; MESH_FILL of that is a first guess at a
    # conforming mesh's mean patch area, corrected by the loop
    h = math.sqrt(scene.total_area / patches / (MESH_FILL * EQUILATERAL_AREA))
    best = None
    for _ in range(6):
        mesh = conforming_subdivide(scene, h)
        if best is None or abs(mesh.n_patches - patches) < abs(best.n_patches - patches):
            best = mesh
        if abs(mesh.n_patches - patches) <= 0.03 * patches:
            break
        h *= math.sqrt(mesh.n_patches / patches)
    return best


def split_faces(scene: Scene, splits: np.ndarray) -> tuple[Scene, np.ndarray]:
    """Split face f of an unclustered scene into ``splits[f]**2`` congruent triangles.

    Returns the new scene (patches of one face kept together, in face order)
    and ``owner`` (t,): the index in ``scene.faces`` each new patch was cut from.
    """
    tri = scene.triangles
    points, faces, owner = [], [], []
    offset = 0
    for m in np.unique(splits):
        sel = np.flatnonzero(splits == m)
        ij, sub = _grid_pattern(int(m))
        w1, w2 = ij[:, 0] / m, ij[:, 1] / m
        w0 = 1.0 - w1 - w2
        t = tri[sel]  # (s, 3, 3)
        pts = (w0[None, :, None] * t[:, None, 0] + w1[None, :, None] * t[:, None, 1]
               + w2[None, :, None] * t[:, None, 2])  # (s, p, 3)
        base = offset + np.arange(len(sel))[:, None, None] * len(ij)
        faces.append((base + sub[None]).reshape(-1, 3))
        owner.append(np.repeat(sel, len(sub)))
        points.append(pts.reshape(-1, 3))
        offset += len(sel) * len(ij)
    points_all = np.concatenate(points)
    faces_all = np.concatenate(faces)
    owner_all = np.concatenate(owner)
    ids = weld_points(points_all, bounds=scene.bounds)  # neighbouring patches share their corners
    first = first_index(ids, int(ids.max(initial=-1)) + 1)  # where each vertex first occurs
    vertices, faces_all = points_all[first], ids[faces_all]
    order = np.argsort(owner_all, kind="stable")  # keep patches of one face together
    faces_all, owner_all = faces_all[order], owner_all[order]
    return scene.remeshed(vertices, faces_all, owner_all), owner_all


def drop_degenerate(scene: Scene, *, rel_area: float = 1e-12) -> Scene:
    """Remove zero-area (or NaN-area) patches, with a warning that counts them."""
    tol = rel_area * max(float(np.nanmax(scene.areas, initial=0.0)), 1e-300)
    keep = scene.areas > tol
    dropped = int((~keep).sum())
    if dropped == 0:
        return scene
    if not keep.any():
        raise SceneError(f"{scene.name}: every face is degenerate (zero area)")
    first = np.flatnonzero(~keep)[:5].tolist()
    note = f"dropped {dropped} degenerate (zero-area) faces, e.g. faces {first}"
    return scene.remeshed(scene.vertices, scene.faces[keep], np.flatnonzero(keep), notes=(note,))
