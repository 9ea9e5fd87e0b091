"""A realistic IFC building: several storeys, hundreds of elements, loaded, clustered and precomputed.

No public IFC model is downloaded: the building is made here with ``ifcopenshell.api``
(``tests/ifc_building.py``): ``--storeys`` storeys of ``--rooms NX,NY`` rooms, each with a ceiling
covering, an IfcSpace, a window in the outer wall, desks, and doors between rooms; walls styled,
slabs and ceilings on hfrad's defaults. The run times each stage and samples the memory
(the process's PSS, every 0.5 s: ``common.TreeMemorySampler``):

1. writing the IFC file (ifcopenshell.api);
2. ``hfrad.load_scene(path)`` (ifcopenshell.geom triangulation, styles, defaults; uncut);
3. clustering to ``--patches N`` (``hfrad.scene.load.cut_patches``);
4. the precompute (``hfrad.factorize(scene, eps)``);
5. the work planes of every IfcSpace (``hfrad.lighting.space_grids``).

Usage::

    PYTHONPATH=src python benchmarks/bench_buildings.py --storeys 6 --rooms 5,2 --patches 3000

Results: ``benchmarks/results/buildings.json``.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent / "tests"))
from common import TreeMemorySampler, check_load, machine, machine_line, write_json  # noqa: E402
from ifc_building import build_building  # noqa: E402


def _stage(name: str, fn, out: dict):
    t0 = time.perf_counter()
    with TreeMemorySampler(every=0.5) as mem:
        result = fn()
    out[name] = {"seconds": time.perf_counter() - t0, "peak_pss_mib": mem.peak_tree_pss / 2**20}
    print(f"{name}: {out[name]['seconds']:.2f} s, peak PSS {out[name]['peak_pss_mib']:.0f} MiB", flush=True)
    return result


def main() -> None:
    import ifcopenshell

    import hfrad
    from hfrad.lighting import space_grids
    from hfrad.scene.load import cut_patches

    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--storeys", type=int, default=6)
    p.add_argument("--rooms", default="5,2", help="rooms per storey, NX,NY")
    p.add_argument("--desks", type=int, default=2, help="desks per room")
    p.add_argument("--patches", type=int, default=3000)
    p.add_argument("--eps", type=float, default=0.02)
    p.add_argument("--name", default="buildings")
    args = p.parse_args()
    nx, ny = (int(x) for x in args.rooms.split(","))
    load = check_load()
    m = machine()
    print(machine_line(m))
    stages: dict = {}
    with tempfile.TemporaryDirectory(prefix="hfrad-building-") as tmp:
        path = Path(tmp) / "building.ifc"
        _stage("write_ifc", lambda: build_building(path, storeys=args.storeys, rooms=(nx, ny), desks=args.desks),
               stages)
        f = ifcopenshell.open(str(path))
        counts = {c: len(f.by_type(c)) for c in ("IfcBuildingStorey", "IfcWall", "IfcSlab", "IfcCovering",
                                                 "IfcWindow", "IfcDoor", "IfcFurniture", "IfcSpace",
                                                 "IfcOpeningElement")}
        elements = len(f.by_type("IfcElement"))
        print(f"{path.stat().st_size / 1024:.0f} KiB, {elements} elements: {counts}", flush=True)
        scene = _stage("load_scene", lambda: hfrad.load_scene(path), stages)
        clustered = _stage("cluster", lambda: cut_patches(scene, patches=args.patches), stages)
        fac = _stage("precompute", lambda: hfrad.factorize(clustered, eps=args.eps), stages)
        grids = _stage("space_grids", lambda: space_grids(path, scene=clustered), stages)
        size = path.stat().st_size
    result = {
        "machine": m, "load_average_at_start": load, "args": vars(args),
        "model": {"storeys": args.storeys, "rooms_per_storey": nx * ny, "elements": elements, "counts": counts,
                  "ifc_bytes": size, "triangles": scene.n_triangles, "materials": list(scene.material_names)},
        "patches": clustered.n_patches, "rank": fac.rank, "achieved_error": fac.relative_error,
        "grids": len(grids), "sensors": int(sum(len(g) for g in grids)), "stages": stages,
    }
    out = write_json(args.name, result)
    print(f"{clustered.n_patches:,} patches (asked {args.patches:,}), rank {fac.rank}, "
          f"{len(grids)} work planes; wrote {out}")


if __name__ == "__main__":
    main()
