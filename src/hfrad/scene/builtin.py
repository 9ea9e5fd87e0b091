"""Built-in scenes, addressable by name wherever a scene path is accepted.

- ``cornell``: the classic Cornell box, closed by an inward-facing front wall so
  every row of F sums to 1; a camera outside looks through that wall's back.
- ``parallel``, ``perpendicular``, ``disks``: the view-factor catalogue's
  analytic configurations (see :mod:`hfrad.formfactors.analytic`).
- ``furnace``: a closed cube of one grey material, every face emitting; the
  exact radiosity is B = E / (1 - rho).

All are built from quads split into two triangles; units are metres.
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np

from ..errors import SceneError
from .scene import Material, Scene

WHITE = (0.725, 0.71, 0.68)
RED = (0.63, 0.065, 0.05)
GREEN = (0.14, 0.45, 0.091)
LIGHT_EMISSION = (17.0, 12.0, 4.0)


class _Builder:
    """Collects quads and triangles with their material and group names."""

    def __init__(self) -> None:
        self.vertices: list[np.ndarray] = []
        self.faces: list[tuple[int, int, int]] = []
        self.face_material: list[str] = []
        self.face_group: list[str] = []

    def triangle(self, a, b, c, material: str, group: str) -> None:
        base = len(self.vertices)
        self.vertices.extend(np.asarray(p, dtype=np.float64) for p in (a, b, c))
        self.faces.append((base, base + 1, base + 2))
        self.face_material.append(material)
        self.face_group.append(group)

    def quad(self, a, b, c, d, material: str, group: str) -> None:
        """Quad a-b-c-d, counter-clockwise seen from the front."""
        self.triangle(a, b, c, material, group)
        self.triangle(a, c, d, material, group)

    def build(self, materials: list[Material], name: str) -> Scene:
        mat_names = [m.name for m in materials]
        groups = list(dict.fromkeys(self.face_group))
        return Scene(
            vertices=np.array(self.vertices), faces=np.array(self.faces, dtype=np.int64),
            material=np.array([mat_names.index(m) for m in self.face_material]),
            materials=tuple(materials),
            group=np.array([groups.index(g) for g in self.face_group]), groups=tuple(groups),
            name=name,
        )


def _rectangle_with_holes(x0, x1, z0, z1, holes: list[np.ndarray]) -> list[np.ndarray]:
    """Triangles covering [x0,x1] x [z0,z1] minus convex holes, using only their corners.

    Triangle's constrained Delaunay triangulation (``p``; quality ``q20`` with
    ``Y``: no points added on the boundary, so the walls and the blocks' sides
    meet the floor at their own corners). Patches are cut from these faces by
    :func:`hfrad.scene.patches.subdivide`. Returns (3, 2) corner arrays (x, z),
    counter-clockwise in (x, z).
    """
    import triangle

    rings = [np.array([[x0, z0], [x1, z0], [x1, z1], [x0, z1]], dtype=float)]
    rings += [np.asarray(h, dtype=float) for h in holes]
    points, segments = [], []
    for ring in rings:
        base = sum(len(r) for r in points)
        points.append(ring)
        segments += [(base + k, base + (k + 1) % len(ring)) for k in range(len(ring))]
    mesh = triangle.triangulate({"vertices": np.vstack(points), "segments": np.array(segments),
                                 "holes": np.array([h.mean(axis=0) for h in rings[1:]]).reshape(-1, 2)},
                                "pq20Y")
    out = []
    for t in mesh["vertices"][mesh["triangles"]]:
        ccw = (t[1, 0] - t[0, 0]) * (t[2, 1] - t[0, 1]) - (t[1, 1] - t[0, 1]) * (t[2, 0] - t[0, 0]) > 0
        out.append(t if ccw else t[::-1])
    return out


def _footprint(cx: float, cz: float, size: float, angle_deg: float) -> np.ndarray:
    """(4, 2) corners (x, z) of a square block footprint, counter-clockwise in (x, z)."""
    a = math.radians(angle_deg)
    u = np.array([math.cos(a), math.sin(a)]) * size / 2
    v = np.array([-math.sin(a), math.cos(a)]) * size / 2
    c = np.array([cx, cz])
    return np.array([c - u - v, c + u - v, c + u + v, c - u + v])


def cornell_box() -> Scene:
    """The Cornell box: 2 m cube, red left wall, green right wall, two white blocks.

    x in [-1, 1] (left to right seen from the camera), y in [0, 2] (up),
    z in [-1, 1] (back to front). The light is a 0.5 m square cut into the
    ceiling, so the enclosure is closed and every row of F sums to 1.
    """
    b = _Builder()
    lo, hi = -1.0, 1.0

    def floor_or_ceiling(y: float, holes, material: str, group: str, up: bool) -> None:
        for t in _rectangle_with_holes(lo, hi, lo, hi, holes):
            p = [(x, y, z) for x, z in t]  # counter-clockwise in (x, z) -> normal -y
            if up:
                p = p[::-1]
            b.triangle(*p, material, group)

    short = _footprint(0.33, 0.30, 0.6, -17.0)
    tall = _footprint(-0.33, -0.30, 0.6, 17.0)
    light = np.array([[-0.25, -0.25], [0.25, -0.25], [0.25, 0.25], [-0.25, 0.25]])
    floor_or_ceiling(0.0, [short, tall], "white", "floor", up=True)
    floor_or_ceiling(2.0, [light], "white", "ceiling", up=False)
    lp = [(x, 2.0, z) for x, z in light]
    b.quad(*lp, "light", "light")  # counter-clockwise in (x, z) -> faces down
    b.quad((lo, 0, lo), (hi, 0, lo), (hi, 2, lo), (lo, 2, lo), "white", "back")
    b.quad((lo, 0, hi), (lo, 0, lo), (lo, 2, lo), (lo, 2, hi), "red", "left")
    b.quad((hi, 0, lo), (hi, 0, hi), (hi, 2, hi), (hi, 2, lo), "green", "right")
    b.quad((hi, 0, hi), (lo, 0, hi), (lo, 2, hi), (hi, 2, hi), "white", "front")
    for name, fp, height in (("short_block", short, 0.6), ("tall_block", tall, 1.2)):
        _box_sides(b, fp, height, name)
    materials = [Material("white", WHITE), Material("red", RED), Material("green", GREEN),
                 Material("light", (0.78, 0.78, 0.78), LIGHT_EMISSION)]
    return b.build(materials, "cornell")


def _box_sides(b: _Builder, footprint: np.ndarray, height: float, group: str) -> None:
    """Four outward sides and the top of a block standing on the floor (no bottom)."""
    for k in range(4):
        (xa, za), (xb, zb) = footprint[k], footprint[(k + 1) % 4]
        # footprint is counter-clockwise in (x, z); seen from outside this ordering faces out
        b.quad((xb, 0, zb), (xa, 0, za), (xa, height, za), (xb, height, zb), "white", group)
    top = [(x, height, z) for x, z in footprint][::-1]
    b.quad(*top, "white", group)


def parallel_plates(width: float = 1.0, depth: float = 1.0, distance: float = 1.0) -> Scene:
    """Two directly opposed width x depth rectangles ``distance`` apart.

    ``plate1`` at z = 0 faces +z and emits 1 W/m^2; ``plate2`` at z = distance faces -z.
    """
    b = _Builder()
    w, d, c = width, depth, distance
    b.quad((0, 0, 0), (w, 0, 0), (w, d, 0), (0, d, 0), "plate1", "plate1")
    b.quad((0, 0, c), (0, d, c), (w, d, c), (w, 0, c), "plate2", "plate2")
    return b.build(_plate_materials(), f"parallel({w},{d},{c})")


def perpendicular_plates(edge: float = 1.0, width1: float = 1.0, width2: float = 1.0) -> Scene:
    """Two rectangles at 90 degrees sharing an edge of length ``edge`` (along x).

    ``plate1`` lies in y = 0 (z in [0, width1]) facing +y; ``plate2`` lies in
    z = 0 (y in [0, width2]) facing +z.
    """
    b = _Builder()
    l, w1, w2 = edge, width1, width2
    b.quad((0, 0, 0), (0, 0, w1), (l, 0, w1), (l, 0, 0), "plate1", "plate1")
    b.quad((0, 0, 0), (l, 0, 0), (l, w2, 0), (0, w2, 0), "plate2", "plate2")
    return b.build(_plate_materials(), f"perpendicular({l},{w1},{w2})")


def coaxial_disks(radius1: float = 1.0, radius2: float = 1.0, distance: float = 1.0,
                  segments: int = 96) -> Scene:
    """Two parallel coaxial disks (regular polygons of ``segments`` sides) facing each other.

    ``plate1`` (radius1) at z = 0 faces +z; ``plate2`` (radius2) at z = distance faces -z.
    """
    b = _Builder()
    t = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    ring = np.stack([np.cos(t), np.sin(t)], axis=1)
    for k in range(segments):
        p, q = ring[k], ring[(k + 1) % segments]
        b.triangle((0, 0, 0), (*(radius1 * p), 0), (*(radius1 * q), 0), "plate1", "plate1")
        b.triangle((0, 0, distance), (*(radius2 * q), distance), (*(radius2 * p), distance),
                   "plate2", "plate2")
    return b.build(_plate_materials(), f"disks({radius1},{radius2},{distance})")


def _plate_materials() -> list[Material]:
    return [Material("plate1", (0.5, 0.5, 0.5), (1.0, 1.0, 1.0)), Material("plate2", (0.5, 0.5, 0.5))]


def furnace(reflectance: float = 0.5, emission: float = 1.0, size: float = 1.0) -> Scene:
    """A closed cube with inward faces, one grey material that emits everywhere.

    Every row of F sums to 1, so the exact radiosity is B = E / (1 - rho).
    """
    b = _Builder()
    s = size
    c = [(x, y, z) for x in (0, s) for y in (0, s) for z in (0, s)]
    centre = np.full(3, s / 2)
    for quad in ((0, 2, 6, 4), (1, 5, 7, 3), (0, 4, 5, 1), (2, 3, 7, 6), (0, 1, 3, 2), (4, 6, 7, 5)):
        p = [np.array(c[i], dtype=float) for i in quad]
        if np.dot(np.cross(p[1] - p[0], p[2] - p[0]), centre - p[0]) < 0:
            p = p[::-1]  # make the face look into the cube
        b.quad(*p, "grey", "walls")
    mat = Material("grey", (reflectance,) * 3, (emission,) * 3)
    return b.build([mat], f"furnace(rho={reflectance})")


BUILTIN_SCENES: dict[str, Callable[[], Scene]] = {
    "cornell": cornell_box,
    "parallel": parallel_plates,
    "perpendicular": perpendicular_plates,
    "disks": coaxial_disks,
    "furnace": furnace,
}


def builtin_scene(name: str) -> Scene:
    """A built-in scene by name (see ``BUILTIN_SCENES``)."""
    try:
        return BUILTIN_SCENES[name]()
    except KeyError:
        raise SceneError(f"unknown built-in scene '{name}'; built-ins are: "
                         + ", ".join(BUILTIN_SCENES)) from None
