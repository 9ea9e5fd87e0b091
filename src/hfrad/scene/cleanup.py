"""Broken meshes: duplicate faces, coplanar overlapping faces, faces that touch face to face.

Real meshes (CAD exports, scans, game levels, the Cornell boxes of McGuire's Computer Graphics Archive)
contain faces that radiosity must not take at face value:

- **duplicates**: two triangles with the same three corners (in any order or
  rotation; corners are compared after welding positions that agree to
  ``WELD`` x the scene size) and the same orientation. Both copies would get
  the full form factor, so the light they reflect is counted twice (a row i
  of F sums to 1 plus the form factors F_ij to the extra copies, up to 2
  where every face is doubled). They are merged by default: the first copy
  is kept.
- **coplanar overlaps**: two triangles in the same plane, same orientation,
  whose interiors overlap by more than ``MIN_OVERLAP`` of the smaller area
  (z-fighting geometry, floors laid twice). Their light is partly double
  counted too: a row of F to such a surface counts the overlap once per
  layer, while a ray sees one (on the Šibenik cathedral a parapet's row
  summed to 1.14, 0.44 of it to a floor patch that ray shooting puts at
  0.25). They are resolved by default: the later face of a pair is cut by
  the earlier one (:func:`resolve_overlaps`), so that every point of the
  plane is covered once, by the lowest-numbered face covering it; a face
  covered wholly is dropped.
- **face to face**: two triangles in the same plane with opposite normals that
  overlap (a box's bottom lying on the floor, a wall modelled as two
  back-to-back faces). The kernel gives such pairs zero form factor (each lies
  in the other's tangent plane); reported so the user knows the surfaces touch.

All tests are exact up to the welding tolerance; the cost is a sort of the
faces by plane plus a sweep over each plane's faces (O(n log n) plus the
candidate pairs whose bounding boxes overlap). The per-face and per-pair loops
are compiled (:mod:`hfrad.scene.coplanar`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .coplanar import by_plane_then_u, cut_faces, plane_coordinates, plane_keys, sweep
from .scene import Scene
from .weld import first_index, grouped_order, row_ids, weld

#: Corners closer than this times the scene size are one vertex when comparing faces.
WELD = 1e-6

#: Normals within this angle (radians) are parallel when grouping faces by plane.
PLANE_ANGLE = 1e-4

#: Coplanar triangles overlap if their intersection exceeds this fraction of the smaller one.
MIN_OVERLAP = 1e-4

#: Triangles of a cut face's pieces smaller than this fraction of the face (or of zero area by
#: :func:`hfrad.scene.patches.drop_degenerate`'s measure) are dropped (slivers).
SLIVER = 1e-6

#: Passes of finding and cutting overlaps (a cut piece can meet a face its parent's plane missed).
ROUNDS = 3

# A fixed direction no normal in a real scene is perpendicular to, to orient planes canonically.
_CANONICAL = np.array([0.2113248654, 0.5773502692, 0.7886751346])


@dataclass(frozen=True)
class FaceReport:
    """Duplicate, overlapping and face-to-face triangles of a scene.

    Attributes
    ----------
    duplicates : (d, 2) int
        Pairs (kept, duplicate): ``duplicate`` repeats ``kept`` with the same orientation.
    overlaps : (o, 2) int
        Coplanar pairs of the same orientation whose interiors overlap (duplicates excluded).
    resolved : dict, optional
        What :func:`resolve_overlaps` did: ``cut`` (faces cut to their uncovered part),
        ``dropped`` (faces covered wholly), ``pieces`` (triangles the cut faces became).
    facing : (f, 2) int
        Coplanar pairs of opposite orientation that overlap (touch face to face).
    """

    duplicates: np.ndarray
    overlaps: np.ndarray
    facing: np.ndarray
    resolved: dict | None = None

    def summary(self, scene: Scene) -> dict:
        """Counts, example pairs and the materials involved, for ``hfrad info``."""
        def part(pairs: np.ndarray) -> dict:
            faces = np.unique(pairs) if len(pairs) else np.zeros(0, np.int64)
            mats = sorted({scene.material_names[m] for m in np.unique(scene.material[faces])})
            return {"count": int(len(pairs)), "examples": pairs[:5].tolist(), "materials": mats}
        out = {"duplicates": part(self.duplicates), "overlaps": part(self.overlaps), "facing": part(self.facing)}
        if self.resolved is not None:
            out["overlaps"]["resolved"] = dict(self.resolved)
        return out

    def warnings(self, scene: Scene, *, merged: bool) -> list[str]:
        """One line per kind of problem found (empty when the mesh is clean)."""
        out = []
        s = self.summary(scene)
        if s["duplicates"]["count"]:
            d = s["duplicates"]
            what = (f"{d['count']} duplicate faces (same corners as another face) of material(s) "
                    f"{', '.join(d['materials'])}, e.g. face pairs {d['examples'][:3]}")
            out.append(f"merged {what}" if merged else
                       f"kept {what} (--keep-duplicates): their light is counted twice")
        if s["overlaps"]["count"]:
            o = s["overlaps"]
            what = (f"{o['count']} pairs of coplanar faces overlap (material(s) {', '.join(o['materials'])}), "
                    f"e.g. face pairs {o['examples'][:3]}")
            r = o.get("resolved")
            out.append(f"{what}: resolved, each overlap kept once (cut {r['cut']} faces into {r['pieces']} "
                       f"triangles, dropped {r['dropped']} covered wholly)" if r is not None else
                       f"{what}; the overlap's light is counted twice" + (" (--keep-duplicates)" if not merged else ""))
        if s["facing"]["count"]:
            f = s["facing"]
            out.append(f"{f['count']} pairs of faces touch face to face at zero distance (material(s) "
                       f"{', '.join(f['materials'])}), e.g. face pairs {f['examples'][:3]}")
        return out


def _size(scene: Scene) -> float:
    if not scene.n_patches:
        return 1.0
    lo, hi = scene.bounds
    size = float(np.max(hi - lo))
    return size if size > 0 else 1.0


def find_face_problems(scene: Scene) -> FaceReport:
    """Duplicate, coplanar-overlapping and face-to-face triangles (see module docstring).

    Parameters
    ----------
    scene : Scene
        Patches without zero-area ones (see :func:`hfrad.scene.patches.drop_degenerate`).

    Returns
    -------
    FaceReport
        Pairs of patch indices, each pair (i, j) with i < j.
    """
    n = scene.n_patches
    empty = np.zeros((0, 2), np.int64)
    if n < 2:
        return FaceReport(empty, empty, empty)
    normals = np.asarray(scene.normals)
    corners = np.sort(weld(scene.vertices, scene.faces, rel_tol=WELD, bounds=scene.bounds), axis=1)
    group = row_ids(corners)
    order = grouped_order(group, int(group.max()) + 1)
    g = group[order]
    starts = np.r_[0, np.flatnonzero(g[1:] != g[:-1]) + 1]  # first position of each corner set
    later = np.flatnonzero(g[1:] == g[:-1]) + 1  # positions repeating the corner set before them
    first = order[starts[np.searchsorted(starts, later, side="right") - 1]]
    other = order[later]
    aligned = np.einsum("pd,pd->p", normals[first], normals[other]) > 0
    duplicates = np.column_stack([first[aligned], other[aligned]]).astype(np.int64)
    reversed_pairs = np.column_stack([first[~aligned], other[~aligned]]).astype(np.int64)

    live = np.ones(n, bool)
    live[duplicates[:, 1]] = False
    pairs, area, sign = _coplanar_overlaps(scene, np.flatnonzero(live))
    overlap_mask = area > MIN_OVERLAP * np.minimum(scene.areas[pairs[:, 0]], scene.areas[pairs[:, 1]]) \
        if len(pairs) else np.zeros(0, bool)
    pairs, sign = pairs[overlap_mask], sign[overlap_mask]
    overlaps = pairs[sign > 0]
    facing = pairs[sign < 0]
    if len(reversed_pairs):  # reversed copies are caught by the sweep too; keep each pair once
        both = np.vstack([np.sort(facing, axis=1), np.sort(reversed_pairs, axis=1)])
        code = np.unique(both[:, 0] * n + both[:, 1])  # one number a pair, in the order of the rows
        facing = np.column_stack([code // n, code % n])
    return FaceReport(_sorted_pairs(duplicates), _sorted_pairs(overlaps), _sorted_pairs(facing))


def _sorted_pairs(pairs: np.ndarray) -> np.ndarray:
    if not len(pairs):
        return np.zeros((0, 2), np.int64)
    return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))].astype(np.int64)


def _coplanar_overlaps(scene: Scene, faces: np.ndarray):
    """Pairs of ``faces`` in one plane whose bounding boxes overlap, with overlap area and orientation sign."""
    tri = np.ascontiguousarray(np.asarray(scene.triangles)[faces])
    nrm = np.ascontiguousarray(np.asarray(scene.normals)[faces])
    centre = 0.5 * (scene.bounds[0] + scene.bounds[1])
    size = _size(scene)
    flip, plane_n, key = plane_keys(tri, nrm, centre, _CANONICAL, PLANE_ANGLE, WELD * size)
    plane = row_ids(key)
    # 2D coordinates in each plane: one (u, v) basis per plane, from its first face's normal
    # (per-face bases would differ by up to PLANE_ANGLE and fake overlaps along shared edges)
    first = first_index(plane, int(plane.max()) + 1)
    uv, lo, hi = plane_coordinates(tri, np.ascontiguousarray(plane_n[first][plane]), centre)
    order = by_plane_then_u(plane, int(plane.max()) + 1, np.ascontiguousarray(lo[:, 0]))
    i, j, area = sweep(np.ascontiguousarray(uv[order]), plane[order], lo[order], hi[order], 1e-9 * size)
    i, j = order[i], order[j]
    sign = flip[i] * flip[j]
    pairs = np.column_stack([faces[i], faces[j]])
    pairs.sort(axis=1)
    return pairs.astype(np.int64), area, sign


def resolve_overlaps(scene: Scene, overlaps: np.ndarray, *, drop=()) -> tuple[Scene, dict]:
    """Cut each face of ``overlaps`` pairs (i, j), i < j, to the part no lower face covers.

    Face j becomes the convex pieces of (j minus every face i < j paired with it), fanned
    into triangles; pieces smaller than ``MIN_OVERLAP`` of j's area (slivers of rounding)
    are dropped, and j with them when nothing is left. The union of the faces is unchanged
    and each point of it is covered once (by the lowest-numbered face over it), so a row of
    F counts the surface once, as a ray does.

    Parameters
    ----------
    scene : Scene
        Unclustered faces (the input, after duplicates are merged).
    overlaps : (o, 2) int
        Pairs from :func:`find_face_problems`.
    drop : sequence of int
        Faces to leave out as well (the merged duplicates).

    Returns
    -------
    scene : Scene
        The pieces replace the cut faces (other faces keep their order); the pieces are
        appended at the end, each with its face's material, group and parent.
    counts : dict
        ``cut``, ``dropped`` and ``pieces`` (see :class:`FaceReport`).

    Notes
    -----
    Compiled (:func:`hfrad.scene.coplanar.cut_faces`): the conference room's ~5,000 cut
    faces take ~66,000 clips of a polygon by a line, ~10 us each as NumPy calls, well under
    1 us compiled (the two cuts ~1.5 s -> ~0.15 s under cProfile).
    """
    tri = np.ascontiguousarray(scene.triangles, np.float64)
    normals = np.ascontiguousarray(scene.normals, np.float64)
    pairs = np.sort(np.asarray(overlaps, np.int64).reshape(-1, 2), axis=1)
    order = np.argsort(pairs[:, 1], kind="stable")  # by cut face j; its faces i in the order given
    j_sorted, below = pairs[order, 1], np.ascontiguousarray(pairs[order, 0])
    faces_cut, start = np.unique(j_sorted, return_index=True)
    start = np.append(start, len(j_sorted)).astype(np.int64)
    gone = np.zeros(scene.n_patches, bool)
    gone[np.asarray(drop, np.int64)] = True
    tiny = 1e-12 * float(np.max(scene.areas))  # what patches.drop_degenerate calls zero area
    points, pieces, owner, cut, dropped = cut_faces(
        tri, normals, np.ascontiguousarray(scene.areas, np.float64), faces_cut.astype(np.int64), start, below,
        gone, MIN_OVERLAP, SLIVER, tiny)
    keep = np.flatnonzero(~gone)
    vertices = np.vstack([scene.vertices, points])
    faces = np.vstack([scene.faces[keep], pieces + len(scene.vertices)])
    owners = np.concatenate([keep, owner])
    return scene.remeshed(vertices, faces, owners), {"cut": int(cut), "dropped": int(dropped), "pieces": len(pieces)}


def merge_duplicates(scene: Scene, *, keep_duplicates: bool = False) -> Scene:
    """Drop exact duplicate faces (keeping the first copy), cut coplanar overlaps to one layer,
    and note every problem in ``scene.warnings``.

    Parameters
    ----------
    scene : Scene
        Input faces, before subdivision into patches.
    keep_duplicates : bool
        Keep duplicate and overlapping faces as they are (only warn). Their light is then
        counted twice.

    Returns
    -------
    Scene
        Without the duplicates, the overlapping faces cut (:func:`resolve_overlaps`; same
        materials, groups and occluder mesh; ``parent`` still points into the occluder
        mesh), with one warning per kind of problem.
    """
    out, report = clean_faces(scene, keep_duplicates=keep_duplicates)
    return out


def clean_faces(scene: Scene, *, keep_duplicates: bool = False) -> tuple[Scene, FaceReport]:
    """:func:`merge_duplicates`, also returning what was found and done (``FaceReport.resolved``)."""
    report = find_face_problems(scene)
    if not (len(report.duplicates) or len(report.overlaps) or len(report.facing)):
        return scene, report
    if keep_duplicates:
        return scene.replace(warnings=scene.warnings + tuple(report.warnings(scene, merged=False))), report
    if not len(report.overlaps):
        notes = tuple(report.warnings(scene, merged=True))
        if not len(report.duplicates):
            return scene.replace(warnings=scene.warnings + notes), report
        keep = np.ones(scene.n_patches, bool)
        keep[report.duplicates[:, 1]] = False
        return scene.remeshed(scene.vertices, scene.faces[keep], np.flatnonzero(keep), notes=notes), report
    out, resolved = resolve_overlaps(scene, report.overlaps, drop=report.duplicates[:, 1])
    for _ in range(ROUNDS - 1):
        # pieces whose plane offset rounds into a neighbouring plane's bin meet faces they missed
        again = find_face_problems(out)
        if not (len(again.duplicates) or len(again.overlaps)):
            break
        out, more = resolve_overlaps(out, again.overlaps, drop=again.duplicates[:, 1])
        resolved = {k: resolved[k] + more[k] for k in resolved}
        resolved["dropped"] += len(again.duplicates)
    report = FaceReport(report.duplicates, report.overlaps, report.facing, resolved)
    return out.replace(warnings=out.warnings + tuple(report.warnings(scene, merged=True))), report
