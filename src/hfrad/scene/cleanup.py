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
candidate pairs whose bounding boxes overlap).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic

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
    flip, plane_n, key = _plane_keys(tri, nrm, centre, _CANONICAL, PLANE_ANGLE, WELD * size)
    plane = row_ids(key)
    # 2D coordinates in each plane: one (u, v) basis per plane, from its first face's normal
    # (per-face bases would differ by up to PLANE_ANGLE and fake overlaps along shared edges)
    first = first_index(plane, int(plane.max()) + 1)
    uv, lo, hi = _plane_coordinates(tri, np.ascontiguousarray(plane_n[first][plane]), centre)
    order = _by_plane_then_u(plane, int(plane.max()) + 1, np.ascontiguousarray(lo[:, 0]))
    i, j, area = _sweep(np.ascontiguousarray(uv[order]), plane[order], lo[order], hi[order], 1e-9 * size)
    i, j = order[i], order[j]
    sign = flip[i] * flip[j]
    pairs = np.column_stack([faces[i], faces[j]])
    pairs.sort(axis=1)
    return pairs.astype(np.int64), area, sign


@njit(cache=True)
def _plane_keys(tri, nrm, centre, canonical, angle_step, offset_step):
    """Each face's plane: the sign turning its normal to the canonical side, that normal, and
    the plane's key (the normal's components / PLANE_ANGLE and the offset of the centroid
    from ``centre`` / ``offset_step``, rounded), (p, 4) int64.

    The sums are in the order of the NumPy calls this replaces (``nrm @ canonical``, OpenBLAS's
    dgemv; ``np.einsum("pd,pd->p", ...)``, which adds terms 0 and 2 first), so the keys are
    the same to the bit.
    """
    p = tri.shape[0]
    flip = np.empty(p)
    plane_n = np.empty((p, 3))
    key = np.empty((p, 4), np.int64)
    for f in range(p):
        s = _fma(nrm[f, 2], canonical[2], _fma(nrm[f, 0], canonical[0], nrm[f, 1] * canonical[1]))
        flip[f] = -1.0 if s < 0 else 1.0
        for d in range(3):
            plane_n[f, d] = nrm[f, d] * flip[f]
            key[f, d] = np.int64(np.rint(plane_n[f, d] / angle_step))
        m0 = (tri[f, 0, 0] + tri[f, 1, 0] + tri[f, 2, 0]) / 3.0 - centre[0]
        m1 = (tri[f, 0, 1] + tri[f, 1, 1] + tri[f, 2, 1]) / 3.0 - centre[1]
        m2 = (tri[f, 0, 2] + tri[f, 1, 2] + tri[f, 2, 2]) / 3.0 - centre[2]
        offset = (plane_n[f, 0] * m0 + plane_n[f, 2] * m2) + plane_n[f, 1] * m1
        key[f, 3] = np.int64(np.rint(offset / offset_step))
    return flip, plane_n, key


@njit(cache=True)
def _plane_coordinates(tri, rep, centre):
    """(u, v) coordinates (p, 3, 2) of each face's corners in a basis of its plane's normal
    ``rep`` (p, 3), with each face's lowest and highest u and v (p, 2).

    ``u = rep x (1, 0, 0)`` (or ``(0, 1, 0)`` where rep is near the x axis), normalised;
    ``v = rep x u``; sums in np.linalg.norm's and np.einsum's order (the same bits).
    """
    p = tri.shape[0]
    uv = np.empty((p, 3, 2))
    lo = np.empty((p, 2))
    hi = np.empty((p, 2))
    for f in range(p):
        n0, n1, n2 = rep[f, 0], rep[f, 1], rep[f, 2]
        h0, h1, h2 = (1.0, 0.0, 0.0) if abs(n0) < 0.9 else (0.0, 1.0, 0.0)
        u0, u1, u2 = n1 * h2 - n2 * h1, n2 * h0 - n0 * h2, n0 * h1 - n1 * h0
        length = math.sqrt((u0 * u0 + u1 * u1) + u2 * u2)
        u0, u1, u2 = u0 / length, u1 / length, u2 / length
        v0, v1, v2 = n1 * u2 - n2 * u1, n2 * u0 - n0 * u2, n0 * u1 - n1 * u0
        for k in range(3):
            r0, r1, r2 = tri[f, k, 0] - centre[0], tri[f, k, 1] - centre[1], tri[f, k, 2] - centre[2]
            uv[f, k, 0] = (r0 * u0 + r2 * u2) + r1 * u1
            uv[f, k, 1] = (r0 * v0 + r2 * v2) + r1 * v1
        for e in range(2):
            lo[f, e] = min(uv[f, 0, e], min(uv[f, 1, e], uv[f, 2, e]))
            hi[f, e] = max(uv[f, 0, e], max(uv[f, 1, e], uv[f, 2, e]))
    return uv, lo, hi


