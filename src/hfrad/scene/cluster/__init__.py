"""Patches that are clusters of triangles: a real mesh at the patch count asked for.

Game-level and CAD meshes are made of many small triangles (mouldings,
railings, chair legs) whose light matters in aggregate. When ``--patches N``
asks for fewer patches than the scene has faces, :func:`cluster` grows
adjacent triangles into patches of roughly equal area instead of giving each
triangle its own patch (the "target mesh / detail mesh" split of production
radiosity systems):

1. Target area A* = total area / N (times a factor found by a few secant
   steps so that the patch count comes out within ~5 % of N).
1b. Faces longer than PRESPLIT_EDGE sqrt(A*) are first cut by longest-edge
   bisection until no piece is (:func:`presplit`), and the pieces are grown
   like any small face: a long thin face (a floor strip of a game level)
   would otherwise be a long thin patch, one radiosity value along a strip;
   now its pieces join their neighbours across the strip into compact
   patches.
2. Faces larger than A* are split m x m, m = round(sqrt(area / A*)), as
   :func:`hfrad.scene.patches.subdivide` does; each piece is a patch.
3. The other faces are grown into clusters. Seeds are taken along the Z-order
   curve of the face centroids; a cluster absorbs the unassigned neighbour
   (sharing a vertex, welded by position) nearest to its seed while its area
   is below A*, if the neighbour has the same material, group, reflectance
   and emission, its normal is within ``normal_tolerance`` of the cluster's
   mean normal, and it lies within ``1.5 sqrt(A*)`` of the seed (compact
   patches); a patch holds at most MAX_TRIANGLES triangles (this bounds the
   form-factor cost of a pair of patches).
4. Leftover slivers smaller than A*/4 join a compatible adjacent cluster;
   clusters under A*/2 that touch none (separate small parts, gaps, T-joints)
   join a compatible one among the nearest within 1.5 sqrt(A*) if the union
   stays within the normal tolerance; crumbs under A*/100 join the nearest
   one of their material whatever its normal (a patch of almost no area
   would make the columns of F, A_j F_ji / A_i, huge).

With ``max_edge=L`` faces longer than L are split as before and faces shorter
than L/2 are grown into patches no wider than L (no area limit).

Each triangle belongs to exactly one patch (``Scene.triangle_patch``); the
patch's area is the sum of its triangles' areas, so area per material is
conserved exactly, and its normal is the area-weighted mean normal
(``Scene.non_flatness`` measures how far from flat it is). The occluder mesh
is the original mesh, untouched.

The work is split by job: :mod:`~hfrad.scene.cluster.growing` (steps 3 and 4),
:mod:`~hfrad.scene.cluster.bisection` (step 1b) and
:mod:`~hfrad.scene.cluster.quality` (patch diameter, compactness, summary);
this module holds :func:`cluster` and re-exports their public names.
"""

from __future__ import annotations

import math
import numbers

import numpy as np

from ...errors import InputError, SceneError
from ..patches import check_cut_options, split_faces
from ..scene import Scene
from ..weld import row_ids, weld
from ..zorder import zorder_permutation
from .bisection import presplit
from .growing import (CRUMB, CRUMB_CAP, CRUMB_SHARE, MAX_TRIANGLES, MERGE_BELOW, NEARBY_BELOW, NEARBY_CANDIDATES,
                      NEARBY_ROUNDS, REACH, FaceGraph, compatibility_classes)
from .quality import cluster_summary, compactness, patch_diameters

__all__ = ["COUNT_TOLERANCE", "CRUMB", "CRUMB_CAP", "CRUMB_SHARE", "MAX_TRIANGLES", "MERGE_BELOW", "NEARBY_BELOW",
           "NEARBY_CANDIDATES", "NEARBY_ROUNDS", "NORMAL_TOLERANCE", "PRESPLIT_EDGE", "REACH", "cluster",
           "cluster_summary", "compactness", "compatibility_classes", "patch_diameters", "presplit", "row_ids",
           "weld"]

