"""IFC (BIM) reader: element geometry, reflectances from surface styles or class defaults, windows, spaces.

Geometry comes from ``ifcopenshell.geom`` in world coordinates, in metres
(ifcopenshell converts the model's length unit), openings cut. Each element's
faces take:

- the reflectance of their surface style where the model has one (the style's
  diffuse or surface colour, clamped to 0.99 like an OBJ colour);
- glazing where the style is transparent: transmittance = the style's
  transparency, reflectance :data:`GLAZING_REFLECTANCE` (a transparent style's
  colour is a display tint, not a reflectance);
- else the default of their element class, :data:`DEFAULTS` (a slab's upward
  faces are a floor, its downward faces a ceiling, its edges walls; a ceiling
  covering is all ceiling; a roof's upward faces are ``roof``; an unstyled
  ``IfcWindow`` is glazing). Each default used is listed in the scene's warnings
  (``hfrad info``).

``IfcSpace`` and ``IfcOpeningElement`` are not surfaces: spaces give the
work-plane grids (:func:`read_spaces`, used by :mod:`hfrad.lighting.spaces`).
Errors and warnings name the entity (``#123 IfcWall 'W-01'``). The model is
Z-up; it is turned to y-up (:func:`hfrad.scene.polygons.z_up_to_y_up`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import SceneError
from ..validation import clip_token
from .polygons import Z_UP_NOTE, z_up_to_y_up

__all__ = ["read_ifc", "read_spaces", "Space", "DEFAULTS", "GLAZING", "MAX_ELEMENTS", "MAX_TRIANGLES"]

#: Most building elements (products with geometry) a model may have.
MAX_ELEMENTS = 200_000

#: Most triangles a model may have.
MAX_TRIANGLES = 20_000_000

#: Most bytes of an IFC file (checked before ifcopenshell parses it).
MAX_FILE_BYTES = 4 * 2**30

#: Reflectance of glazing (a clear pane at normal incidence, Radiance's glass with n = 1.52).
GLAZING_REFLECTANCE = 0.08

#: Unstyled window glazing: (reflectance, transmittance) of clear double glazing.
GLAZING = (GLAZING_REFLECTANCE, 0.78)

#: Default reflectance by role (hfrad material name), for faces with no surface style
#: (EN 12464-1's usual ranges: ceiling 0.7-0.9, walls 0.5-0.8, floor 0.2-0.4, furniture 0.2-0.7).
DEFAULTS = {"ceiling": 0.7, "wall": 0.5, "floor": 0.2, "door": 0.4, "furniture": 0.4, "roof": 0.3, "other": 0.5}

#: The role of each element class (subclasses through ifcopenshell's ``is_a``), checked in order.
ROLES = (("IfcWindow", "window"), ("IfcDoor", "door"), ("IfcSlab", "slab"), ("IfcRoof", "roof"),
         ("IfcCovering", "covering"), ("IfcWall", "wall"), ("IfcCurtainWall", "wall"), ("IfcColumn", "wall"),
         ("IfcBeam", "wall"), ("IfcFurnishingElement", "furniture"), ("IfcFurniture", "furniture"))

#: Classes that are not surfaces.
SKIPPED = ("IfcSpace", "IfcOpeningElement", "IfcVirtualElement", "IfcAnnotation", "IfcGrid", "IfcSite")


def _ifcopenshell():
    try:
        import ifcopenshell
        import ifcopenshell.geom
    except ImportError:
        raise ImportError("reading IFC files needs ifcopenshell: pip install ifcopenshell "
                          "(or pip install 'hfrad[buildings]')") from None
    return ifcopenshell


def _open(path: Path):
    ifcopenshell = _ifcopenshell()
    try:
        size = path.stat().st_size
    except OSError as exc:
        raise SceneError(f"{path}: cannot read: {exc.strerror or exc}") from None
    if path.is_dir():
        raise SceneError(f"{path}: is a directory, not a scene file")
    if size > MAX_FILE_BYTES:
        raise SceneError(f"{path}: {size / 2**30:.1f} GiB; hfrad reads IFC files of at most "
                         f"{MAX_FILE_BYTES / 2**30:.0f} GiB")
    try:
        return ifcopenshell.open(str(path))
    except Exception as exc:  # noqa: BLE001 - ifcopenshell raises its own and RuntimeError for broken files
        raise SceneError(f"{path}: not a readable IFC file: {clip_token(str(exc) or type(exc).__name__)}") from None


def _label(element) -> str:
    name = getattr(element, "Name", None)
    return f"#{element.id()} {element.is_a()}" + (f" {clip_token(name, 60)}" if name else "")


def _iterate(ifc, path: Path, include=None, exclude=None):
    """(element, vertices (v, 3) Z-up m, faces (t, 3), material ids (t,), materials) of each shape."""
    ifcopenshell = _ifcopenshell()
    settings = ifcopenshell.geom.settings()
    settings.set("use-world-coords", True)
    kwargs = {"include": include} if include is not None else {"exclude": exclude}
    iterator = ifcopenshell.geom.iterator(settings, ifc, 1, **kwargs)
    if not iterator.initialize():
        return
    while True:
        shape = iterator.get()
        g = shape.geometry
        yield (ifc.by_id(shape.id), np.asarray(g.verts, np.float64).reshape(-1, 3),
               np.asarray(g.faces, np.int64).reshape(-1, 3), np.asarray(g.material_ids, np.int64), g.materials)
        if not iterator.next():
            break


def _role(element) -> str:
    kind = str(getattr(element, "PredefinedType", None) or "")
    for cls, role in ROLES:
        if element.is_a(cls):
            if role == "slab" and kind == "ROOF":
                return "roof"
            if role == "covering":  # a ceiling's faces are all ceiling (its top is no floor to light)
                return {"CEILING": "ceiling", "FLOORING": "floor"}.get(kind, "wall")
            return role
    return "other"


def _style_props(ifc, style, where: str, notes: list[str]) -> tuple[str, dict]:
    """(hfrad material name, properties) of a styled ifcopenshell material."""
    entity = ifc.by_id(style.instance_id())
    name = getattr(entity, "Name", None) or style.name
    transparency = float(style.transparency)
    colour = np.array(style.diffuse.components if hasattr(style.diffuse, "components") else style.diffuse,
                      dtype=np.float64).reshape(-1)[:3]
    if not np.isfinite(colour).all() or (colour < 0).any():
        raise SceneError(f"{where}: surface style {clip_token(name)} has the colour {tuple(colour.tolist())}")
    if math.isfinite(transparency) and transparency > 0:
        tau = min(transparency, 1.0 - GLAZING_REFLECTANCE)
        notes.append(f"surface style {name} ({where}) is transparent ({transparency:g}): read as glazing, "
                     f"transmittance {tau:g}, reflectance {GLAZING_REFLECTANCE:g}")
        return name, {"reflectance": (GLAZING_REFLECTANCE,) * 3, "transmittance": (tau,) * 3, "where": where}
    if colour.max() > 0.99:
        notes.append(f"surface style {name} ({where}): colour {tuple(colour.round(3).tolist())} clamped to "
                     "reflectance <= 0.99")
    return name, {"reflectance": tuple(float(x) for x in np.minimum(colour, 0.99)), "where": where}


def _default_roles(role: str, normals_z: np.ndarray) -> np.ndarray:
    """(t,) hfrad default material names of an unstyled element's faces."""
    if role in ("slab", "roof"):  # up: a floor (a roof's outside); down: a ceiling; edges: as walls
        return np.where(normals_z > 0.5, "floor" if role == "slab" else "roof",
                        np.where(normals_z < -0.5, "ceiling", "wall"))
    return np.full(len(normals_z), role if role in DEFAULTS or role == "window" else "other")