@njit(cache=True)
def _by_plane_then_u(plane, n_planes, u):
    """``np.lexsort((u, plane))``: faces by plane, then by lowest u, ties in index order; most
    planes hold a few faces, so a counting sort by plane and a stable sort of each plane's run."""
    order = grouped_order(plane, n_planes)
    a = 0
    while a < order.shape[0]:
        b = a + 1
        while b < order.shape[0] and plane[order[b]] == plane[order[a]]:
            b += 1
        if b - a > 16:
            run = order[a:b].copy()
            order[a:b] = run[np.argsort(u[run], kind="mergesort")]
        else:
            for q in range(a + 1, b):  # insertion sort, stable
                x = order[q]
                r = q - 1
                while r >= a and u[order[r]] > u[x]:
                    order[r + 1] = order[r]
                    r -= 1
                order[r + 1] = x
        a = b
    return order


@njit(cache=True)
def _sweep(uv, plane, lo, hi, tol):
    """Candidate pairs in one plane with overlapping boxes (sorted by plane, then lo u), and their overlap areas."""
    n = uv.shape[0]
    out_i, out_j, out_a = [], [], []
    poly, nxt, clip = np.empty((9, 2)), np.empty((9, 2)), np.empty((3, 2))  # reused by every pair
    for a in range(n):
        for b in range(a + 1, n):
            if plane[b] != plane[a] or lo[b, 0] > hi[a, 0] - tol:
                break
            if lo[b, 1] > hi[a, 1] - tol or lo[a, 1] > hi[b, 1] - tol:
                continue
            area = _intersection_area(uv[a], uv[b], poly, nxt, clip)
            if area > 0.0:
                out_i.append(a)
                out_j.append(b)
                out_a.append(area)
    ri = np.empty(len(out_i), np.int64)
    rj = np.empty(len(out_i), np.int64)
    ra = np.empty(len(out_i))
    for k in range(len(out_i)):
        ri[k], rj[k], ra[k] = out_i[k], out_j[k], out_a[k]
    return ri, rj, ra


@njit(cache=True)
def _signed_area(p, m):
    s = 0.0
    for k in range(m):
        k1 = (k + 1) % m
        s += p[k, 0] * p[k1, 1] - p[k1, 0] * p[k, 1]
    return 0.5 * s


@njit(cache=True)
def _intersection_area(t1, t2, poly, nxt, clip):
    """Area of the intersection of two 2D triangles (Sutherland-Hodgman clip of t1 by t2);
    ``poly``, ``nxt`` (9, 2) and ``clip`` (3, 2) are work space."""
    for k in range(3):
        poly[k, 0], poly[k, 1] = t1[k, 0], t1[k, 1]
    m = 3
    clip[:] = t2
    if _signed_area(clip, 3) < 0:  # make the clipping triangle counter-clockwise
        clip[1, 0], clip[2, 0] = t2[2, 0], t2[1, 0]
        clip[1, 1], clip[2, 1] = t2[2, 1], t2[1, 1]
    for e in range(3):
        ax, ay = clip[e, 0], clip[e, 1]
        bx, by = clip[(e + 1) % 3, 0], clip[(e + 1) % 3, 1]
        k2 = 0
        for k in range(m):
            px, py = poly[k, 0], poly[k, 1]
            qx, qy = poly[(k + 1) % m, 0], poly[(k + 1) % m, 1]
            dp = (bx - ax) * (py - ay) - (by - ay) * (px - ax)
            dq = (bx - ax) * (qy - ay) - (by - ay) * (qx - ax)
            if dp >= 0.0:
                nxt[k2, 0], nxt[k2, 1] = px, py
                k2 += 1
            if (dp >= 0.0) != (dq >= 0.0):
                t = dp / (dp - dq)
                nxt[k2, 0], nxt[k2, 1] = px + t * (qx - px), py + t * (qy - py)
                k2 += 1
        m = k2
        if m < 3:
            return 0.0
        for k in range(m):
            poly[k, 0], poly[k, 1] = nxt[k, 0], nxt[k, 1]
    return abs(_signed_area(poly, m))