#: Default largest angle between a triangle's normal and its patch's mean normal, degrees.
NORMAL_TOLERANCE = 30.0

#: Accept a patch count within this relative distance of the one asked for.
COUNT_TOLERANCE = 0.05

#: Faces longer than this times sqrt(target area) are cut before growing (compact patches).
PRESPLIT_EDGE = 1.5

def cluster(scene: Scene, *, patches: int | None = None, max_edge: float | None = None,
            normal_tolerance: float = NORMAL_TOLERANCE) -> Scene:
    """Group a scene's faces into patches of about equal area (see the module docstring).

    Parameters
    ----------
    scene : Scene
        Unclustered (one triangle per patch), degenerate faces already dropped.
    patches : int, optional
        Patch count to aim for (met within ~5 % where the mesh allows it).
    max_edge : float, metres, optional
        Instead of ``patches``: split faces longer than this, and grow faces
        shorter than half of it into patches no wider than it.
    normal_tolerance : float, degrees
        Largest angle between a triangle's normal and its patch's mean normal.

    Returns
    -------
    Scene
        ``faces`` are the detail triangles (the input faces, large ones split),
        ``triangle_patch`` maps each to its patch; patches are in Z-order of
        their centroids and each patch's triangles are contiguous. When the
        request cannot be met (fewer patches than materials and separate
        surfaces allow), the scene carries a warning saying so.

    Raises
    ------
    InputError
        Both or neither of ``patches`` and ``max_edge``; ``patches`` not a
        whole number >= 1; ``max_edge`` not a positive finite length;
        ``normal_tolerance`` outside (0, 90) degrees.
    SceneError
        The scene is already clustered.

    Examples
    --------
    >>> from hfrad.scene.builtin import cornell_box
    >>> from hfrad.scene.patches import subdivide
    >>> fine = subdivide(cornell_box(), patches=4000)
    >>> coarse = cluster(fine, patches=1000)
    >>> bool(abs(coarse.n_patches - 1000) <= 100), coarse.n_triangles == fine.n_patches
    (True, True)
    >>> bool(np.isclose(coarse.total_area, fine.total_area, rtol=1e-12))
    True
    """
    check_cut_options(max_edge, patches, one_required=True)
    if scene.is_clustered:
        raise SceneError(f"{scene.name}: the scene is already clustered ({scene.n_triangles:,} triangles in "
                         f"{scene.n_patches:,} patches); cluster the unclustered scene it was made from")
    if not (isinstance(normal_tolerance, numbers.Real) and 0.0 < normal_tolerance < 90.0):
        raise InputError(f"normal_tolerance must be an angle in (0, 90) degrees, got {normal_tolerance!r}")
    if scene.n_patches == 0:
        return scene
    if patches is not None:
        scene = presplit(scene, PRESPLIT_EDGE * math.sqrt(scene.total_area / patches))
    mesh = FaceGraph(scene)
    cos_tol = math.cos(math.radians(normal_tolerance))
    if max_edge is not None:
        splits = np.maximum(1, np.ceil(mesh.longest / max_edge - 1e-9)).astype(np.int64)
        eligible = mesh.longest < 0.5 * max_edge
        label, count = mesh.grow(eligible, cos_tol, np.inf, 0.5 * max_edge, merge=False)
        return _build(scene, splits, label, count, note=None)
    label, splits, count = _fit_count(mesh, int(patches), cos_tol)
    total = int((splits[splits > 1] ** 2).sum()) + count
    note = None
    if total > (1 + COUNT_TOLERANCE) * patches:
        floor = _fewest(mesh, cos_tol)
        why = (f"clusters cannot cross materials or groups, bend more than {normal_tolerance:g} degrees, "
               f"bridge gaps wider than {REACH:g} sqrt(patch area) or hold more than {MAX_TRIANGLES} triangles, "
               f"so this mesh needs at least about {max(floor, -(-mesh.areas.size // MAX_TRIANGLES)):,}")
        note = (f"--patches {patches:,} cannot be met: got {total:,} patches; " + why if floor > patches else
                f"--patches {patches:,} was met only to {total:,} patches (small separate parts limit the merging; "
                + why + ")")
    return _build(scene, splits, label, count, note=note)


