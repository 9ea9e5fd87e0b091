"""Longest-edge bisection: long faces cut into pieces no longer than a given edge before growing.

Step 1b of :mod:`hfrad.scene.cluster`: a long thin face (a floor strip in a
game level) would be a long thin patch, one radiosity value along the
strip; its pieces join their neighbours across the strip into compact
patches instead.
"""

from __future__ import annotations

import numpy as np

from ..patches import longest_edges
from ..scene import Scene
from ..weld import weld_points

def presplit(scene: Scene, max_edge: float) -> Scene:
    """The unclustered scene with every face longer than ``max_edge`` bisected until none is.

    Longest-edge bisection (cut at the midpoint of the longest edge, again and
    again): a sliver of length L becomes ~2 L / max_edge pieces, not the
    (L / max_edge)^2 of an m x m split, and a well-shaped face gets
    well-shaped pieces. Area and orientation are kept exactly; coincident
    points are merged (the growing welds by position anyway); ``parent``
    still names the input face. Unchanged when no face is that long.

    Parameters
    ----------
    scene : Scene
        Unclustered (one triangle per patch).
    max_edge : float, metres
        Longest edge a piece may have.

    Returns
    -------
    Scene
        One patch per piece, the pieces of one face contiguous and in face order.
    """
    tri = scene.triangles
    owner = np.arange(len(tri))
    long = longest_edges(tri) > max_edge
    if not long.any():
        return scene
    done_tri, done_owner = [tri[~long]], [owner[~long]]
    tri, owner = tri[long], owner[long]
    while len(tri):
        # rotate each triangle so that its longest edge is (corner 0, corner 1), then cut it there
        k = np.argmax(np.linalg.norm(np.roll(tri, -1, axis=1) - tri, axis=2), axis=1)
        rot = (k[:, None] + np.arange(3)[None]) % 3
        a, b, c = (tri[np.arange(len(tri)), rot[:, q]] for q in range(3))
        mid = 0.5 * (a + b)
        tri = np.concatenate([np.stack([a, mid, c], axis=1), np.stack([mid, b, c], axis=1)])
        owner = np.concatenate([owner, owner])
        long = longest_edges(tri) > max_edge
        done_tri.append(tri[~long])
        done_owner.append(owner[~long])
        tri, owner = tri[long], owner[long]
    tri = np.concatenate(done_tri)
    owner = np.concatenate(done_owner)
    order = np.argsort(owner, kind="stable")  # pieces of one face together, in face order
    tri, owner = tri[order], owner[order]
    points = tri.reshape(-1, 3)
    ids = weld_points(points, bounds=scene.bounds)  # coincident points share an id
    vertices = np.empty((int(ids.max()) + 1, 3))
    vertices[ids] = points
    faces = ids.reshape(-1, 3)
    return scene.remeshed(vertices, faces, owner)
