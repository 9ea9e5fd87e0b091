"""Wavefront OBJ + MTL reader.

Own parser rather than trimesh's because trimesh 5.2 resolves relative
(negative) face indices wrongly (the McGuire Cornell boxes come out with
zero-area faces and a wrong bounding box) and drops ``Ke`` emission. The
parser keeps what radiosity needs: positions, polygons (fan-triangulated),
``usemtl`` materials (Kd = reflectance, Ke = emitted exitance, and for
glazing ``d`` < 1 = dissolve with ``Tf`` its filter colour: transmittance
``(1 - d) x Tf``, ``Tf`` white when absent; see docs/daylight.md) and ``g``/``o``
groups. Every error names the file and line, and quotes at most
``QUOTE_CHARS`` characters of the offending text.

Lines are UTF-8; a line that is not (an exporter writing Latin-1 names) is
read as Latin-1, so material and file names with accented letters work
either way. ``mtllib`` takes the rest of the line as one file name when
such a file exists (names with spaces), else a list of names. Material
libraries must lie in the scene's folder or below it, as glTF buffer files
must: ``mtllib ../../etc/passwd`` is refused, never read.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import SceneError
from ..validation import clip_token

#: Longest material or group name accepted (a longer one is a broken file, not a name).
MAX_NAME = 1000


def _lines(path: Path):
    """``(number, text)`` of each line of a text scene file: UTF-8, else Latin-1 per line.

    Raises
    ------
    SceneError
        A directory, an unreadable file, or UTF-16/32 text (named, with the fix).
    """
    try:
        f = open(path, "rb")
    except IsADirectoryError:
        raise SceneError(f"{path}: is a directory, not a scene file") from None
    except OSError as exc:
        raise SceneError(f"{path}: cannot read: {exc.strerror or exc}") from None
    with f:
        head = f.read(4)
        if head[:2] in (b"\xff\xfe", b"\xfe\xff") or head[:4] in (b"\x00\x00\xfe\xff", b"\xff\xfe\x00\x00"):
            raise SceneError(f"{path}: UTF-16/32 text; save the file as UTF-8 (or ASCII)")
        f.seek(0)
        for number, raw in enumerate(f, 1):
            try:
                yield number, raw.decode("utf-8")
            except UnicodeDecodeError:
                yield number, raw.decode("latin-1")


def _name(text: str, what: str, where: str) -> str:
    if len(text) > MAX_NAME:
        raise SceneError(f"{where}: {what} of {len(text):,} characters (at most {MAX_NAME}): {clip_token(text)}")
    return text


def _confined(folder: Path, name: str, where: str) -> Path:
    """``folder / name``, refused when it leaves ``folder`` (``..``, an absolute path, a symbolic link)."""
    target = folder / name
    root = folder.resolve()
    try:
        resolved = target.resolve()
    except (OSError, RuntimeError):  # a symbolic link loop
        raise SceneError(f"{where}: cannot resolve the file name {clip_token(name)}") from None
    if resolved != root and root not in resolved.parents:
        raise SceneError(f"{where}: material library {clip_token(name)} lies outside the scene's folder "
                         f"{clip_token(str(root))}; hfrad reads material files only from the scene's folder "
                         "and below it (copy the file next to the scene)")
    return target


def _floats(values: list[str], count: int, where: str) -> tuple[float, ...]:
    if len(values) < count:
        raise SceneError(f"{where}: expected {count} numbers, got {len(values)}")
    try:
        out = tuple(float(v) for v in values[:count])
    except ValueError:
        raise SceneError(f"{where}: not a number in {clip_token(' '.join(values[:count]))}") from None
    if not all(np.isfinite(out)):
        raise SceneError(f"{where}: non-finite value in {clip_token(' '.join(values[:count]))}")
    return out


def _strip_comment(line: str) -> str:
    cut = line.find("#")
    return (line if cut < 0 else line[:cut]).strip()


def read_mtl(path: Path) -> dict[str, dict]:
    """Materials of an MTL file: name -> {'reflectance': Kd, 'emission': Ke, 'line': n}, and for a
    material with ``d`` < 1 (dissolve) 'transmittance': (1 - d) x Tf (Tf: the transmission filter, white
    when absent; ``Tf`` alone, which many exporters write as 1 1 1 for opaque materials, means nothing)."""
    materials: dict[str, dict] = {}
    current = None
    for number, raw in _lines(path):
        line = _strip_comment(raw)  # also strips indentation (one McGuire MTL indents newmtl)
        if not line:
            continue
        key, *rest = line.split()
        where = f"{path}:{number}"
        if key == "newmtl":
            current = _name(" ".join(rest), "material name", where)
            materials[current] = {"reflectance": (0.0, 0.0, 0.0), "emission": (0.0, 0.0, 0.0),
                                  "line": number}
        elif key in ("Kd", "Ke"):
            if current is None:
                raise SceneError(f"{where}: {key} before any newmtl")
            if len(rest) == 2:
                raise SceneError(f"{where}: {key} needs one number (grey) or three (R G B), got two: "
                                 f"{clip_token(' '.join(rest))}")
            rgb = rest if len(rest) >= 3 else rest * 3  # 'Kd 0.5' means grey
            materials[current]["reflectance" if key == "Kd" else "emission"] = _floats(rgb, 3, where)
        elif key in ("d", "Tf"):
            if current is None:
                raise SceneError(f"{where}: {key} before any newmtl")
            rest = [r for r in rest if r != "-halo"]           # 'd -halo 0.5': the halo form, same number
            rgb = rest if (key == "d" or len(rest) >= 3) else rest * 3
            value = _floats(rgb[:1] if key == "d" else rgb[:3], 1 if key == "d" else 3, where)
            if not all(0.0 <= v <= 1.0 for v in value):
                raise SceneError(f"{where}: {key} must lie in [0, 1], got {' '.join(rest)}")
            materials[current]["dissolve" if key == "d" else "filter"] = value
    for props in materials.values():
        dissolve = props.pop("dissolve", (1.0,))[0]
        tf = props.pop("filter", (1.0, 1.0, 1.0))
        if dissolve < 1.0:
            props["transmittance"] = tuple((1.0 - dissolve) * t for t in tf)
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
    material_index: dict[str, int] = {}
    group_index_of: dict[str, int] = {"default": 0}
    for number, raw in _lines(path):
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
            name = _name(rest.strip(), "material name", where)
            if name not in material_index:
                material_index[name] = len(material_names)
                material_names.append(name)
            mat_index = material_index[name]
        elif key in ("g", "o"):
            name = _name(rest.strip() or "default", "group name", where)
            if name not in group_index_of:
                group_index_of[name] = len(group_names)
                group_names.append(name)
            group_index = group_index_of[name]
        elif key == "mtllib":
            for lib in _library_names(path.parent, rest.strip()):
                mtl = _confined(path.parent, lib, where)
                if _is_file(mtl):
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


def _is_file(path: Path) -> bool:
    try:
        return path.is_file()
    except OSError:  # a name too long for the file system, say
        return False


def _library_names(folder: Path, rest: str) -> list[str]:
    """The file names of an ``mtllib`` line: the whole rest when it names a file (spaces in the
    name), else its words (several libraries)."""
    if not rest:
        return []
    if " " in rest or "\t" in rest:
        if _is_file(folder / rest):
            return [rest]
    return rest.split()


def _vertex_index(token: str, count: int, where: str) -> int:
    """0-based index of an ``f`` corner token ``v``, ``v/vt``, ``v//vn`` or ``v/vt/vn``.

    A negative index counts back from the last vertex read so far (-1 = last).
    """
    head = token.split("/", 1)[0]
    try:
        k = int(head)
    except ValueError:
        raise SceneError(f"{where}: bad vertex index {clip_token(token)}") from None
    index = k - 1 if k > 0 else count + k
    if k == 0 or not 0 <= index < count:
        shown = head if len(head) <= 40 else clip_token(head)
        raise SceneError(f"{where}: vertex index {shown} out of range "
                         f"(only {count} vertices read so far)")
    return index
