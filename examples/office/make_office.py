"""Write office.obj + office.mtl, the worked example of `hfrad design` (run from this folder).

A 6 m x 5 m x 2.8 m office (metres, y up): carpet floor, four walls, a ceiling
with a 3 x 2 grid of flush 0.6 m x 0.6 m luminaires (groups lum_1 .. lum_6,
material "luminaire"), a window in the west wall (x = 0) that lets in daylight
(material "window", emitting), and four desks (box desks; the tops are material
"desk", the sides "desk_side"). Surfaces that meet share their edges (the
ceiling and the west wall are cut into cells around the luminaires and the
window), so no faces overlap. Faces are counter-clockwise seen from the room.
"""

from pathlib import Path

import numpy as np

W, D, H = 6.0, 5.0, 2.8             # room: x, z, y
LUM_X = [(0.7, 1.3), (2.7, 3.3), (4.7, 5.3)]
LUM_Z = [(1.2, 1.8), (3.2, 3.8)]
WIN_Z, WIN_Y = (1.0, 4.0), (0.9, 2.2)
DESKS = [(1.6, 1.3), (1.6, 3.7), (4.2, 1.3), (4.2, 3.7)]   # centres (x, z)
DESK_W, DESK_D, DESK_H = 1.4, 0.7, 0.74

MTL = """# office for `hfrad design` (Kd reflectance, Ke exitance in W/m^2)
newmtl floor
Kd 0.30 0.30 0.32
newmtl wall
Kd 0.70 0.70 0.66
newmtl ceiling
Kd 0.80 0.80 0.80
newmtl desk
Kd 0.55 0.42 0.30
newmtl desk_side
Kd 0.45 0.34 0.24
newmtl window
Kd 0.05 0.05 0.05
Ke 1.8 2.0 2.4
newmtl luminaire
Kd 0.80 0.80 0.80
Ke 20 20 20
"""


def main() -> None:
    index: dict[tuple, int] = {}   # shared corners, so that shading is smooth across faces
    lines: list[str] = ["mtllib office.mtl"]

    def quad(group: str, material: str, corners, normal) -> None:
        """Two triangles of the quad a, b, c, d, counter-clockwise seen from the ``normal`` side."""
        a, b, c = (np.asarray(p, float) for p in corners[:3])
        if np.dot(np.cross(b - a, c - a), normal) < 0:
            corners = corners[::-1]
        # lights keep their own corners: smooth shading must not blend their exitance into the wall
        own = material if material in ("window", "luminaire") else ""
        a, b, c, d = (index.setdefault((*map(float, p), own), len(index) + 1) for p in corners)
        lines.extend([f"g {group}", f"usemtl {material}", f"f {a} {b} {c}", f"f {a} {c} {d}"])

    def cells(edges):
        return list(zip(edges[:-1], edges[1:]))

    quad("floor", "floor", [(0, 0, 0), (0, 0, D), (W, 0, D), (W, 0, 0)], (0, 1, 0))
    xs = [0.0] + [x for pair in LUM_X for x in pair] + [W]
    zs = [0.0] + [z for pair in LUM_Z for z in pair] + [D]
    lum = 0
    for (x0, x1) in cells(xs):
        for (z0, z1) in cells(zs):
            is_lum = (x0, x1) in LUM_X and (z0, z1) in LUM_Z
            if is_lum:
                lum += 1
            group, mat = (f"lum_{lum}", "luminaire") if is_lum else ("ceiling", "ceiling")
            quad(group, mat, [(x0, H, z0), (x1, H, z0), (x1, H, z1), (x0, H, z1)], (0, -1, 0))
    quad("wall_east", "wall", [(W, 0, 0), (W, 0, D), (W, H, D), (W, H, 0)], (-1, 0, 0))
    quad("wall_north", "wall", [(0, 0, D), (0, H, D), (W, H, D), (W, 0, D)], (0, 0, -1))
    quad("wall_south", "wall", [(0, 0, 0), (W, 0, 0), (W, H, 0), (0, H, 0)], (0, 0, 1))
    for (z0, z1) in cells([0.0, *WIN_Z, D]):          # the west wall, cut around the window
        for (y0, y1) in cells([0.0, *WIN_Y, H]):
            window = (z0, z1) == WIN_Z and (y0, y1) == WIN_Y
            quad("window" if window else "wall_west", "window" if window else "wall",
                 [(0, y0, z0), (0, y0, z1), (0, y1, z1), (0, y1, z0)], (1, 0, 0))
    for k, (cx, cz) in enumerate(DESKS, 1):
        x0, x1, z0, z1 = cx - DESK_W / 2, cx + DESK_W / 2, cz - DESK_D / 2, cz + DESK_D / 2
        h, g = DESK_H, f"desk_{k}"
        quad(g, "desk", [(x0, h, z0), (x0, h, z1), (x1, h, z1), (x1, h, z0)], (0, 1, 0))
        quad(g, "desk_side", [(x0, 0, z0), (x1, 0, z0), (x1, h, z0), (x0, h, z0)], (0, 0, -1))
        quad(g, "desk_side", [(x0, 0, z1), (x0, h, z1), (x1, h, z1), (x1, 0, z1)], (0, 0, 1))
        quad(g, "desk_side", [(x0, 0, z0), (x0, h, z0), (x0, h, z1), (x0, 0, z1)], (-1, 0, 0))
        quad(g, "desk_side", [(x1, 0, z0), (x1, 0, z1), (x1, h, z1), (x1, h, z0)], (1, 0, 0))
    here = Path(__file__).resolve().parent
    obj = [f"v {x:g} {y:g} {z:g}" for x, y, z, _ in index] + lines
    (here / "office.obj").write_text("# office for `hfrad design`, written by make_office.py\n"
                                     + "\n".join(obj) + "\n")
    (here / "office.mtl").write_text(MTL)


if __name__ == "__main__":
    main()