@intrinsic
def _fma(typingctx, a, b, c):
    """``a * b + c`` rounded once (IEEE fused multiply-add), in numba-compiled code."""
    sig = types.float64(types.float64, types.float64, types.float64)

    def codegen(context, builder, signature, args):
        d = ir.DoubleType()
        fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(d, [d, d, d]), "llvm.fma.f64")
        return builder.call(fn, args)
    return sig, codegen


# The cut points and the tests on them are computed as numpy's BLAS calls (OpenBLAS, x86-64)
# computed them when this module used ``(poly - a) @ inward`` and ``np.dot``: the same fused
# products in the same order, so the pieces are the same triangles to the bit. A fused
# multiply-add is rounded once by IEEE 754, so the result no longer depends on the machine.
@njit(cache=True)
def _side(p, a, w):
    """``(p - a) . w`` of 3-vectors, as OpenBLAS's dgemv sums a row of three."""
    return _fma(p[2] - a[2], w[2], _fma(p[0] - a[0], w[0], (p[1] - a[1]) * w[1]))


@njit(cache=True)
def _dot(a, b):
    """``a . b`` of 3-vectors, as OpenBLAS's ddot sums them."""
    return _fma(a[2], b[2], _fma(a[1], b[1], a[0] * b[0]))


@njit(cache=True)
def _cross(a, b):
    """``a x b`` of 3-vectors."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


@njit(cache=True)
def _clip(poly, a, inward, keep_inside):
    """The part of convex polygon ``poly`` ((k, 3) points in one plane) inside (left of the line
    a -> b about the plane's normal n) or outside it; fewer than 3 rows where less than a
    polygon is left.

    ``inward = n x (b - a)``: the side of a point is ``n . ((b - a) x (p - a)) = (p - a) . inward``,
    one cross product an edge, not one a point."""
    m = poly.shape[0]
    side = np.empty(m)
    for k in range(m):
        side[k] = _side(poly[k], a, inward) if keep_inside else -_side(poly[k], a, inward)
    out = np.empty((m + 1, 3))
    c = 0
    for k in range(m):
        k1 = (k + 1) % m
        sp, sq = side[k], side[k1]
        if sp >= 0.0:
            out[c] = poly[k]
            c += 1
        if (sp >= 0.0) != (sq >= 0.0):
            t = sp / (sp - sq)
            for d in range(3):
                out[c, d] = poly[k, d] + t * (poly[k1, d] - poly[k, d])
            c += 1
    return out[:c]


@njit(cache=True)
def _minus(polys, tri, n):
    """Convex polygons covering ``polys`` minus triangle ``tri`` (counter-clockwise about n): the
    parts outside edge 0, outside edge 1 but inside edge 0, outside edge 2 but inside 0 and 1."""
    out = []
    inward = np.empty((3, 3))  # n x (b - a) of each edge a -> b
    for e in range(3):
        inward[e] = _cross(n, tri[(e + 1) % 3] - tri[e])
    for poly in polys:
        inside = poly
        for e in range(3):
            piece = _clip(inside, tri[e], inward[e], False)
            if piece.shape[0] >= 3:
                out.append(piece)
            inside = _clip(inside, tri[e], inward[e], True)
            if inside.shape[0] < 3:
                break
    return out


@njit(cache=True)
def _polygon_area(poly):
    """Area of a convex polygon ((k, 3) points), from its fan of triangles."""
    total = 0.0
    for k in range(1, poly.shape[0] - 1):
        c = _cross(poly[k] - poly[0], poly[k + 1] - poly[0])
        total += math.sqrt(c[0] * c[0] + (c[1] * c[1] + c[2] * c[2]))
    return 0.5 * total


@njit(cache=True)
def _cut_face(tri, normals, j, below, keep_area):
    """Face j minus the faces ``below`` (indices), as convex polygons of more than ``keep_area``."""
    n = normals[j]
    polys = [tri[j].copy()]
    for i in below:
        t = tri[i] if _dot(_cross(tri[i, 1] - tri[i, 0], tri[i, 2] - tri[i, 0]), n) > 0 else tri[i, ::-1].copy()
        polys = _minus(polys, t, n)
    return [p for p in polys if _polygon_area(p) > keep_area]


@njit(cache=True)
def _cut_faces(tri, normals, areas, cut_faces, start, below, gone, min_overlap, sliver, tiny):
    """:func:`resolve_overlaps`'s loop: face ``cut_faces[q]`` minus faces ``below[start[q]:start[q + 1]]``.

    Returns the new points (p, 3), the fan triangles (f, 3) indexing them, each triangle's
    face (f,), and the numbers of faces cut and dropped; marks every cut face in ``gone``.
    """
    points, corners, owner = [], [], []
    n_points = 0
    cut = dropped = 0
    for q in range(cut_faces.shape[0]):
        j = cut_faces[q]
        if gone[j]:  # a merged duplicate
            continue
        polys = _cut_face(tri, normals, j, below[start[q]:start[q + 1]], min_overlap * areas[j])
        gone[j] = True
        if len(polys) == 0:
            dropped += 1
            continue
        cut += 1
        n = normals[j]
        for poly in polys:
            for k in range(1, poly.shape[0] - 1):  # convex: a fan keeps the orientation of j
                c = _cross(poly[k] - poly[0], poly[k + 1] - poly[0])
                length = math.sqrt(_dot(c, c))
                # no slivers of rounding (their normals are noise): a real piece has area and j's normal
                if _dot(c, n) > 0.99 * length and 0.5 * length > max(sliver * areas[j], tiny):
                    corners.append((n_points, n_points + k, n_points + k + 1))
                    owner.append(j)
            points.append(poly)
            n_points += poly.shape[0]
    out_points = np.empty((n_points, 3))
    k = 0
    for poly in points:
        out_points[k:k + poly.shape[0]] = poly
        k += poly.shape[0]
    out_faces = np.empty((len(corners), 3), np.int64)
    for f in range(len(corners)):
        out_faces[f, 0], out_faces[f, 1], out_faces[f, 2] = corners[f]
    return out_points, out_faces, np.array(owner, np.int64), cut, dropped


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
    Compiled (numba): the conference room's ~5,000 cut faces take ~66,000 clips of a
    polygon by a line, ~10 us each as NumPy calls, well under 1 us compiled.
    """
    tri = np.ascontiguousarray(scene.triangles, np.float64)
    normals = np.ascontiguousarray(scene.normals, np.float64)
    pairs = np.sort(np.asarray(overlaps, np.int64).reshape(-1, 2), axis=1)
    order = np.argsort(pairs[:, 1], kind="stable")  # by cut face j; its faces i in the order given
    j_sorted, below = pairs[order, 1], np.ascontiguousarray(pairs[order, 0])
    cut_faces, start = np.unique(j_sorted, return_index=True)
    start = np.append(start, len(j_sorted)).astype(np.int64)
    gone = np.zeros(scene.n_patches, bool)
    gone[np.asarray(drop, np.int64)] = True
    tiny = 1e-12 * float(np.max(scene.areas))  # what patches.drop_degenerate calls zero area
    points, pieces, owner, cut, dropped = _cut_faces(
        tri, normals, np.ascontiguousarray(scene.areas, np.float64), cut_faces.astype(np.int64), start, below,
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
