"""Conforming, well-shaped patches: no T-junctions, no slivers.

Every mesh edge is cut ONCE into ``ceil(length / h)`` equal pieces, after
first cutting it at any mesh vertex lying on it (a T-junction of the input,
like a block's bottom corner on the floor's edge). Both faces that share an
edge, and faces meeting at a T-junction vertex, therefore see the same points.
Coplanar, edge-connected faces of one material and group are then meshed
together as one planar region by Shewchuk's Triangle (``triangle`` package):
its boundary points fixed (switch ``YY``: no new points on any segment), a
triangular lattice of spacing :data:`LATTICE` h inside, and an edge still
longer than h given its midpoint until none is. Edges of other faces lying
inside a region (a block standing on a floor that is not cut around it) are
constraints of its mesh too, cut at the same points, so the floor's patches
meet the block's along the contact line.

The result: no patch vertex lies inside another patch's edge (no T-junction),
patches on either side of a crease or contact line share their points, every
patch edge is at most h, and each region's area is kept to rounding.
"""

from __future__ import annotations

import math

import numpy as np
import triangle
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from ..errors import SceneError
from .scene import Scene

#: Interior point spacing, in units of the longest allowed edge h.
LATTICE = 0.95
#: Lattice points nearer than this many spacings to a boundary point are dropped.
CLEARANCE = 0.7
#: Relative tolerance (of the scene size) for "on an edge" and "coplanar".
REL_TOL = 1e-7


def _merge(points: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Merge points closer than ``tol``: (unique points, index of each input point)."""
    label = np.arange(len(points))
    pairs = cKDTree(points).query_pairs(tol, output_type="ndarray")
    if len(pairs):
        graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(points),) * 2)
        label = connected_components(graph, directed=False)[1]
    _, first, inverse = np.unique(label, return_index=True, return_inverse=True)
    return points[first], inverse.reshape(-1)


def _edge_cuts(V: np.ndarray, edges: np.ndarray, tol: float) -> list[list[int]]:
    """For each edge (a, b): the mesh vertices on it, ordered from a to b (a and b included)."""
    tree = cKDTree(V)
    a, b = V[edges[:, 0]], V[edges[:, 1]]
    length = np.linalg.norm(b - a, axis=1)
    near = tree.query_ball_point(0.5 * (a + b), 0.5 * length + tol)
    out = []
    for k, cand in enumerate(near):
        i, j = edges[k]
        cand = np.array([c for c in cand if c != i and c != j], dtype=np.int64)
        chain = [int(i)]
        if len(cand):
            d = b[k] - a[k]
            t = (V[cand] - a[k]) @ d / (length[k] ** 2)
            off = np.linalg.norm(V[cand] - a[k] - t[:, None] * d, axis=1)
            on = (off <= tol) & (t > 0) & (t < 1)
            chain += [int(c) for c in cand[on][np.argsort(t[on])]]
        chain.append(int(j))
        out.append(chain)
    return out


def _regions(scene: Scene, F: np.ndarray, V: np.ndarray, seg_faces: dict, tol: float) -> np.ndarray:
    """(t,) region label: coplanar faces of one material/group/reflectance/emission joined across shared pieces.

    ``seg_faces`` maps each boundary piece to the ``(face, forward)`` pairs using it.
    """
    t = len(F)
    parent = np.arange(t)

    def find(x: int) -> int:
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    n = scene.triangle_normals
    attrs = np.hstack([scene.material[:, None], scene.group[:, None], scene.reflectance, scene.emission])
    for faces in seg_faces.values():
        # join only across a manifold piece: two faces, traversing it in opposite directions
        # (duplicate faces, or three faces on one edge, stay separate regions)
        if len(faces) != 2 or faces[0][1] == faces[1][1]:
            continue
        (f, _), (g, _) = faces
        if not np.array_equal(attrs[f], attrs[g]) or n[f] @ n[g] < 1 - 1e-9:
            continue
        if np.abs((V[F[f]] - V[F[g][0]]) @ n[g]).max() > tol:
            continue
        rf, rg = find(f), find(g)
        if rf != rg:
            parent[max(rf, rg)] = min(rf, rg)
    return np.array([find(x) for x in range(t)])


def _basis(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Orthonormal (u, v) with u x v = normal."""
    helper = np.eye(3)[int(np.argmin(np.abs(normal)))]
    u = np.cross(helper, normal)
    u /= np.linalg.norm(u)
    return u, np.cross(normal, u)


def _mesh_region(xy: np.ndarray, segments: np.ndarray, h: float, inside) -> dict:
    """Mesh one planar region given its boundary points and segments (2-D).

    Interior points: a triangular lattice of spacing ``LATTICE * h``, less the
    points nearer than ``CLEARANCE`` lattice spacings to a boundary point; then
    Triangle's constrained Delaunay triangulation (``p``, ``YY``: no points added
    on any segment). An edge still longer than h (say across a right-angled
    corner) gets its midpoint added, and the region is meshed again.
    """
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    s = LATTICE * h
    rows = np.arange(int((hi[1] - lo[1]) / (s * math.sqrt(3) / 2)) + 2)
    cols = np.arange(int((hi[0] - lo[0]) / s) + 2)
    i, j = np.meshgrid(cols, rows)
    lattice = lo + np.stack([(i + 0.5 * (j % 2)) * s, j * s * math.sqrt(3) / 2], axis=-1).reshape(-1, 2)
    lattice = lattice[(lattice <= hi).all(axis=1)]
    if len(lattice):
        lattice = lattice[cKDTree(xy).query(lattice)[0] > CLEARANCE * s]
    if len(lattice):
        lattice = lattice[inside(lattice)]
    pslg = {"vertices": np.vstack([xy, lattice]), "segments": segments}
    rough = triangle.triangulate({"vertices": xy, "segments": segments}, "pYY")
    cent = rough["vertices"][rough["triangles"]].mean(axis=1)
    outside = ~inside(cent)
    if outside.any():
        pslg["holes"] = cent[outside]
    mesh = triangle.triangulate(pslg, "pYY")
    for _ in range(20):
        v, t = mesh["vertices"], mesh["triangles"]
        e = np.unique(np.sort(np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]]), axis=1), axis=0)
        long_ = np.linalg.norm(v[e[:, 1]] - v[e[:, 0]], axis=1) > h * (1 + 1e-9)
        if not long_.any():
            break
        pslg = dict(pslg, vertices=np.vstack([v, 0.5 * (v[e[long_, 0]] + v[e[long_, 1]])]))
        mesh = triangle.triangulate(pslg, "pYY")
    return mesh