def _default_props(name: str) -> dict:
    if name == "window":
        return {"reflectance": (GLAZING[0],) * 3, "transmittance": (GLAZING[1],) * 3, "where": "hfrad default"}
    return {"reflectance": (DEFAULTS[name],) * 3, "where": "hfrad default"}


def _check_counts(ifc, path: Path) -> None:
    products = ifc.by_type("IfcProduct")
    if len(products) > MAX_ELEMENTS:
        raise SceneError(f"{path}: {len(products):,} building elements; hfrad reads at most {MAX_ELEMENTS:,}")


def read_ifc(path: Path) -> dict:
    """Parse an IFC file into the loader's plain dict (as :func:`hfrad.scene.obj.read_obj`).

    Returns
    -------
    dict
        ``vertices`` (v, 3) y-up metres, ``faces``, ``face_material`` /
        ``material_names`` / ``materials`` (style names, or the defaults
        ``floor``, ``ceiling``, ``wall``, ``door``, ``furniture``, ``other``,
        ``window``), ``face_group`` / ``group_names`` (one group per element:
        ``'#id Class Name'``), ``warnings`` (defaults used, elements without geometry).

    Raises
    ------
    SceneError
        Not an IFC file, too many elements or triangles, no geometry.
    ImportError
        ifcopenshell is not installed (with the pip command).
    """
    path = Path(path)
    ifc = _open(path)
    _check_counts(ifc, path)
    notes: list[str] = []
    exclude = [e for cls in SKIPPED for e in ifc.by_type(cls)]
    verts, faces, mats, groups = [], [], [], []
    materials: dict[str, dict] = {}
    defaults_used: dict[str, set] = {}
    seen: set[int] = set()
    group_names: list[str] = []
    nv = nt = 0
    for element, v, f, mid, styles in _iterate(ifc, path, exclude=exclude):
        where = _label(element)
        seen.add(element.id())
        nt += len(f)
        if nt > MAX_TRIANGLES:
            raise SceneError(f"{path}: more than {MAX_TRIANGLES:,} triangles (at {where}); hfrad reads at most "
                             "that many")
        if not len(f):
            continue
        tri = v[f]
        nz = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        nz = nz[:, 2] / np.maximum(np.linalg.norm(nz, axis=1), 1e-300)
        names = _default_roles(_role(element), nz).astype(object)
        styled = np.zeros(len(f), bool)
        for k, style in enumerate(styles):
            on = mid == k
            if style.instance_id() == 0 or not on.any():
                continue  # ifcopenshell's own default colour: no style in the model
            said: list[str] = []
            name, props = _style_props(ifc, style, where, said)
            if name not in materials:  # said once per style, at its first element
                materials[name] = props
                notes += said
            names[on], styled[on] = name, True
        for name in set(names[~styled].tolist()):
            materials.setdefault(name, _default_props(name))
            defaults_used.setdefault(name, set()).add(element.is_a())
        verts.append(v)
        faces.append(f + nv)
        nv += len(v)
        mats.append(names)
        group_names.append(where)
        groups.append(np.full(len(f), len(group_names) - 1))
    _report_missing(ifc, seen, exclude, notes)
    if not faces:
        raise SceneError(f"{path}: no building element with geometry found")
    for name, classes in sorted(defaults_used.items()):
        props = materials[name]
        tau = props.get("transmittance", (0.0,))[0]
        notes.append(f"no surface style: {', '.join(sorted(classes))} faces use the hfrad default '{name}', "
                     f"reflectance {props['reflectance'][0]:g}" + (f", transmittance {tau:g}" if tau else ""))
    notes.append(Z_UP_NOTE)
    material_names = list(materials)
    index = {n: k for k, n in enumerate(material_names)}
    all_names = np.concatenate(mats)
    return {
        "vertices": z_up_to_y_up(np.vstack(verts)),
        "faces": np.vstack(faces),
        "face_material": np.array([index[n] for n in all_names], dtype=np.int64),
        "material_names": material_names,
        "materials": materials,
        "face_group": np.concatenate(groups).astype(np.int64),
        "group_names": group_names,
        "missing_mtl": [],
        "missing_materials": [],
        "warnings": notes,
    }


