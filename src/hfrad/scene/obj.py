"""Wavefront OBJ + MTL reader.

Own parser rather than trimesh's because trimesh 5.2 resolves relative
(negative) face indices wrongly (the McGuire Cornell boxes come out with
zero-area faces and a wrong bounding box) and drops ``Ke`` emission. The
parser keeps what radiosity needs: positions, polygons (fan-triangulated),
``usemtl`` materials (Kd = reflectance, Ke = emitted exitance) and ``g``/``o``
groups. Every error names the file and line.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import SceneError


def _floats(values: list[str], count: int, where: str) -> tuple[float, ...]:
    if len(values) < count:
        raise SceneError(f"{where}: expected {count} numbers, got {len(values)}")
    try:
        out = tuple(float(v) for v in values[:count])
    except ValueError:
        raise SceneError(f"{where}: not a number in {' '.join(values[:count])!r}") from None
    if not all(np.isfinite(out)):
        raise SceneError(f"{where}: non-finite value in {' '.join(values[:count])!r}")
    return out


def _strip_comment(line: str) -> str:
    cut = line.find("#")
    return (line if cut < 0 else line[:cut]).strip()


def read_mtl(path: Path) -> dict[str, dict]:
    """Materials of an MTL file: name -> {'reflectance': Kd, 'emission': Ke, 'line': n}."""
    materials: dict[str, dict] = {}
    current = None
    with open(path, encoding="utf-8", errors="replace") as f:
        for number, raw in enumerate(f, 1):
            line = _strip_comment(raw)  # also strips indentation (one McGuire MTL indents newmtl)
            if not line:
                continue
            key, *rest = line.split()
            where = f"{path}:{number}"
            if key == "newmtl":
                current = " ".join(rest)
                materials[current] = {"reflectance": (0.0, 0.0, 0.0), "emission": (0.0, 0.0, 0.0),
                                      "line": number}
            elif key in ("Kd", "Ke"):
                if current is None:
                    raise SceneError(f"{where}: {key} before any newmtl")
                rgb = rest if len(rest) >= 3 else rest * 3  # 'Kd 0.5' means grey
                materials[current]["reflectance" if key == "Kd" else "emission"] = _floats(rgb, 3, where)
    return materials


def read_obj(path: Path) -> dict:
    """Parse an OBJ file.

    Returns
    -------
    dict with ``vertices`` (v, 3), ``faces`` (n, 3) int, ``face_material``
    (n,) int into ``material_names`` (-1 = no material), ``materials`` (name ->
    properties from the MTL files), ``face_group`` (n,) int into ``group_names``,
    ``missing_materials`` (names used but not defined) and ``missing_mtl`` (files).
    """
    path = Path(path)
    vertices: list[tuple[float, float, float]] = []
    faces: list[tuple[int, int, int]] = []
    face_material: list[int] = []
    face_group: list[int] = []
    material_names: list[str] = []
    group_names: list[str] = ["default"]
    materials: dict[str, dict] = {}
    missing_mtl: list[str] = []
    mat_index, group_index = -1, 0
    with open(path, encoding="utf-8", errors="replace") as f:
        for number, raw in enumerate(f, 1):
            line = _strip_comment(raw)
            if not line:
                continue
            key, *tail = line.split(None, 1)  # fields may be separated by tabs
            rest = tail[0] if tail else ""
            where = f"{path}:{number}"
            if key == "v":
                vertices.append(_floats(rest.split(), 3, where))
            elif key == "f":
                corners = [_vertex_index(tok, len(vertices), where) for tok in rest.split()]
                if len(corners) < 3:
                    raise SceneError(f"{where}: a face needs at least 3 vertices, got {len(corners)}")
                for k in range(1, len(corners) - 1):  # fan triangulation
                    faces.append((corners[0], corners[k], corners[k + 1]))
                    face_material.append(mat_index)
                    face_group.append(group_index)
            elif key == "usemtl":
                name = rest.strip()
                if name not in material_names:
                    material_names.append(name)
                mat_index = material_names.index(name)
            elif key in ("g", "o"):
                name = rest.strip() or "default"
                if name not in group_names:
                    group_names.append(name)
                group_index = group_names.index(name)
            elif key == "mtllib":
                for lib in rest.split():
                    mtl = path.parent / lib
                    if mtl.is_file():
                        materials.update(read_mtl(mtl))
                    else:
                        missing_mtl.append(str(mtl))
    if not faces:
        raise SceneError(f"{path}: no faces found (is this an OBJ file?)")
    return {
        "vertices": np.array(vertices, dtype=np.float64).reshape(-1, 3),
        "faces": np.array(faces, dtype=np.int64),
        "face_material": np.array(face_material, dtype=np.int64),
        "material_names": material_names,
        "materials": materials,
        "face_group": np.array(face_group, dtype=np.int64),
        "group_names": group_names,
        "missing_mtl": missing_mtl,
        "missing_materials": [m for m in material_names if m not in materials],
    }


def _vertex_index(token: str, count: int, where: str) -> int:
    """0-based index of an ``f`` corner token ``v``, ``v/vt``, ``v//vn`` or ``v/vt/vn``.

    A negative index counts back from the last vertex read so far (-1 = last).
    """
    head = token.split("/", 1)[0]
    try:
        k = int(head)
    except ValueError:
        raise SceneError(f"{where}: bad vertex index {token!r}") from None
    index = k - 1 if k > 0 else count + k
    if k == 0 or not 0 <= index < count:
        raise SceneError(f"{where}: vertex index {k} out of range (only {count} vertices read so far)")
    return index