def _point_in_triangles(p: np.ndarray, tri: np.ndarray, tol: float) -> np.ndarray:
    """(m, k) bool: whether each 2-D point lies in each 2-D triangle (tolerance ``tol``)."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]

    def side(p0, p1):
        d = p1 - p0
        length = np.linalg.norm(d, axis=1)
        return ((p[:, None, 0] - p0[None, :, 0]) * d[None, :, 1]
                - (p[:, None, 1] - p0[None, :, 1]) * d[None, :, 0]) / np.maximum(length, 1e-300)

    s1, s2, s3 = side(a, b), side(b, c), side(c, a)
    return ((s1 <= tol) & (s2 <= tol) & (s3 <= tol)) | ((s1 >= -tol) & (s2 >= -tol) & (s3 >= -tol))


#: A scene whose centre lies more than this many times its size from the origin is meshed centred.
FAR_FROM_ORIGIN = 100.0


def conforming_subdivide(scene: Scene, h: float) -> Scene:
    """Conforming, quality patches with no edge longer than ``h`` (see module doc).

    Parameters
    ----------
    scene : Scene
        An unclustered scene (one triangle per patch).
    h : float, metres
        Longest allowed patch edge.

    Returns
    -------
    Scene
        Same materials and groups; ``parent`` is the input face under each
        patch's centroid; the input faces stay the occluder mesh. Patches of
        one region are kept together, regions in the order of their first face.
    """
    if scene.is_clustered:
        raise SceneError(f"{scene.name}: cannot subdivide a clustered scene")
    # A scene lying far from the origin (more than FAR_FROM_ORIGIN times its size) is meshed in a frame
    # centred on it: the tolerances below are relative to the largest coordinate, which there is far
    # larger than the scene, and points would merge or be missed. Nearer scenes are meshed where they
    # are, since moving them re-rounds every coordinate and the mesher may then flip diagonals.
    lo, hi = np.asarray(scene.bounds, dtype=np.float64)
    centre = 0.5 * (lo + hi)
    if np.abs(centre).max() > FAR_FROM_ORIGIN * max(float(np.max(hi - lo)), np.finfo(float).tiny):
        local = scene.replace(vertices=scene.vertices - centre, occluder_vertices=scene.occluder_vertices - centre)
        out = _conforming_subdivide(local, h)
        return out.replace(vertices=out.vertices + centre, occluder_vertices=out.occluder_vertices + centre)
    return _conforming_subdivide(scene, h)


def _conforming_subdivide(scene: Scene, h: float) -> Scene:
    """:func:`conforming_subdivide` of a scene centred on the origin."""
    scale = float(np.abs(scene.bounds).max()) or 1.0
    tol = REL_TOL * scale
    V, index = _merge(scene.vertices, tol)
    F = index[scene.faces]
    # unique undirected edges, cut at the vertices on them, then into equal pieces
    e = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    edges, edge_of = np.unique(e, axis=0, return_inverse=True)
    edge_of = edge_of.reshape(3, -1).T  # (t, 3): edge k of face f is (F[f,k], F[f,(k+1)%3])
    cuts = _edge_cuts(V, edges, tol)
    points = [V]
    n_points = len(V)
    piece_points: dict[tuple[int, int], list[int]] = {}  # (p < q) -> point ids from p to q
    seg_faces: dict[tuple[int, int], list[int]] = {}
    for chain in cuts:
        for p, q in zip(chain[:-1], chain[1:]):
            key = (min(p, q), max(p, q))
            if key in piece_points:
                continue
            a, b = V[key[0]], V[key[1]]
            m = max(1, math.ceil(np.linalg.norm(b - a) / h - 1e-9))
            inner = a + (b - a) * (np.arange(1, m) / m)[:, None]
            piece_points[key] = [key[0], *range(n_points, n_points + m - 1), key[1]]
            points.append(inner)
            n_points += m - 1
    P = np.concatenate(points)
    # each face's boundary as oriented pieces
    face_pieces: list[list[tuple[int, int]]] = []
    for f in range(len(F)):
        pieces = []
        for k in range(3):
            chain = cuts[edge_of[f, k]]
            if chain[0] != F[f, k]:
                chain = chain[::-1]
            for p, q in zip(chain[:-1], chain[1:]):
                pieces.append((p, q))
                seg_faces.setdefault((min(p, q), max(p, q)), []).append((f, p < q))
        face_pieces.append(pieces)
    region = _regions(scene, F, V, seg_faces, tol)
    normals, areas = scene.triangle_normals, scene.triangle_areas
    longest = np.linalg.norm(V[F] - V[np.roll(F, 1, axis=1)], axis=2).max(axis=1)
    face_keys = [[(min(p, q), max(p, q)) for p, q in pieces] for pieces in face_pieces]

    keys = list(piece_points)
    ends = np.array(keys, dtype=np.int64).reshape(-1, 2)
    piece_tree = cKDTree(0.5 * (P[ends[:, 0]] + P[ends[:, 1]]))

    def _contact_lines(members, own, normal, origin, u, v, face_xy) -> list:
        """Segments of other faces' edges lying inside the region (a block standing on a floor).

        They become constraints of the region's mesh, cut at the same points as
        on the faces they belong to, so the floor's patches meet the block's.
        """
        corners = V[F[members]].reshape(-1, 3)
        centre = 0.5 * (corners.min(axis=0) + corners.max(axis=0))
        radius = 0.5 * float(np.linalg.norm(corners.max(axis=0) - corners.min(axis=0)))
        cand = np.array(piece_tree.query_ball_point(centre, radius + tol), dtype=np.int64)
        if not len(cand):
            return []
        a, b = P[ends[cand, 0]] - origin, P[ends[cand, 1]] - origin
        on = (np.abs(a @ normal) <= tol) & (np.abs(b @ normal) <= tol)
        cand, a, b = cand[on], a[on], b[on]
        out = []
        if len(cand):
            test = np.concatenate([a, b, 0.5 * (a + b)])
            inside = _point_in_triangles(np.stack([test @ u, test @ v], axis=1), face_xy, tol).any(axis=1)
            inside = inside.reshape(3, -1).all(axis=0)
            for c in cand[inside]:
                if keys[c] not in own:
                    chain = piece_points[keys[c]]
                    out += list(zip(chain[:-1], chain[1:]))
        return out

    def mesh_members(members: np.ndarray):
        """(new 3-D points, triangles as ids (P first, then the new points), owner face) or None."""
        count: dict[tuple[int, int], int] = {}
        directed: dict[tuple[int, int], tuple[int, int]] = {}
        for f in members:
            for p, q in face_pieces[f]:
                key = (min(p, q), max(p, q))
                count[key] = count.get(key, 0) + 1
                directed[key] = (p, q)
        segs = []
        for key, c in count.items():
            if c == 1:  # on the region's boundary
                chain = piece_points[key] if directed[key][0] == key[0] else piece_points[key][::-1]
                segs += list(zip(chain[:-1], chain[1:]))
        if not segs:
            return None
        normal = areas[members] @ normals[members]
        normal /= np.linalg.norm(normal)
        u, v = _basis(normal)
        origin = P[segs[0][0]]
        face_xy = np.stack([(V[F[members]] - origin) @ u, (V[F[members]] - origin) @ v], axis=-1)
        segs += _contact_lines(members, count, normal, origin, u, v, face_xy)
        ids = np.unique(segs)
        local = {g: k for k, g in enumerate(ids)}
        xy = np.stack([(P[ids] - origin) @ u, (P[ids] - origin) @ v], axis=1)
        try:
            mesh = _mesh_region(xy, np.array([(local[a], local[b]) for a, b in segs]), h,
                                lambda c: _point_in_triangles(c, face_xy, tol).any(axis=1))
        except (KeyError, RuntimeError, ValueError):  # Triangle gave no triangles, or failed
            return None
        mv, mt = mesh.get("vertices"), mesh.get("triangles")
        if mt is None or not len(mt) or not np.allclose(mv[:len(ids)], xy, rtol=0, atol=tol):
            return None
        T = mv[mt]
        d1, d2 = T[:, 1] - T[:, 0], T[:, 2] - T[:, 0]
        cross = d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]
        if abs(0.5 * np.abs(cross).sum() - areas[members].sum()) > 1e-6 * areas[members].sum() \
                or not (np.abs(cross) > 0).all():
            return None  # a hole filled or a face lost: not the region's area
        mt = np.where((cross > 0)[:, None], mt, mt[:, ::-1])
        new = mv[len(ids):]
        hit = _point_in_triangles(T.mean(axis=1), face_xy, tol)
        return origin + new[:, :1] * u + new[:, 1:] * v, (ids, mt), members[np.argmax(hit, axis=1)]

    out_vertices = [P]
    n_out = len(P)
    out_faces, out_owner = [], []
    unsplit = []
    for r in np.unique(region):  # unique() sorts: regions in the order of their first face
        members = np.flatnonzero(region == r)
        if longest[members].max() <= h and all(len(piece_points[k]) == 2 for f in members
                                                for k in face_keys[f]):
            out_faces.append(F[members])  # small faces, no point on their edges: already conforming
            out_owner.append(members)
            continue
        results = [mesh_members(members)]
        if results[0] is None and len(members) > 1:  # mesh the faces one by one: still conforming
            results = [mesh_members(members[k:k + 1]) for k in range(len(members))]
        for k, res in enumerate(results):
            if res is None:  # a face Triangle cannot mesh (say, nearly degenerate): keep it whole
                f = members[k] if len(results) > 1 else members[0]
                unsplit.append(int(f))
                out_faces.append(F[f][None])
                out_owner.append(np.array([f]))
                continue
            new, (ids, mt), owner = res
            gid = np.concatenate([ids, n_out + np.arange(len(new))])
            out_vertices.append(new)
            n_out += len(new)
            out_faces.append(gid[mt])
            out_owner.append(owner)
    warnings = scene.warnings
    if unsplit:
        warnings += (f"subdivision kept {len(unsplit)} faces whole (the mesher could not cut them), "
                     f"e.g. faces {unsplit[:5]}",)
    owner = np.concatenate(out_owner)
    faces = np.concatenate(out_faces)
    used, faces = np.unique(faces, return_inverse=True)  # drop vertices interior to a region
    return Scene(
        vertices=np.concatenate(out_vertices)[used], faces=faces.reshape(-1, 3),
        material=scene.material[owner], materials=scene.materials, group=scene.group[owner],
        groups=scene.groups, reflectance=scene.reflectance[owner], emission=scene.emission[owner],
        parent=scene.parent[owner], occluder_vertices=scene.occluder_vertices,
        occluder_faces=scene.occluder_faces, name=scene.name, warnings=warnings,
    )