def _fit_count(mesh: FaceGraph, patches: int, cos_tol: float) -> tuple[np.ndarray, np.ndarray, int]:
    """Secant steps on the target area until the patch count is within COUNT_TOLERANCE."""
    total_area = float(mesh.areas.sum())
    factor = 1.0
    best = None
    for _ in range(8):
        a_max = factor * total_area / patches
        splits = np.maximum(1, np.rint(np.sqrt(mesh.areas / a_max))).astype(np.int64)
        eligible = splits == 1
        label, count = mesh.grow(eligible, cos_tol, a_max, REACH * math.sqrt(a_max), merge=True)
        total = int((splits[~eligible] ** 2).sum()) + count
        if best is None or abs(total - patches) < abs(best[0] - patches):
            best = (total, label, splits, count)
        if abs(total - patches) <= COUNT_TOLERANCE * patches:
            break
        # patch count ~ 1 / target area where clustering works; damp the step
        factor *= (total / patches) ** 0.9
    return best[1], best[2], best[3]


def _fewest(mesh: FaceGraph, cos_tol: float) -> int:
    """Patches left when clusters may grow without limit (materials, groups, creases, gaps)."""
    eligible = np.ones(len(mesh.areas), bool)
    total = float(mesh.areas.sum())
    return mesh.grow(eligible, cos_tol, total, float(np.ptp(mesh.centroids, axis=0).max()), merge=True,
                     max_triangles=len(mesh.areas))[1]


def _build(scene: Scene, splits: np.ndarray, label: np.ndarray, count: int, note: str | None) -> Scene:
    """The clustered scene: split faces become one patch per piece, clusters one patch each."""
    split_scene, owner = split_faces(scene, splits)
    # a piece of a split face, or a face that was not grown (too long), is a patch on its own
    single = (splits[owner] > 1) | (label[owner] < 0)
    tri_patch = np.empty(len(owner), np.int64)
    tri_patch[~single] = label[owner[~single]]
    tri_patch[single] = count + np.arange(int(single.sum()))
    n = count + int(single.sum())
    # one face -> one patch: per-patch material etc. from any of its triangles
    first = np.full(n, -1, np.int64)
    first[tri_patch[::-1]] = np.arange(len(tri_patch))[::-1]
    # patches in Z-order of their centroids, triangles grouped by patch
    draft = split_scene.replace(material=split_scene.material[first], group=split_scene.group[first],
                                reflectance=split_scene.reflectance[first], emission=split_scene.emission[first],
                                triangle_patch=tri_patch)
    rank = np.empty(n, np.int64)
    rank[zorder_permutation(draft.centroids)] = np.arange(n)
    tri_patch = rank[tri_patch]
    tri_order = np.argsort(tri_patch, kind="stable")
    first_sorted = first[np.argsort(rank)]
    warnings = split_scene.warnings + ((note,) if note else ())
    return Scene(
        vertices=split_scene.vertices, faces=split_scene.faces[tri_order],
        material=split_scene.material[first_sorted], materials=scene.materials,
        group=split_scene.group[first_sorted], groups=scene.groups,
        reflectance=split_scene.reflectance[first_sorted], emission=split_scene.emission[first_sorted],
        parent=split_scene.parent[tri_order], triangle_patch=tri_patch[tri_order],
        occluder_vertices=scene.occluder_vertices, occluder_faces=scene.occluder_faces,
        name=scene.name, warnings=warnings)
