"""The ``.hfr`` factorization file (HDF5): everything needed to solve again without F.

Layout (format version 1)::

    /                  attrs: format ("hfrad-factorization"), format_version,
                       hfrad_version, n_patches, rank, eps, relative,
                       achieved_error, norm, method, sigma_max, error_bound,
                       parameters (JSON), timings (JSON)
    /factors/perm      (n,) int64, internal order
    /factors/Q, V      (n, k) float32/64, internal order
    /factors/Y         (3, n, k), eq. 4 per channel
    /factors/rho_max   (n,) float64, user order
    /patches/...       vertices, faces, material, reflectance, emission,
                       areas, normals, centroids, group, triangle_patch
                       (only for clustered patches: the patch of each
                       triangle of ``faces``); attrs
                       material_names, group_names, materials (JSON)

The file is written under a temporary name in the same folder and renamed
when complete, so a crash never leaves a partial ``.hfr`` behind.
"""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np

from .._version import __version__
from ..atomic import atomic_path
from ..errors import FileFormatError
from ..factorize.lowrank import LowRank
from ..validation import object_first
from .woodbury import HFactorization

FORMAT = "hfrad-factorization"
FORMAT_VERSION = 1

__all__ = ["save_hfr", "load_hfr", "read_hfr_metadata", "FORMAT_VERSION"]


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


def _write_scene(g: h5py.Group, scene) -> None:
    for name in ("vertices", "faces", "material", "reflectance", "emission", "areas", "normals",
                 "centroids", "group", "parent", "occluder_vertices", "occluder_faces"):
        g.create_dataset(name, data=np.asarray(getattr(scene, name)))
    if scene.is_clustered:  # patches that are clusters of the detail triangles `faces`
        g.create_dataset("triangle_patch", data=np.asarray(scene.triangle_patch))
    g.attrs["material_names"] = json.dumps(list(scene.material_names))
    g.attrs["group_names"] = json.dumps(list(scene.groups))
    g.attrs["materials"] = json.dumps([{"name": m.name, "reflectance": list(m.reflectance),
                                        "emission": list(m.emission)} for m in scene.materials],
                                      default=_json_default)
    g.attrs["name"] = str(scene.name)


def save_hfr(factorization: HFactorization, path, *, scene=None, timings: dict | None = None) -> Path:
    """Write ``factorization`` (and optionally its scene's patches) to an .hfr file.

    Parameters
    ----------
    factorization : HFactorization
    path : str or Path
    scene : Scene, optional
        Defaults to ``factorization.scene``.
    timings : dict, optional
        Seconds per stage, stored as JSON.

    Returns
    -------
    Path of the written file. Written atomically (temporary file + rename).
    """
    factorization, path = object_first(factorization, path, "save_hfr(factorization, path)")
    path = Path(path)
    fac = factorization
    scene = fac.scene if scene is None else scene
    estimate = fac.error_estimate()
    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w") as f:
            lr = fac.lowrank
            a = f.attrs
            a["format"] = FORMAT
            a["format_version"] = FORMAT_VERSION
            a["hfrad_version"] = __version__
            a["n_patches"] = fac.n_patches
            a["rank"] = fac.rank
            a["eps"] = lr.eps
            a["relative"] = bool(lr.relative)
            a["achieved_error"] = lr.achieved_error
            a["norm"] = lr.norm
            a["method"] = lr.method
            a["sigma_max"] = estimate.sigma_max
            a["error_bound"] = estimate.bound
            a["parameters"] = json.dumps(fac.params, default=_json_default)
            a["timings"] = json.dumps(timings or {}, default=_json_default)
            a["lowrank_info"] = json.dumps({k: v for k, v in lr.info.items() if k != "leaf_ranks"},
                                           default=_json_default)
            g = f.create_group("factors")
            g.create_dataset("perm", data=fac.perm)
            g.create_dataset("Q", data=fac.Q)
            g.create_dataset("V", data=fac.V)
            g.create_dataset("Y", data=fac.Y)
            g.create_dataset("rho_max", data=fac.rho_max)
            g.create_dataset("reflectance", data=fac.reflectance)
            if scene is not None:
                _write_scene(f.create_group("patches"), scene)
    return path


