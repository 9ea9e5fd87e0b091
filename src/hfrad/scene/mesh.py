"""PLY and glTF/GLB readers through trimesh.

Each reader returns the same plain dict as :func:`hfrad.scene.obj.read_obj`, so
the scene builder does not care where a mesh came from.

PLY (ASCII or binary): per-face float properties ``reflectance_r/g/b`` and
``emission_r/g/b`` are used when present, else per-face ``red/green/blue``
colours (uchar, /255) as reflectance; faces with neither get the default
reflectance. Polygons are fan-triangulated here (each triangle keeps its
polygon's properties). A file holding fewer elements than its header
declares (truncated), a non-finite property or a vertex index out of range
is refused with one line naming the file and the element.

glTF/GLB: each primitive's material gives reflectance = baseColorFactor (RGB)
and emission = emissiveFactor x KHR_materials_emissive_strength (W/m^2),
read from the file's JSON (a non-numeric or non-finite factor is refused).
Node transforms are applied. Buffers and images are read only from the
file's folder and below (trimesh's resolver refuses ``../`` escapes).
"""

from __future__ import annotations

import json
import math
import struct
from pathlib import Path

import numpy as np

from ..errors import SceneError
from ..validation import QUOTE_CHARS, clip_token


def _short(text) -> str:
    """An error text from a library cut to about QUOTE_CHARS characters (it may quote file data)."""
    text = " ".join(str(text).split())
    return text if len(text) <= QUOTE_CHARS else text[:QUOTE_CHARS] + f"... ({len(text):,} characters)"


def _check_file(path: Path) -> None:
    if path.is_dir():
        raise SceneError(f"{path}: is a directory, not a scene file")
    try:
        with open(path, "rb"):
            pass
    except OSError as exc:
        raise SceneError(f"{path}: cannot read: {exc.strerror or exc}") from None


_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


def _binary_ply(path: Path, trimesh_error: Exception) -> dict:
    """A binary PLY that trimesh could not read, element by element: ``{element: {"length", "data"}}``
    in the layout of trimesh's raw PLY (``data`` is ``{property: array}``; a list property gives an
    object array of index arrays). Elements without lists are read in one go; those with lists
    row by row in Python (one ``np.frombuffer`` call per property and row).

    Raises
    ------
    SceneError
        Not a binary PLY (with trimesh's complaint), an unknown type, or fewer bytes than the
        header's elements need (truncated).
    """
    data = path.read_bytes()
    end = data.find(b"end_header")
    newline = data.find(b"\n", end)
    if not data.startswith(b"ply") or end < 0 or newline < 0:
        raise SceneError(f"{path}: could not read as PLY: {_short(trimesh_error)}")
    fmt, elements = None, []
    for line in data[:end].decode("ascii", "replace").splitlines():
        words = line.split()
        if len(words) >= 2 and words[0] == "format":
            fmt = words[1]
        elif len(words) >= 3 and words[0] == "element" and words[2].isdigit():
            elements.append((words[1], int(words[2]), []))
        elif len(words) >= 3 and words[0] == "property" and elements:
            elements[-1][2].append(tuple(words[1:]))
    if fmt not in ("binary_little_endian", "binary_big_endian"):
        raise SceneError(f"{path}: could not read as PLY: {_short(trimesh_error)}")
    order = "<" if fmt == "binary_little_endian" else ">"

    def dtype(name: str, where: str) -> np.dtype:
        if name not in _PLY_TYPES:
            raise SceneError(f"{path}: unknown PLY type {clip_token(name)} in {where}")
        return np.dtype(order + _PLY_TYPES[name])

    pos, out = newline + 1, {}
    for name, count, props in elements:
        where = f"element {clip_token(name)}"
        if all(p[0] != "list" for p in props):
            rec = np.dtype([(p[-1], dtype(p[0], where)) for p in props if len(p) >= 2])
            if pos + rec.itemsize * count > len(data):
                raise SceneError(f"{path}: truncated PLY: {where} needs {rec.itemsize * count:,} bytes, "
                                 f"{len(data) - pos:,} are left")
            arr = np.frombuffer(data, rec, count, pos)
            pos += rec.itemsize * count
            out[name] = {"length": count, "data": {n: arr[n] for n in rec.names}}
            continue
        layout = [(p[-1], dtype(p[1], where), dtype(p[2], where)) if p[0] == "list" and len(p) >= 4
                  else (p[-1], None, dtype(p[0], where)) for p in props]
        smallest = sum((c if c is not None else t).itemsize for n, c, t in layout)  # a row of empty lists
        if pos + smallest * count > len(data):  # before allocating: the header may claim 1e11 rows
            raise SceneError(f"{path}: truncated PLY: {where} declares {count:,} rows, which need at least "
                             f"{smallest * count:,} bytes; {len(data) - pos:,} are left")
        columns = {n: np.empty(count, dtype=object if c is not None else t) for n, c, t in layout}
        try:
            for row in range(count):
                for n, c, t in layout:
                    if c is None:
                        columns[n][row] = np.frombuffer(data, t, 1, pos)[0]
                        pos += t.itemsize
                    else:
                        k = int(np.frombuffer(data, c, 1, pos)[0])
                        pos += c.itemsize
                        columns[n][row] = np.frombuffer(data, t, k, pos).astype(np.int64)
                        pos += k * t.itemsize
        except ValueError:  # frombuffer past the end
            raise SceneError(f"{path}: truncated PLY: {where} ends after {row:,} of {count:,} rows") from None
        out[name] = {"length": count, "data": columns}
    return out


