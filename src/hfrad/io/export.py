"""Writing radiosity solutions: coloured meshes (.glb, .ply) and tables (.npz, .csv).

Every writer goes through a temporary file in the destination folder that is
renamed over the target when complete (:func:`hfrad.atomic.atomic_path`), so a reader never sees
half a file and a failed write leaves nothing behind.

Colours of meshes come from the same smooth per-vertex radiosity as rendered
pictures (:func:`hfrad.render.smooth_corners`): the patch mesh is split along
creases (> 30 degrees) and material borders so colours do not bleed, and the
vertex colour is the exposed radiance ``clip(B / pi * 2**EV, 0, 1)``:

- ``.glb``: ``COLOR_0`` is *linear* by the glTF 2.0 specification, so the
  default ``colors='linear'`` stores the clipped linear value (8-bit
  normalised); ``colors='srgb'`` stores sRGB-encoded values instead, for
  tools that show vertex colours without conversion (not spec-conformant).
- ``.ply``: vertex ``red/green/blue`` uchar are *sRGB-encoded* by default, as
  MeshLab and most viewers display them as-is; per-face float properties carry
  the physical values (W/m^2) in patch order.
"""

from __future__ import annotations

import csv
import os
import warnings
from pathlib import Path

import numpy as np

from ..atomic import atomic_path
from ..errors import InputError
from ..render.shading import CREASE_ANGLE, corner_vertices, smooth_corners
from ..render.tonemap import auto_exposure, tonemap

MESH_FORMATS = (".glb", ".ply")
RADIOSITY_FORMATS = (".npz", ".csv", ".ply", ".glb")


def _check(scene, array, name: str) -> np.ndarray:
    a = np.asarray(array, dtype=np.float64)
    n = scene.n_patches
    if a.shape == (n,):
        a = np.repeat(a[:, None], 3, axis=1)
    if a.shape != (n, 3):
        raise InputError(f"{name} must have shape ({n}, 3) or ({n},) for a scene of {n} patches, got {a.shape}")
    return a


def _extension(path, allowed: tuple[str, ...], what: str) -> str:
    ext = Path(path).suffix.lower()
    if ext not in allowed:
        raise InputError(f"cannot write {what} to '{path}': unsupported extension '{ext or '(none)'}'; "
                         f"supported: {', '.join(allowed)}")
    return ext