def _report_missing(ifc, seen: set[int], exclude, notes: list[str]) -> None:
    """Warn about elements with a representation that gave no geometry (named by entity id)."""
    skipped = {e.id() for e in exclude}
    missing = [e for e in ifc.by_type("IfcElement") if getattr(e, "Representation", None) is not None
               and e.id() not in seen and e.id() not in skipped]
    if missing:
        shown = ", ".join(_label(e) for e in missing[:10])
        notes.append(f"{len(missing)} element(s) with a representation gave no geometry (left out): {shown}"
                     + (" ..." if len(missing) > 10 else ""))


@dataclass(frozen=True)
class Space:
    """An ``IfcSpace``'s floor: where its work plane goes.

    Attributes
    ----------
    name : str
        The space's LongName, else its Name, else ``#id``.
    entity : str
        ``#id IfcSpace Name``, for messages.
    floor : float, metres
        Height (y) of the space's lowest point, y-up.
    outline : (t, 3, 2) float, metres
        The space's floor triangles in plan (x, z), y-up.
    """

    name: str
    entity: str
    floor: float
    outline: np.ndarray


def read_spaces(path: Path) -> list[Space]:
    """The spaces (``IfcSpace``) of an IFC file, each with its floor outline in hfrad's y-up frame.

    The outline is the set of the space's faces that face down at its lowest
    height (the bottom of its volume), seen in plan.

    Raises
    ------
    SceneError
        Not an IFC file, or a space whose geometry has no bottom face (named by entity id).
    ImportError
        ifcopenshell is not installed (with the pip command).
    """
    path = Path(path)
    ifc = _open(path)
    _check_counts(ifc, path)
    spaces = ifc.by_type("IfcSpace")
    if not spaces:
        return []
    out = []
    for element, v, f, _, _ in _iterate(ifc, path, include=spaces):
        where = _label(element)
        if not len(f):
            continue
        tri = v[f]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        length = np.linalg.norm(n, axis=1)
        z0 = float(v[:, 2].min())
        size = float(np.ptp(v, axis=0).max())
        bottom = (n[:, 2] < -0.99 * length) & (np.abs(tri[..., 2] - z0).max(axis=1) <= 1e-6 * max(size, 1.0))
        if not bottom.any():
            raise SceneError(f"{path}: {where} has no horizontal bottom face to lay a work plane on")
        plan = z_up_to_y_up(tri[bottom].reshape(-1, 3)).reshape(-1, 3, 3)[..., [0, 2]]
        name = getattr(element, "LongName", None) or getattr(element, "Name", None) or f"#{element.id()}"
        out.append(Space(str(name), where, float(z0), plan))
    return out
