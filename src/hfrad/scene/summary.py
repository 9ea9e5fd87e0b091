"""A scene summary: what ``hfrad info`` prints (and writes as JSON)."""

from __future__ import annotations

import numpy as np

from .cluster import cluster_summary
from .scene import Scene

#: How today's radiosity treats glazing (``hfrad info`` prints it; docs/buildings.md).
GLAZING_NOTE = ("windows are patches that reflect their reflectance; the light they transmit leaves the scene "
                "(no sky yet: nothing comes in through them)")


def scene_summary(scene: Scene) -> dict:
    """Patch count, area, bounds, materials, emitters and loader warnings of a scene."""
    materials = []
    for k, m in enumerate(scene.materials):
        mask = scene.material == k
        materials.append({
            "name": m.name,
            "reflectance": [round(float(x), 6) for x in m.reflectance],
            "emission": [round(float(x), 6) for x in m.emission],
            "transmittance": [round(float(x), 6) for x in m.transmittance],
            "patches": int(mask.sum()),
            "area": float(scene.areas[mask].sum()),
        })
    emitting = scene.emitters
    emitter_names = sorted({scene.material_names[i] for i in np.unique(scene.material[emitting])})
    power = (scene.emission * scene.areas[:, None]).sum(axis=0)
    warnings = list(scene.warnings)
    if not emitting.any():
        warnings.append("no emitter: add light with --emission NAME=R,G,B or --area-light R,G,B before solving")
    return {
        "scene": scene.name,
        "patches": scene.n_patches,
        "vertices": int(len(scene.vertices)),
        "input_faces": int(len(scene.occluder_faces)),
        "clustering": cluster_summary(scene),
        "total_area_m2": scene.total_area,
        "bounds_min": scene.bounds[0].tolist(),
        "bounds_max": scene.bounds[1].tolist(),
        "materials": materials,
        "groups": len(scene.groups),
        "emitter_patches": int(emitting.sum()),
        "emitter_materials": emitter_names,
        "emitted_power_w": power.tolist(),
        "glazing": _glazing(scene),
        "warnings": warnings,
    }


def _glazing(scene: Scene) -> dict:
    """Patches, area and materials of the windows (materials with a transmittance)."""
    glazing = [k for k, m in enumerate(scene.materials) if m.is_glazing]
    mask = np.isin(scene.material, glazing)
    return {"patches": int(mask.sum()), "area": float(scene.areas[mask].sum()),
            "materials": [scene.materials[k].name for k in glazing], "treatment": GLAZING_NOTE if glazing else None}
