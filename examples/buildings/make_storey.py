"""Write storey.ifc and its layout: the two-room storey of tests/test_ifc.py, made with ifcopenshell.api.

    python examples/buildings/make_storey.py      # needs ifcopenshell (pip install 'hfrad[buildings]')

Two 4 x 3 m rooms, 2.8 m high: styled walls ("Wall paint", 0.6), a floor slab and ceiling coverings with no
style (hfrad's defaults: floor 0.2, ceiling 0.7), a glazed window per room ("Glazing", transparency 0.8), a
door between the rooms (no style: door 0.4), two desks per room ("Desk", 0.45) and an IfcSpace per room.
"""

import json
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[1] / "tests"))
from ifc_building import WALL, build_building  # noqa: E402

ROOM, HEIGHT = (4.0, 3.0), 2.8

if __name__ == "__main__":
    build_building(HERE / "storey.ifc", rooms=(2, 1), room=ROOM, height=HEIGHT, desks=2)
    # two downlights per room, 1 cm under the ceiling (hfrad's y-up frame: the IFC's (x, y, z) is (x, z, -y))
    luminaires = [{"name": f"down_{i}_{k}", "position": [WALL + i * (ROOM[0] + WALL) + ROOM[0] * (k + 1) / 3,
                                                         HEIGHT - 0.01, -(WALL + ROOM[1] / 2)]}
                  for i in range(2) for k in range(2)]
    layout = {"defaults": {"photometry": "../office/luminaires/downlight-150.ies"}, "luminaires": luminaires}
    (HERE / "storey-layout.json").write_text(json.dumps(layout, indent=1) + "\n")
    print(f"wrote {HERE / 'storey.ifc'} and {HERE / 'storey-layout.json'}")