def _open(path: Path) -> h5py.File:
    try:
        f = h5py.File(path, "r")
    except FileNotFoundError:
        raise
    except OSError as exc:
        raise FileFormatError(f"{path}: not a readable .hfr file (truncated or corrupted): {exc}") from exc
    try:
        fmt, version = f.attrs.get("format"), f.attrs.get("format_version")
        if fmt != FORMAT or version is None:
            raise FileFormatError(f"{path}: not an hfrad factorization file (format attribute {fmt!r})")
        if int(version) > FORMAT_VERSION:
            raise FileFormatError(f"{path}: format version {int(version)} is newer than this hfrad "
                                  f"reads ({FORMAT_VERSION}); upgrade hfrad (pip install -U hfrad)")
    except FileFormatError:
        f.close()
        raise
    except Exception as exc:
        f.close()
        raise FileFormatError(f"{path}: corrupted .hfr header: {exc}") from exc
    return f


def _metadata(f: h5py.File) -> dict:
    a = f.attrs
    return {"format_version": int(a["format_version"]), "hfrad_version": str(a["hfrad_version"]),
            "n_patches": int(a["n_patches"]), "rank": int(a["rank"]), "eps": float(a["eps"]),
            "relative": bool(a["relative"]), "achieved_error": float(a["achieved_error"]),
            "norm": float(a["norm"]), "method": str(a["method"]),
            "sigma_max": np.asarray(a["sigma_max"], np.float64),
            "error_bound": np.asarray(a["error_bound"], np.float64),
            "parameters": json.loads(a["parameters"]), "timings": json.loads(a["timings"]),
            "lowrank_info": json.loads(a["lowrank_info"]), "has_patches": "patches" in f}


def read_hfr_metadata(path) -> dict:
    """The header of an .hfr file (sizes, errors, parameters) without reading the factors.

    Raises
    ------
    FileFormatError
        Truncated/corrupted file, or a newer format version.
    """
    path = Path(path)
    with _open(path) as f:
        try:
            return _metadata(f)
        except (KeyError, ValueError, OSError) as exc:
            raise FileFormatError(f"{path}: corrupted .hfr header: {exc}") from exc


def _read_scene(g: h5py.Group):
    from ..scene.scene import Material, Scene
    mats = tuple(Material(m["name"], tuple(m["reflectance"]), tuple(m["emission"]))
                 for m in json.loads(g.attrs["materials"]))
    return Scene(vertices=g["vertices"][()], faces=g["faces"][()], material=g["material"][()],
                 materials=mats, group=g["group"][()], groups=tuple(json.loads(g.attrs["group_names"])),
                 reflectance=g["reflectance"][()], emission=g["emission"][()], name=str(g.attrs["name"]),
                 **{k: g[k][()] for k in ("parent", "occluder_vertices", "occluder_faces", "triangle_patch") if k in g})


def load_hfr(path) -> HFactorization:
    """Read an .hfr file back into an :class:`HFactorization` (with ``.scene`` if stored).

    Raises
    ------
    FileNotFoundError
    FileFormatError
        Truncated or corrupted file (names it), or a newer format version
        (upgrade hfrad).
    """
    path = Path(path)
    with _open(path) as f:
        try:
            meta = _metadata(f)
            g = f["factors"]
            perm, Q, V, Y = g["perm"][()], g["Q"][()], g["V"][()], g["Y"][()]
            rho_max, rho = g["rho_max"][()], g["reflectance"][()]
            scene = _read_scene(f["patches"]) if "patches" in f else None
        except FileFormatError:
            raise
        except Exception as exc:  # h5py raises KeyError/OSError/ValueError on damaged data
            raise FileFormatError(f"{path}: truncated or corrupted .hfr file: {exc}") from exc
    n, k = meta["n_patches"], meta["rank"]
    if Q.shape != (n, k) or V.shape != (n, k) or Y.shape != (3, n, k) or perm.shape != (n,):
        raise FileFormatError(f"{path}: inconsistent array shapes (Q {Q.shape}, V {V.shape}, Y {Y.shape})")
    lr = LowRank(Q=Q, V=V, achieved_error=meta["achieved_error"], norm=meta["norm"], eps=meta["eps"],
                 relative=meta["relative"], method=meta["method"], info=meta["lowrank_info"])
    fac = HFactorization(perm, Q, V, rho_max, rho, lr, Y=Y, sigma_max=meta["sigma_max"],
                         params=meta["parameters"], scene=scene)
    fac.timings = meta["timings"]
    return fac
