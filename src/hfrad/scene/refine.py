"""Refining patches where the radiosity changes fast, keeping the mesh conforming.

:func:`marks_from_radiosity` marks the two patches on either side of every
edge across which a first (coarse) solution's luminance jumps by more than a
threshold: contact lines, shadow boundaries, the rim of a light's pool.
:func:`refine_patches` then splits the marked patches by red-green
refinement (Bank, Sherman & Weiser 1983): a marked patch is cut into four
congruent triangles through its edge midpoints ("red"); a neighbour left with two or
three cut edges is made red too, a neighbour with one cut edge is bisected
from the opposite corner ("green"), so no T-junction is created. One call is
one level; red children keep their parent's angles, green halves at least
half of them.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError, SceneError
from .scene import Scene
from .weld import weld

#: Rec. 709 luminance weights of RGB radiosity.
LUMINANCE = np.array([0.2126, 0.7152, 0.0722])


def _edges(F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unique undirected edges (e, 2) and, per triangle, its three edge ids (t, 3) (edge k = corners k, k+1)."""
    e = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    edges, inverse = np.unique(e, axis=0, return_inverse=True)
    return edges, inverse.reshape(3, -1).T


def marks_from_radiosity(scene: Scene, radiosity: np.ndarray, threshold: float) -> np.ndarray:
    """(n,) bool: patches on an edge across which luminance changes by more than ``threshold``.

    Parameters
    ----------
    scene : Scene
        Unclustered (one triangle per patch).
    radiosity : (n,) or (n, 3) float, W/m^2
        A first solution on these patches.
    threshold : float > 0
        Relative jump |L_p - L_q| / max(L_p, L_q) that marks both patches p, q.
        Edges of emitters are ignored (a light's outline always jumps).
    """
    if not threshold > 0:
        raise InputError(f"refine threshold must be > 0, got {threshold}")
    B = np.asarray(radiosity, dtype=np.float64)
    L = B @ LUMINANCE if B.ndim == 2 else B
    if L.shape != (scene.n_patches,):
        raise InputError(f"radiosity has {L.shape[0]} rows for {scene.n_patches} patches")
    F = weld(scene.vertices, scene.faces)  # patches of two faces share corners
    _, edge_of = _edges(F)
    # the (up to two) patches on each edge
    tri = np.repeat(np.arange(len(F)), 3)
    eid = edge_of.reshape(-1)
    order = np.argsort(eid, kind="stable")
    eid, tri = eid[order], tri[order]
    pair = np.flatnonzero(eid[1:] == eid[:-1])
    p, q = tri[pair], tri[pair + 1]
    light = scene.emitters[p] | scene.emitters[q]
    jump = np.abs(L[p] - L[q]) > threshold * np.maximum(np.maximum(L[p], L[q]), 1e-300)
    marked = np.zeros(scene.n_patches, bool)
    marked[p[jump & ~light]] = True
    marked[q[jump & ~light]] = True
    return marked


def refine_patches(scene: Scene, marked: np.ndarray) -> Scene:
    """Split ``marked`` patches in four and their neighbours as needed (red-green, conforming).

    Returns a new Scene; the children of patch p keep its material, group,
    reflectance, emission and parent face, and area is conserved to rounding.
    """
    if scene.is_clustered:
        raise SceneError(f"{scene.name}: cannot refine a clustered scene (patches are clusters of triangles)")
    marked = np.asarray(marked, dtype=bool).reshape(-1)
    if marked.shape != (scene.n_patches,):
        raise InputError(f"marks have {marked.size} entries for {scene.n_patches} patches")
    F = weld(scene.vertices, scene.faces)  # patches of two faces share corners
    edges, edge_of = _edges(F)
    red = marked.copy()
    while True:  # red patches cut all their edges; a patch with two or more cut edges turns red
        cut = np.zeros(len(edges), bool)
        cut[edge_of[red].reshape(-1)] = True
        more = (cut[edge_of].sum(axis=1) >= 2) & ~red
        if not more.any():
            break
        red |= more
    # positions: merged vertices, then one midpoint per cut edge
    V = np.zeros((F.max() + 1, 3))
    V[F.reshape(-1)] = scene.vertices[scene.faces].reshape(-1, 3)
    cut_ids = np.flatnonzero(cut)
    mid_index = np.full(len(edges), -1)
    mid_index[cut_ids] = len(V) + np.arange(len(cut_ids))
    V = np.vstack([V, 0.5 * (V[edges[cut_ids, 0]] + V[edges[cut_ids, 1]])])
    out, owner = [], []
    for t in range(len(F)):
        a, b, c = F[t]
        m = mid_index[edge_of[t]]  # midpoints of edges ab, bc, ca (-1: not cut)
        if red[t]:
            out += [(a, m[0], m[2]), (m[0], b, m[1]), (m[2], m[1], c), (m[0], m[1], m[2])]
            owner += [t] * 4
        elif (m >= 0).any():  # green: bisect from the corner opposite the cut edge
            k = int(np.flatnonzero(m >= 0)[0])
            p0, p1, p2 = F[t][k], F[t][(k + 1) % 3], F[t][(k + 2) % 3]
            out += [(p0, m[k], p2), (m[k], p1, p2)]
            owner += [t] * 2
        else:
            out.append((a, b, c))
            owner.append(t)
    owner = np.array(owner)
    faces = np.array(out, dtype=np.int64)
    used, faces = np.unique(faces, return_inverse=True)
    return scene.remeshed(V[used], faces.reshape(-1, 3), owner)
