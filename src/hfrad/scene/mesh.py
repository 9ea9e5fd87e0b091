"""PLY and glTF/GLB readers through trimesh.

Each reader returns the same plain dict as :func:`hfrad.scene.obj.read_obj`, so
the scene builder does not care where a mesh came from.

PLY: per-face float properties ``reflectance_r/g/b`` and ``emission_r/g/b``
are used when present, else per-face ``red/green/blue`` colours (uchar,
/255) as reflectance; faces with neither get the default reflectance.

glTF/GLB: each primitive's material gives reflectance = baseColorFactor (RGB)
and emission = emissiveFactor x KHR_materials_emissive_strength (W/m^2).
Node transforms are applied.
"""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np

from ..errors import SceneError


def _trimesh():
    try:
        import trimesh
    except ImportError as exc:  # pragma: no cover
        raise ImportError("reading PLY/glTF needs trimesh: pip install trimesh") from exc
    return trimesh


def read_ply(path: Path) -> dict:
    """Parse a PLY file (triangles or polygons) with trimesh."""
    trimesh = _trimesh()
    try:
        mesh = trimesh.load(str(path), process=False, force="mesh")
    except Exception as exc:
        raise SceneError(f"{path}: could not read as PLY: {exc}") from None
    faces = np.asarray(mesh.faces, dtype=np.int64)
    if not len(faces):
        raise SceneError(f"{path}: no faces found")
    raw = mesh.metadata.get("_ply_raw", {}).get("face", {}).get("data")
    names = raw.dtype.names if raw is not None and raw.dtype.names else ()
    rho = emission = None
    from_colour = False
    if all(f"reflectance_{c}" in names for c in "rgb") and len(raw) == len(faces):
        rho = np.stack([raw[f"reflectance_{c}"] for c in "rgb"], axis=1).astype(np.float64).reshape(-1, 3)
    elif all(c in names for c in ("red", "green", "blue")) and len(raw) == len(faces):
        rho = np.stack([raw[c] for c in ("red", "green", "blue")], axis=1).astype(np.float64).reshape(-1, 3) / 255.0
        from_colour = True
    if all(f"emission_{c}" in names for c in "rgb") and len(raw) == len(faces):
        emission = np.stack([raw[f"emission_{c}"] for c in "rgb"], axis=1).astype(np.float64).reshape(-1, 3)
    return _per_face_materials(mesh.vertices, faces, rho, emission, from_colour)


def _per_face_materials(vertices, faces, rho, emission, from_colour: bool) -> dict:
    """Group faces by their (reflectance, emission) into materials named ``ply_K``."""
    n = len(faces)
    if rho is None and emission is None:
        face_material = np.full(n, -1, np.int64)
        material_names: list[str] = []
        materials: dict[str, dict] = {}
    else:
        props = np.hstack([np.full((n, 3), np.nan) if rho is None else rho,
                           np.zeros((n, 3)) if emission is None else emission])
        unique, face_material = np.unique(props, axis=0, return_inverse=True)
        material_names = [f"ply_{k}" for k in range(len(unique))]
        materials = {}
        for name, row in zip(material_names, unique):
            entry = {"emission": tuple(row[3:])}
            if not np.isnan(row[:3]).any():
                entry["reflectance"] = tuple(row[:3])
                entry["from_colour"] = from_colour
            materials[name] = entry
    return {
        "vertices": np.asarray(vertices, dtype=np.float64), "faces": faces,
        "face_material": np.asarray(face_material, np.int64).reshape(n), "material_names": material_names,
        "materials": materials, "face_group": np.zeros(n, np.int64), "group_names": ["default"],
        "missing_mtl": [], "missing_materials": [],
    }


def _emissive_strengths(path: Path) -> dict[str, float]:
    """KHR_materials_emissive_strength per material name (trimesh ignores it)."""
    try:
        data = path.read_bytes()
        if data[:4] == b"glTF":
            length = struct.unpack_from("<I", data, 12)[0]
            doc = json.loads(data[20:20 + length])
        else:
            doc = json.loads(data)
    except Exception:
        return {}
    out = {}
    for k, mat in enumerate(doc.get("materials", [])):
        ext = mat.get("extensions", {}).get("KHR_materials_emissive_strength", {})
        out[mat.get("name", f"material_{k}")] = float(ext.get("emissiveStrength", 1.0))
    return out


def read_gltf(path: Path) -> dict:
    """Parse a glTF/GLB file with trimesh, keeping one material per primitive."""
    trimesh = _trimesh()
    try:
        scene = trimesh.load(str(path), force="scene")
    except Exception as exc:
        raise SceneError(f"{path}: could not read as glTF: {exc}") from None
    strengths = _emissive_strengths(path)
    vertices, faces, face_material, face_group = [], [], [], []
    material_names: list[str] = []
    materials: dict[str, dict] = {}
    group_names: list[str] = []
    offset = 0
    for node in scene.graph.nodes_geometry:
        transform, geometry_name = scene.graph[node]
        mesh = scene.geometry[geometry_name]
        if not hasattr(mesh, "faces") or not len(mesh.faces):
            continue
        v = trimesh.transformations.transform_points(mesh.vertices, transform)
        name = _material_entry(mesh, materials, strengths, len(material_names))
        if name not in material_names:
            material_names.append(name)
        if node not in group_names:
            group_names.append(node)
        vertices.append(v)
        faces.append(np.asarray(mesh.faces, np.int64) + offset)
        face_material.append(np.full(len(mesh.faces), material_names.index(name)))
        face_group.append(np.full(len(mesh.faces), group_names.index(node)))
        offset += len(v)
    if not faces:
        raise SceneError(f"{path}: no triangle meshes found")
    return {
        "vertices": np.concatenate(vertices), "faces": np.concatenate(faces),
        "face_material": np.concatenate(face_material), "material_names": material_names,
        "materials": materials, "face_group": np.concatenate(face_group), "group_names": group_names,
        "missing_mtl": [], "missing_materials": [],
    }


def _material_entry(mesh, materials: dict, strengths: dict, index: int) -> str:
    mat = getattr(getattr(mesh, "visual", None), "material", None)
    name = getattr(mat, "name", None) or f"material_{index}"
    if name in materials:
        return name
    entry: dict = {}
    base = getattr(mat, "baseColorFactor", None)
    if base is not None:
        base = np.asarray(base, dtype=np.float64)[:3]
        entry["reflectance"] = tuple(base / 255.0 if base.max() > 1.0 else base)
        entry["from_colour"] = True  # a colour of 1.0 is common: clamp it, don't reject it
    emissive = getattr(mat, "emissiveFactor", None)
    if emissive is not None:
        entry["emission"] = tuple(np.asarray(emissive, np.float64)[:3] * strengths.get(name, 1.0))
    materials[name] = entry
    return name