def _ply_columns(element: dict) -> dict:
    """{property: array} of one element of trimesh's raw PLY (a structured array when binary, a dict when ASCII)."""
    data = element.get("data")
    if data is None:
        return {}
    if isinstance(data, dict):
        return dict(data)
    return {name: data[name] for name in (data.dtype.names or ())}


def _ply_polygons(indices, path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Fan triangles ``(t, 3)`` of PLY ``vertex_indices`` and the polygon ``(t,)`` each comes from."""
    arr = np.asarray(indices) if not isinstance(indices, np.ndarray) else indices
    if arr.dtype.names and len(arr.dtype.names) == 2:  # binary, one length for all: (count, indices) records
        arr = arr[arr.dtype.names[1]]
    if arr.dtype != object and arr.ndim == 1 and len(arr):
        raise SceneError(f"{path}: faces have 1 vertex each; a face needs at least 3")
    if arr.dtype != object and arr.ndim == 2:
        k = arr.shape[1]
        if k < 3:
            raise SceneError(f"{path}: faces have {k} vertices; a face needs at least 3")
        tris = np.stack([np.stack([arr[:, 0], arr[:, j], arr[:, j + 1]], axis=1) for j in range(1, k - 1)], axis=1)
        return tris.reshape(-1, 3).astype(np.int64), np.repeat(np.arange(len(arr)), k - 2)
    tris, owner = [], []
    for i, row in enumerate(arr):
        row = np.asarray(row).reshape(-1)
        if len(row) < 3:
            raise SceneError(f"{path}: face {i} has {len(row)} vertices; a face needs at least 3")
        for j in range(1, len(row) - 1):
            tris.append((row[0], row[j], row[j + 1]))
            owner.append(i)
    return np.asarray(tris, np.int64).reshape(-1, 3), np.asarray(owner, np.int64)


def _trimesh():
    try:
        import trimesh
    except ImportError as exc:  # pragma: no cover
        raise ImportError("reading PLY/glTF needs trimesh: pip install trimesh") from exc
    return trimesh


def read_ply(path: Path) -> dict:
    """Parse a PLY file (ASCII or binary; triangles or polygons) with trimesh's PLY parser.

    Raises
    ------
    SceneError
        Not a PLY file, truncated (fewer elements than the header declares),
        a non-finite vertex or face property, a vertex index out of range,
        no faces; the message names the file and the element.
    """
    trimesh = _trimesh()
    _check_file(path)
    try:
        mesh = trimesh.load(str(path), process=False, force="mesh")
    except Exception as exc:
        # trimesh reads binary lists of one length only ("PLY is unexpected length!" for a mix
        # of triangles and quads): read such a file element by element instead
        raw = _binary_ply(path, exc)
        mesh_faces = np.zeros((0, 3), np.int64)
        vertex = raw.get("vertex", {}).get("data", {})
        if not all(c in vertex for c in "xyz"):
            raise SceneError(f"{path}: no 'vertex' element with x, y and z") from None
        vertices = np.stack([np.asarray(vertex[c], np.float64).reshape(-1) for c in "xyz"], axis=1)
    else:
        raw = mesh.metadata.get("_ply_raw", {})
        mesh_faces = np.asarray(mesh.faces, dtype=np.int64).reshape(-1, 3)
        vertices = np.asarray(mesh.vertices, dtype=np.float64).reshape(-1, 3)
    for element, props in raw.items():  # an ASCII file cut short parses without complaint
        declared = props.get("length")
        for name, column in _ply_columns(props).items():
            if declared is not None and len(column) != declared:
                raise SceneError(f"{path}: truncated or malformed PLY: the header declares {declared:,} "
                                 f"'{element}' elements, the file holds {len(column):,} "
                                 f"(property {clip_token(name)})")
    columns = _ply_columns(raw.get("face", {}))
    if "vertex_indices" in columns or "vertex_index" in columns:
        faces, owner = _ply_polygons(columns.get("vertex_indices", columns.get("vertex_index")), path)
    else:  # not a PLY layout we know: trimesh's triangles, one per face
        faces = mesh_faces
        owner = np.arange(len(faces))
    if not len(faces):
        raise SceneError(f"{path}: no faces found")
    if not np.isfinite(vertices).all():
        bad = int(np.flatnonzero(~np.isfinite(vertices).all(axis=1))[0])
        raise SceneError(f"{path}: vertex {bad} has a non-finite coordinate {tuple(vertices[bad].tolist())}")
    bad = (faces < 0) | (faces >= len(vertices))
    if bad.any():
        t = int(np.flatnonzero(bad.any(axis=1))[0])
        raise SceneError(f"{path}: face {int(owner[t])} uses vertex {int(faces[t][bad[t]][0])}, "
                         f"but the file has {len(vertices):,} vertices (0..{len(vertices) - 1})")

    def per_face(names, scale=1.0):
        if not all(n in columns for n in names):
            return None
        values = np.stack([np.asarray(columns[n], np.float64).reshape(-1) for n in names], axis=1) / scale
        finite = np.isfinite(values).all(axis=1)
        if not finite.all():
            i = int(np.flatnonzero(~finite)[0])
            hint = " (a PLY 'float' holds at most 3.4e38)" if np.isinf(values[i]).any() else ""
            raise SceneError(f"{path}: face {i} has a non-finite {'/'.join(names)}: {tuple(values[i].tolist())}"
                             + hint)
        return values[owner]

    rho = per_face([f"reflectance_{c}" for c in "rgb"])
    from_colour = False
    if rho is None:
        rho = per_face(["red", "green", "blue"], 255.0)
        from_colour = rho is not None
    emission = per_face([f"emission_{c}" for c in "rgb"])
    return _per_face_materials(vertices, faces, rho, emission, from_colour)


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


def _number_list(value, size: tuple[int, ...], where: str) -> tuple[float, ...]:
    ok = (isinstance(value, list) and len(value) in size
          and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in value)
          and all(math.isfinite(x) for x in value))
    if not ok:
        raise SceneError(f"{where}: expected {' or '.join(map(str, size))} finite numbers, got "
                         f"{clip_token(json.dumps(value)[:10 * QUOTE_CHARS])}")
    return tuple(float(x) for x in value)


def _gltf_materials(path: Path) -> dict[str, dict]:
    """Per material name, the factors as the file's JSON states them (trimesh ignores
    KHR_materials_emissive_strength and turns baseColorFactor into 8-bit colours, NaN into 0).

    Returns ``{name: {"base": (4,) or None, "emissive": (3,) or None, "strength": float}}``.

    Raises
    ------
    SceneError
        A factor that is not a list of finite numbers, or a strength that is
        not a finite number >= 0 (material and field named).
    """
    try:
        data = path.read_bytes()
        if data[:4] == b"glTF":
            length = struct.unpack_from("<I", data, 12)[0]
            doc = json.loads(data[20:20 + length])
        else:
            doc = json.loads(data)
    except Exception:  # trimesh read the file: its JSON is fine; anything odd here is not ours to judge
        return {}
    mats = doc.get("materials", []) if isinstance(doc, dict) else []
    out = {}
    for k, mat in enumerate(mats if isinstance(mats, list) else []):
        if not isinstance(mat, dict):
            continue
        name = mat.get("name", f"material_{k}")
        where = f"{path}: material {clip_token(name)}"
        pbr = mat.get("pbrMetallicRoughness", {})
        base = pbr.get("baseColorFactor") if isinstance(pbr, dict) else None
        emissive = mat.get("emissiveFactor")
        ext = mat.get("extensions", {})
        strength = (ext.get("KHR_materials_emissive_strength", {}) if isinstance(ext, dict) else {})
        strength = strength.get("emissiveStrength", 1.0) if isinstance(strength, dict) else 1.0
        if isinstance(strength, bool) or not isinstance(strength, (int, float)) or not (
                math.isfinite(strength) and strength >= 0):
            raise SceneError(f"{where}: emissiveStrength must be a finite number >= 0, got "
                             f"{clip_token(json.dumps(strength)[:10 * QUOTE_CHARS])}")
        out[name] = {"base": None if base is None else _number_list(base, (4,), f"{where}: baseColorFactor"),
                     "emissive": None if emissive is None else _number_list(emissive, (3,),
                                                                             f"{where}: emissiveFactor"),
                     "strength": float(strength)}
    return out


def read_gltf(path: Path) -> dict:
    """Parse a glTF/GLB file with trimesh, keeping one material per primitive."""
    trimesh = _trimesh()
    _check_file(path)
    try:
        scene = trimesh.load(str(path), force="scene")
    except Exception as exc:
        raise SceneError(f"{path}: could not read as glTF: {_short(exc)}") from None
    strengths = _gltf_materials(path)
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
    stated = strengths.get(name, {})
    base = getattr(mat, "baseColorFactor", None)
    if stated.get("base") is not None:
        base = np.asarray(stated["base"], dtype=np.float64)[:3]  # the file's floats, not 8-bit colours
    elif base is not None:
        base = np.asarray(base, dtype=np.float64)[:3]
        base = base / 255.0 if base.max() > 1.0 else base
    if base is not None:
        entry["reflectance"] = tuple(float(x) for x in base)
        entry["from_colour"] = True  # a colour of 1.0 is common: clamp it, don't reject it
    emissive = getattr(mat, "emissiveFactor", None)
    if stated.get("emissive") is not None:
        emissive = stated["emissive"]
    if emissive is not None:
        entry["emission"] = tuple(float(x) for x in np.asarray(emissive, np.float64)[:3] * stated.get("strength", 1.0))
    materials[name] = entry
    return name