def vertex_colors(scene, radiosity: np.ndarray, *, colors: str = "linear", exposure: float | None = None,
                  crease_angle: float = CREASE_ANGLE) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The split patch mesh with 8-bit vertex colours.

    Parameters
    ----------
    scene : Scene
    radiosity : (n, 3) float, W/m^2
    colors : {'linear', 'srgb'}
        Encoding of the 8-bit colours.
    exposure : float, EV, optional
        Colour = clip(B / pi * 2**exposure, 0, 1); default: auto exposure that
        maps the 99th percentile of non-emitting patches' luminance to 0.8.

    Returns
    -------
    vertices : (v, 3) float, metres
    faces : (t, 3) int, the detail triangles in ``scene.faces`` order
    rgb : (v, 3) uint8
    """
    if colors not in ("linear", "srgb"):
        raise InputError(f"colors must be 'linear' or 'srgb', got {colors!r}")
    B = _check(scene, radiosity, "radiosity")
    vertices, faces = corner_vertices(scene, crease_angle=crease_angle)
    corner = smooth_corners(scene, B, crease_angle=crease_angle).reshape(-1, 3)
    value = np.zeros((len(vertices), 3))
    value[faces.reshape(-1)] = corner  # corners merged into one vertex carry equal values
    radiance = value / np.pi
    if exposure is None:
        exposure = auto_exposure(B / np.pi, ~scene.emitters)
    return vertices, faces, tonemap(radiance, exposure=float(exposure), encoding=colors)


def export_mesh(scene, radiosity: np.ndarray, path: "str | os.PathLike", *, colors: str | None = None,
                exposure: float | None = None, exitance: np.ndarray | None = None) -> Path:
    """Write the patches coloured by radiosity as ``.glb`` or ``.ply``.

    Parameters
    ----------
    scene : Scene
    radiosity : (n, 3) float, W/m^2
    path : str or PathLike
        Extension picks the format: ``.glb`` (binary glTF, per-vertex
        ``COLOR_0``) or ``.ply`` (binary PLY with per-face physical values).
    colors : {'linear', 'srgb'}, optional
        Vertex colour encoding; default 'linear' for .glb (glTF spec), 'srgb'
        for .ply (what viewers expect).
    exposure : float, EV, optional
        See :func:`vertex_colors`.
    exitance : (n, 3) float, W/m^2, optional
        Emission written to the PLY ``emission_*`` properties; default
        ``scene.emission``.

    Returns
    -------
    Path
        ``path``, written (a .glb or .ply file).

    Raises
    ------
    InputError (a ValueError)
        Unsupported extension (the message lists the supported ones) or
        arrays of the wrong shape.

    Notes
    -----
    The mesh has one face per detail triangle (one per patch unless the scene
    is clustered; the PLY ``patch`` face property says which), colours
    interpolated smoothly from the patches; its vertices are split where
    triangles meet at a crease or a material border, so it has more vertices
    than ``scene.vertices``.
    """
    if isinstance(scene, (str, os.PathLike)):  # the old order: (path, scene, radiosity)
        warnings.warn("the object comes first, then the path: export_mesh(scene, radiosity, path)",
                      DeprecationWarning, stacklevel=2)
        scene, radiosity, path = radiosity, path, scene
    ext = _extension(path, MESH_FORMATS, "a mesh")
    colors = colors or ("linear" if ext == ".glb" else "srgb")
    vertices, faces, rgb = vertex_colors(scene, radiosity, colors=colors, exposure=exposure)
    if ext == ".glb":
        _write_glb(path, vertices, faces, rgb)
    else:
        E = scene.emission if exitance is None else _check(scene, exitance, "exitance")
        _write_ply(path, scene, vertices, faces, rgb, _check(scene, radiosity, "radiosity"), E)
    return Path(path)


def _write_glb(path, vertices, faces, rgb) -> None:
    import trimesh

    rgba = np.concatenate([rgb, np.full((len(rgb), 1), 255, np.uint8)], axis=1)
    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, vertex_colors=rgba, process=False)
    data = mesh.export(file_type="glb")
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def _write_ply(path, scene, vertices, faces, rgb, B, E) -> None:
    n = len(faces)
    vdtype = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                       ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    fprops = ["radiosity_r", "radiosity_g", "radiosity_b", "emission_r", "emission_g", "emission_b", "area"]
    fdtype = np.dtype([("count", "u1"), ("vertex_indices", "<i4", (3,))] + [(p, "<f4") for p in fprops]
                      + [("patch", "<i4")])
    v = np.empty(len(vertices), vdtype)
    v["x"], v["y"], v["z"] = vertices.T
    v["red"], v["green"], v["blue"] = rgb.T
    f = np.empty(n, fdtype)
    f["count"] = 3
    f["vertex_indices"] = faces
    patch = scene.patch_of_triangle
    for k, c in enumerate("rgb"):
        f[f"radiosity_{c}"] = B[patch, k]
        f[f"emission_{c}"] = E[patch, k]
    f["area"] = scene.triangle_areas
    f["patch"] = patch
    header = "\n".join([
        "ply", "format binary_little_endian 1.0",
        "comment hfrad radiosity: face radiosity_* and emission_* in W/m^2 (of the face's patch), "
        "area in m^2 (of the face), patch = index of the patch the face belongs to",
        "comment vertex colours: sRGB-encoded exposed radiance B/pi",
        f"element vertex {len(v)}",
        "property float x", "property float y", "property float z",
        "property uchar red", "property uchar green", "property uchar blue",
        f"element face {n}",
        "property list uchar int vertex_indices",
        *[f"property float {p}" for p in fprops],
        "property int patch",
        "end_header",
    ]) + "\n"
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(v.tobytes())
        fh.write(f.tobytes())


def _write_npz(path, scene, B, E) -> None:
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(
            fh, B=B, E=E, reflectance=np.asarray(scene.reflectance), area=np.asarray(scene.areas),
            centroid=np.asarray(scene.centroids), normal=np.asarray(scene.normals),
            material=np.asarray(scene.material), material_names=np.array(scene.material_names, dtype=str))


def _write_csv(path, scene, B, E) -> None:
    names = scene.material_names
    with atomic_path(path) as tmp, open(tmp, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(["index", "material", "area", "centroid_x", "centroid_y", "centroid_z",
                    "B_r", "B_g", "B_b", "E_r", "E_g", "E_b"])
        area, cen = scene.areas, scene.centroids
        for i in range(scene.n_patches):
            w.writerow([i, names[scene.material[i]], repr(float(area[i])), *map(lambda x: repr(float(x)), cen[i]),
                        *map(lambda x: repr(float(x)), B[i]), *map(lambda x: repr(float(x)), E[i])])


def write_radiosity(scene, radiosity: np.ndarray, path: "str | os.PathLike", exitance: np.ndarray | None = None,
                    *, colors: str | None = None, exposure: float | None = None) -> Path:
    """Write a radiosity solution; the extension picks the format.

    Parameters
    ----------
    scene : Scene
    radiosity : (n, 3) or (n,) float, W/m^2
    path : str or PathLike
        ``.npz``: arrays ``B`` (n, 3) W/m^2, ``E`` (n, 3) W/m^2,
        ``reflectance`` (n, 3), ``area`` (n,) m^2, ``centroid`` (n, 3) m,
        ``normal`` (n, 3), ``material`` (n,) int, ``material_names`` (m,) str.
        ``.csv``: one row per patch: index, material name, area, centroid
        xyz, B rgb, E rgb (header row first).
        ``.ply`` / ``.glb``: coloured mesh, see :func:`export_mesh`.
    exitance : (n, 3) or (n,) float, W/m^2, optional
        The emission that was solved for; default ``scene.emission``.
    colors : {'linear', 'srgb'}, optional
        Vertex colour encoding for mesh formats (default: linear for .glb,
        sRGB for .ply; see :func:`export_mesh`).
    exposure : float, EV, optional
        Colour exposure for mesh formats.

    Returns
    -------
    Path
        ``path``, written in the format its extension names.

    Raises
    ------
    InputError (a ValueError)
        An extension not in RADIOSITY_FORMATS (the message lists them) or
        arrays of the wrong shape.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> from hfrad.scene.builtin import furnace
    >>> s = furnace()
    >>> B = s.emission / (1 - s.reflectance)
    >>> with tempfile.TemporaryDirectory() as d:
    ...     p = write_radiosity(s, B, pathlib.Path(d) / "b.npz")
    ...     bool(np.allclose(np.load(p)["B"], B))
    True
    """
    if isinstance(scene, (str, os.PathLike)):  # the old order: (path, scene, radiosity[, exitance])
        warnings.warn("the object comes first, then the path: write_radiosity(scene, radiosity, path)",
                      DeprecationWarning, stacklevel=2)
        scene, radiosity, path, exitance = radiosity, path, scene, exitance
    ext = _extension(path, RADIOSITY_FORMATS, "radiosity")
    B = _check(scene, radiosity, "radiosity")
    E = scene.emission if exitance is None else _check(scene, exitance, "exitance")
    if ext in MESH_FORMATS:
        return export_mesh(scene, B, path, colors=colors, exposure=exposure, exitance=E)
    (_write_npz if ext == ".npz" else _write_csv)(path, scene, B, np.asarray(E, dtype=np.float64))
    return Path(path)
