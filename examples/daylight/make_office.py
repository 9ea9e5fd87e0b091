"""Write a sidelit office as OBJ + MTL: 4.5 m wide, 7 m deep, 3 m high, one south window of clear glass.

The window's material has ``d 0.3`` (dissolve): hfrad reads it as glazing of transmittance
1 - d = 0.7 (docs/daylight.md). Run from this folder::

    python make_office.py
    hfrad precompute office.obj --max-edge 0.5 -o office.hfr
    hfrad daylight office.hfr --weather "$(python -c 'import pvlib, os; print(os.path.join(os.path.dirname(pvlib.__file__), "data", "723170TYA.CSV"))')" -o out
"""

from __future__ import annotations

from pathlib import Path

from hfrad.daylight import sidelit_room

HERE = Path(__file__).resolve().parent
MTL = """# sidelit office: grey Lambertian surfaces, clear glass (d < 1: glazing, transmittance (1 - d) x Tf)
newmtl floor
Kd 0.2 0.2 0.2
newmtl ceiling
Kd 0.8 0.8 0.8
newmtl wall
Kd 0.5 0.5 0.5
newmtl glass
Kd 0.08 0.08 0.08
d 0.3
"""


def main() -> None:
    # the room's faces, unsplit (hfrad precompute subdivides them)
    room = sidelit_room(4.5, 7.0, 3.0, sill=0.9, head=2.6, margin=0.5, max_edge=100.0)
    lines = ["# sidelit office, y up, the window in the wall at z = 7 (south with hfrad's default north, -z)",
             "mtllib office.mtl"]
    lines += [f"v {x:.4f} {y:.4f} {z:.4f}" for x, y, z in room.vertices]
    current = None
    for face, m in zip(room.faces, room.material):
        name = room.materials[m].name
        if name != current:
            lines.append(f"usemtl {name}")
            current = name
        lines.append("f " + " ".join(str(i + 1) for i in face))
    (HERE / "office.obj").write_text("\n".join(lines) + "\n")
    (HERE / "office.mtl").write_text(MTL)


if __name__ == "__main__":
    main()
