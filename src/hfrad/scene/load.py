"""Loading a scene: file or built-in name -> materials -> lights -> patches.

``load_scene`` is the one entry point the CLI and the API use. Readers for
each format (``obj.py``, ``mesh.py``) return plain dicts; this module turns them into a
:class:`Scene`, applies the lighting options (make a material or group emit,
add an area light), drops degenerate faces with a counted warning, merges
duplicate faces (and reports overlapping ones), and cuts
the faces into patches.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Callable, Mapping, Sequence

import numpy as np

from ..errors import SceneError
from ..memory import require
from ..progress import StageCallback, stage
from .builtin import BUILTIN_SCENES, builtin_scene
from .cleanup import merge_duplicates
from .cluster import cluster
from .patches import (MESH_BYTES_PER_PATCH, check_cut_options, drop_degenerate, longest_edges,
                      min_patches_for_edge, subdivide)
from .scene import Material, Scene

MAX_COLOUR_REFLECTANCE = 0.99  # a white colour (1.0) would create energy: clamp colours to this


def _readers() -> dict[str, Callable[[Path], dict]]:
    from .ifc import read_ifc
    from .mesh import read_gltf, read_ply
    from .obj import read_obj
    from .rad import read_rad

    return {".obj": read_obj, ".ply": read_ply, ".gltf": read_gltf, ".glb": read_gltf, ".rad": read_rad,
            ".ifc": read_ifc}


SUPPORTED_SUFFIXES = (".obj", ".ply", ".gltf", ".glb", ".rad", ".ifc")

RGB = Sequence[float]


def load_scene(
    source: str | Path,
    *,
    unit_scale: float = 1.0,
    default_reflectance: float = 0.7,
    emit: Mapping[str, RGB] | None = None,
    area_light: RGB | None = None,
    allow_missing_materials: bool = False,
    max_edge: float | None = None,
    patches: int | None = None,
    keep_duplicates: bool = False,
    on_stage: StageCallback = None,
) -> Scene:
    """Load a scene file (OBJ/MTL, PLY, glTF/GLB, Radiance .rad, IFC) or a built-in scene by name.

    Radiance and IFC models are Z-up; they are turned to hfrad's y-up frame,
    (x, y, z) -> (x, z, -y), a rotation (docs/buildings.md).

    Parameters
    ----------
    source : str or path
        A file path, or a built-in name (``cornell``, ``furnace``, ...).
    unit_scale : float
        Multiply coordinates by this to get metres.
    default_reflectance : float in [0, 1)
        Grey reflectance of faces without a material.
    emit : mapping of str to (3,) float, W/m^2, optional
        Make every patch of a material or group of that name emit this exitance.
    area_light : (3,) float, W/m^2, optional
        Add a downward-facing rectangle just under the top of the bounding box
        (y up), half the box's width and depth, emitting this exitance.
    allow_missing_materials : bool
        Give faces whose material (or .mtl file) is missing the default
        reflectance instead of raising.
    max_edge, patches : optional
        Patch size or count. Faces larger than the target are split
        (:func:`hfrad.scene.patches.subdivide`); when ``patches`` is below the
        face count, or ``max_edge`` is more than twice some faces' longest
        edge, small faces are grown into clustered patches instead
        (:func:`hfrad.scene.cluster.cluster`; ``Scene.triangle_patch``).
    keep_duplicates : bool
        Keep faces that duplicate another face (same corners) instead of merging
        them; either way duplicates, coplanar overlaps and faces touching face to
        face are listed in ``scene.warnings`` (see :mod:`hfrad.scene.cleanup`).
    on_stage : callable(name), optional
        Told when each stage starts: ``"load"`` (reading the file), ``"clean"`` (degenerate,
        duplicate and overlapping faces), then ``"cluster"`` or ``"mesh"`` (:func:`cut_patches`),
        for a status line and a summary of where the time went (:class:`hfrad.progress.StageClock`).

    Returns
    -------
    Scene

    Raises
    ------
    SceneError
        Missing or unreadable file, unknown format, missing material, bad values.
    InputError
        Bad ``max_edge`` / ``patches``.
    MemoryLimitError
        Cutting into that many patches would not fit in memory, checked before
        cutting (:func:`estimate_patch_count`, :func:`cut_patches`).
    """
    if not (0.0 <= default_reflectance < 1.0):
        raise SceneError(f"default reflectance must be in [0, 1), got {default_reflectance}")
    if not (unit_scale > 0 and np.isfinite(unit_scale)):
        raise SceneError(f"unit scale must be a positive number, got {unit_scale}")
    stage(on_stage, "load")
    scene = _read(source, default_reflectance, allow_missing_materials)
    if unit_scale != 1.0:
        scene = scene.replace(vertices=scene.vertices * unit_scale,
                              occluder_vertices=scene.occluder_vertices * unit_scale)
    if emit:
        scene = set_emission(scene, emit)
    if area_light is not None:
        scene = add_area_light(scene, area_light)
    check_cut_options(max_edge, patches)
    stage(on_stage, "clean")
    scene = drop_degenerate(scene)
    scene = merge_duplicates(scene, keep_duplicates=keep_duplicates)
    return cut_patches(scene, max_edge=max_edge, patches=patches, on_stage=on_stage)


def _clusters_small_faces(longest: np.ndarray, max_edge: float) -> bool:
    """``max_edge`` more than twice the longest edge of two or more faces: they are grown into clusters."""
    return int((longest < 0.5 * max_edge).sum()) > 1


def estimate_patch_count(scene: Scene, *, max_edge: float | None = None, patches: int | None = None) -> int:
    """How many patches :func:`cut_patches` will make, computed before cutting (O(faces)).

    With ``patches``: that number (met within a few percent). With
    ``max_edge = h``: a lower bound. A patch with no edge longer than h has an
    area of at most ``sqrt(3)/4 h^2`` (the equilateral triangle), so cutting
    faces of total area A makes at least ``A / (0.433 h^2)`` patches, and at
    least one per face; the real count is larger, the more so the closer the
    faces' size is to h (a face's boundary is cut every h, and its patches are
    not all equilateral). Where small faces are grown into clusters instead,
    each face longer than h/2 is split into ``ceil(longest edge / h)^2``
    patches and the small faces' area is divided by ``pi/4 h^2`` (a cluster is
    no wider than h). Neither: the scene's own count.

    Parameters
    ----------
    scene : Scene
        An uncut scene (as :func:`load_scene` reads it, before ``max_edge`` or ``patches``).
    max_edge : float, metres, optional
    patches : int, optional

    Returns
    -------
    int

    Raises
    ------
    InputError
        Both options, ``patches < 1`` or a ``max_edge`` that is not a positive length.
    """
    check_cut_options(max_edge, patches)
    n = scene.n_patches
    if patches is not None:
        return int(patches)
    if max_edge is None or n == 0:
        return n
    h = float(max_edge)
    longest = longest_edges(scene.triangles)
    if _clusters_small_faces(longest, h):
        small = longest < 0.5 * h
        split = np.ceil(longest[~small] / h - 1e-9)
        clusters = float(scene.areas[small].sum()) / (math.pi / 4 * h * h)
        return int(min(float((split ** 2).sum()) + max(1.0, clusters), 1e18))
    return int(min(max(float(n), min_patches_for_edge(scene.total_area, h)), 1e18))


def cut_patches(scene: Scene, *, max_edge: float | None = None, patches: int | None = None,
                on_stage: StageCallback = None) -> Scene:
    """Cut an uncut scene into patches (what :func:`load_scene` does with ``max_edge`` / ``patches``).

    ``on_stage("cluster")`` or ``on_stage("mesh")`` is called before the cut (see :func:`load_scene`).

    The memory the cut needs (:data:`~hfrad.scene.patches.MESH_BYTES_PER_PATCH`
    per patch of :func:`estimate_patch_count`) is checked before any work:
    a ``max_edge`` far too small for the scene is refused at once, not after
    minutes of meshing.

    Raises
    ------
    InputError
        Bad options (see :func:`estimate_patch_count`).
    MemoryLimitError
        The cut would not fit in the available memory (the message gives both numbers).
    """
    count = estimate_patch_count(scene, max_edge=max_edge, patches=patches)
    if max_edge is None and patches is None:
        return scene
    if count > scene.n_patches:
        require(MESH_BYTES_PER_PATCH * float(count),
                f"{scene.name}: cutting into {'at least ' if patches is None else ''}{count:,} patches",
                "use a larger max_edge (--max-edge) or fewer patches (--patches); the count is "
                "area / (0.433 max_edge^2) at least (docs: hfrad.scene.load.estimate_patch_count)")
    if patches is not None and patches < scene.n_patches:
        stage(on_stage, "cluster")
        return cluster(scene, patches=int(patches))
    if max_edge is not None and scene.n_patches and _clusters_small_faces(longest_edges(scene.triangles), max_edge):
        stage(on_stage, "cluster")
        return cluster(scene, max_edge=max_edge)
    stage(on_stage, "mesh")
    return subdivide(scene, max_edge=max_edge, patches=None if patches is None else int(patches))


def _read(source: str | Path, default_reflectance: float, allow_missing: bool) -> Scene:
    text = str(source)
    if text in BUILTIN_SCENES and not Path(text).exists():
        return builtin_scene(text)
    path = Path(text)
    if not path.exists():
        raise SceneError(f"{path}: no such file (built-in scenes: {', '.join(BUILTIN_SCENES)})")
    reader = _readers().get(path.suffix.lower())
    if reader is None:
        raise SceneError(f"{path}: unknown scene format '{path.suffix}'; "
                         f"supported: {', '.join(SUPPORTED_SUFFIXES)}")
    raw = reader(path)
    return _scene_from_raw(raw, str(path), default_reflectance, allow_missing)


def _scene_from_raw(raw: dict, name: str, default_reflectance: float, allow_missing: bool) -> Scene:
    warnings: list[str] = list(raw.get("warnings", ()))
    if raw["missing_mtl"] and not allow_missing:
        raise SceneError(f"{name}: material library not found: {', '.join(raw['missing_mtl'])} "
                         "(use --allow-missing-materials to give those faces the default reflectance)")
    if raw["missing_materials"] and not allow_missing and not raw["missing_mtl"]:
        raise SceneError(f"{name}: material(s) used but not defined in the .mtl: "
                         f"{', '.join(raw['missing_materials'])}")
    for mtl in raw["missing_mtl"]:
        warnings.append(f"material library {mtl} not found; its faces use the default reflectance")
    materials = []
    for mat_name in raw["material_names"]:
        props = raw["materials"].get(mat_name, {})
        rho = np.asarray(props.get("reflectance", (default_reflectance,) * 3), dtype=np.float64)
        if props.get("from_colour") and rho.max() > MAX_COLOUR_REFLECTANCE:
            warnings.append(f"material '{mat_name}': colour {tuple(rho.round(3))} clamped to "
                            f"reflectance <= {MAX_COLOUR_REFLECTANCE}")
            rho = np.minimum(rho, MAX_COLOUR_REFLECTANCE)
        if "reflectance" not in props:
            warnings.append(f"material '{mat_name}' has no reflectance; using default {default_reflectance}")
        line = props.get("line")
        label = f"'{mat_name}'" + (f" (defined at line {line} of its .mtl)" if line else "")
        label += f" (defined at {props['where']})" if props.get("where") else ""
        _check_material(name, label, rho, props.get("emission", (0, 0, 0)))
        emission = tuple(float(x) for x in props.get("emission", (0.0, 0.0, 0.0)))
        tau = tuple(float(x) for x in props.get("transmittance", (0.0, 0.0, 0.0)))
        if max(tau) > 0 and (rho + np.asarray(tau) > 1.0).any():     # an MTL's d/Tf: keep what light is left
            tau = tuple(float(min(t, 1.0 - r)) for t, r in zip(tau, rho))
            warnings.append(f"material '{mat_name}': transmittance (1 - d) x Tf lowered to {tuple(round(t, 3) for t in tau)}"
                            " so that reflectance + transmittance <= 1")
        materials.append(Material(mat_name, tuple(float(x) for x in rho), emission, tau))
    face_material = raw["face_material"].copy()
    if (face_material < 0).any():
        count = int((face_material < 0).sum())
        warnings.append(f"{count} faces have no material; they use the default reflectance {default_reflectance}")
        face_material[face_material < 0] = len(materials)
        materials.append(Material("default", (default_reflectance,) * 3))
    vertices = raw["vertices"]
    return Scene(vertices=vertices, faces=raw["faces"], material=face_material, materials=tuple(materials),
                 group=raw["face_group"], groups=tuple(raw["group_names"]), name=name,
                 warnings=tuple(warnings))


def _check_material(file: str, label: str, rho: np.ndarray, emission) -> None:
    if not ((rho >= 0).all() and (rho < 1).all()):
        raise SceneError(f"{file}: material {label} reflectance {tuple(rho.tolist())} is outside [0, 1)")
    em = np.asarray(emission, dtype=np.float64)
    if not (np.isfinite(em).all() and (em >= 0).all()):
        raise SceneError(f"{file}: material {label} emission {tuple(em.tolist())} must be finite and >= 0")


def _rgb(value: RGB, what: str) -> tuple[float, float, float]:
    arr = np.asarray(value, dtype=np.float64).reshape(-1)
    if arr.size == 1:
        arr = np.repeat(arr, 3)
    if arr.size != 3 or not np.isfinite(arr).all() or (arr < 0).any():
        raise SceneError(f"{what}: expected three finite values >= 0 (R,G,B), got {tuple(arr.tolist())}")
    return tuple(float(x) for x in arr)


def set_emission(scene: Scene, emit: Mapping[str, RGB]) -> Scene:
    """Make the patches of the named materials or groups emit (W/m^2).

    A name is looked up among materials first, then groups; an unknown name
    raises a SceneError that lists the names available.
    """
    emission = scene.emission.copy()
    for name, value in emit.items():
        rgb = _rgb(value, f"emission of '{name}'")
        emission[patches_named(scene, name)] = rgb
    return scene.replace(emission=emission)


def patches_named(scene: Scene, name: str) -> np.ndarray:
    """(n,) bool: the patches of the material ``name``, else of the group ``name``.

    Raises
    ------
    SceneError
        No material or group of that name (the message lists the names).
    """
    if name in scene.material_names:
        return scene.material == scene.material_names.index(name)
    if name in scene.groups:
        return scene.group == scene.groups.index(name)
    raise SceneError(f"{scene.name}: no material or group named '{name}'. Materials: "
                     f"{', '.join(scene.material_names)}; groups: {', '.join(scene.groups[:20])}"
                     + (" ..." if len(scene.groups) > 20 else ""))


def add_area_light(scene: Scene, exitance: RGB, *, reflectance: float = 0.78) -> Scene:
    """Add a downward-facing rectangular emitter just below the top of the scene (y up)."""
    rgb = _rgb(exitance, "area light")
    lo, hi = scene.bounds
    centre = 0.5 * (lo + hi)
    half = 0.25 * (hi - lo)
    y = hi[1] - 0.01 * (hi[1] - lo[1])
    x0, x1, z0, z1 = centre[0] - half[0], centre[0] + half[0], centre[2] - half[2], centre[2] + half[2]
    corners = np.array([[x0, y, z0], [x1, y, z0], [x1, y, z1], [x0, y, z1]])  # normal -y
    base = len(scene.vertices)
    new_faces = np.array([[base, base + 1, base + 2], [base, base + 2, base + 3]])
    materials = scene.materials + (Material("area_light", (reflectance,) * 3, rgb),)
    groups = scene.groups + ("area_light",)
    occ_base = len(scene.occluder_vertices)
    return Scene(
        vertices=np.vstack([scene.vertices, corners]), faces=np.vstack([scene.faces, new_faces]),
        material=np.concatenate([scene.material, [len(materials) - 1] * 2]), materials=materials,
        group=np.concatenate([scene.group, [len(groups) - 1] * 2]), groups=groups,
        reflectance=np.vstack([scene.reflectance, [[reflectance] * 3] * 2]),
        emission=np.vstack([scene.emission, [rgb, rgb]]),
        parent=np.concatenate([scene.parent, [len(scene.occluder_faces), len(scene.occluder_faces) + 1]]),
        occluder_vertices=np.vstack([scene.occluder_vertices, corners]),
        occluder_faces=np.vstack([scene.occluder_faces, new_faces - base + occ_base]),
        name=scene.name, warnings=scene.warnings + (f"added area light {rgb} W/m^2 at y = {y:.4g}",),
    )
