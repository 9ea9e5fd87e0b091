"""Write the office's catalogue luminaires (IES files) and their layout (run from this folder).

Two luminaires, as a manufacturer's catalogue would give them:

- ``luminaires/panel-600.ies``: a recessed 600 x 600 LED panel, IES LM-63-2019,
  type C with quadrant symmetry (C0..C90), 3,240 lm (absolute photometry), 28 W;
  a slightly batwing distribution, wider in the C0 plane than in C90.
- ``luminaires/downlight-150.ies``: a 150 mm round LED downlight,
  IESNA:LM-63-2002, rotationally symmetric (one horizontal angle), 1,800 lm,
  16 W; a cos^4 beam.

``layout.json`` places 12 of them 1 cm under the 2.8 m ceiling (y up): six
panels over the ceiling's luminaire cells (x = 1, 3, 5 m; z = 1.5, 3.5 m) and
six downlights between and beside them (x = 2, 4 m; z = 0.6, 2.5, 4.4 m).
"""

from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
V = np.arange(0, 91, 5.0)


def panel(c, g):
    """cd of the panel (3,240 lm); c and g in degrees."""
    cg = np.cos(np.radians(g))
    return 1020.0 * cg ** 1.1 * (1.0 + 0.25 * np.sin(np.radians(g)) ** 2 * np.cos(np.radians(c)) ** 2)


def downlight(g):
    return 1432.0 * np.cos(np.radians(g)) ** 4


def _rows(values, per_line=10):
    s = [f"{x:.1f}" for x in values]
    return [" ".join(s[i:i + per_line]) for i in range(0, len(s), per_line)]


def write_panel(path: Path) -> None:
    h = [0.0, 22.5, 45.0, 67.5, 90.0]
    lines = ["IES:LM-63-2019", "[TEST] HF-2026-0601", "[TESTLAB] hfrad example photometry",
             "[ISSUEDATE] 02-DEC-2026", "[MANUFAC] Example Lighting", "[LUMCAT] EXP-600-34-840",
             "[LUMINAIRE] recessed LED panel 600 x 600, opal diffuser", "[LAMP] LED module 4000 K",
             "[LAMPCAT] included", "TILT=NONE",
             f"1 -1 1.0 {len(V)} {len(h)} 1 2 0.6 0.6 0.0", "1.0 1.00001 28"]
    lines += _rows(V) + _rows(h)
    for c in h:
        lines += _rows(panel(c, V))
    path.write_text("\r\n".join(lines) + "\r\n", encoding="latin-1")


def write_downlight(path: Path) -> None:
    lines = ["IESNA:LM-63-2002", "[TEST] HF-2026-0602", "[TESTLAB] hfrad example photometry",
             "[ISSUEDATE] 02-DEC-2026", "[MANUFAC] Example Lighting", "[LUMCAT] EXD-150-18-840",
             "[LUMINAIRE] LED downlight 150 mm, clear reflector", "[LAMP] LED module 4000 K", "TILT=NONE",
             f"1 1800 1.0 {len(V)} 1 1 2 -0.15 -0.15 0.0", "1.0 1.0 16"]
    lines += _rows(V) + ["0"] + _rows(downlight(V))
    path.write_text("\r\n".join(lines) + "\r\n", encoding="latin-1")


def layout() -> dict:
    y = 2.79
    lums = []
    for i, (x, z) in enumerate([(x, z) for z in (1.5, 3.5) for x in (1.0, 3.0, 5.0)], 1):
        lums.append({"name": f"panel_{i}", "photometry": "luminaires/panel-600.ies", "position": [x, y, z]})
    for i, (x, z) in enumerate([(x, z) for z in (0.6, 2.5, 4.4) for x in (2.0, 4.0)], 1):
        lums.append({"name": f"down_{i}", "photometry": "luminaires/downlight-150.ies", "position": [x, y, z]})
    return {"description": "12 catalogue luminaires 1 cm under the office ceiling (y up); dimming in [0, 1]",
            "defaults": {"aim": [0, -1, 0], "rotation": 0, "dimming": 1.0, "max": 1.0},
            "luminaires": lums}


if __name__ == "__main__":
    import json

    (HERE / "luminaires").mkdir(exist_ok=True)
    write_panel(HERE / "luminaires" / "panel-600.ies")
    write_downlight(HERE / "luminaires" / "downlight-150.ies")
    (HERE / "layout.json").write_text(json.dumps(layout(), indent=2) + "\n")
    print("wrote luminaires/panel-600.ies, luminaires/downlight-150.ies, layout.json")
