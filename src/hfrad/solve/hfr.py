"""The ``.hfr`` factorization file (HDF5): everything needed to solve again without F.

Layout (format version 4; version 2, which stored three n x k Woodbury
matrices ``Y`` instead of the k x k inverses, is still read: its ``Y`` is not
read and the inverses are recomputed from Q and V, O(n k^2 + k^3); version 1
files carry no checksums, so they are refused)::

    /                  attrs: format ("hfrad-factorization"), format_version,
                       hfrad_version, n_patches, rank, eps, relative,
                       achieved_error, norm, method, sigma_max, error_bound,
                       parameters (JSON), timings (JSON)
    /factors/perm      (n,) int64, internal order
    /factors/Q, V      (n, k) float32/64, internal order
    /factors/capacitance_inverse
                       (3, k, k) in the factors' dtype: the inverse of each
                       channel's k x k Woodbury matrix (``I - V^T D_c Q``, or
                       ``I - V^T A_c^-1 D_c Q`` with the near field), so
                       loading needs no O(n k^2) set-up (recomputed if absent)
    /factors/near_data, near_indices, near_indptr
                       the near field N (CSR, internal order) when the
                       near-field split was used (attr solver says which)
    /factors/near_solution
                       (d, n, k) ``A_c^-1 D_c Q`` for the d channels with
                       distinct ``D_c`` (near field only): loading needs no
                       sparse LU (recomputed if absent, as in older files);
                       or, stored in 16 bits (version 4), near_solution_codes
                       (d, n, k) int16 and near_solution_scale (d, n) float32
                       (:class:`~hfrad.solve.quantized.QuantizedRows`)
    /factors/rho_max   (n,) float64, user order
    /factors/reflectance (n, 3) float64, user order
    /stats/...         row_sums, col_sums, sketch (n, p), weights: what the
                       pass over F recorded, internal order; attrs probes, seed;
                       and (files of 2026-12 on) the exact sampled rows of the
                       per-solve error figure: sample_index (m1,), smooth_index
                       (m2,), sample_rows (m1 + m2 [+ m3], n) float32, smooth_products
                       (n, m2, 3) float32, sample_reflectance (n, 3),
                       sample_bounce (n, 3) (first-bounce norms, files of
                       2026-12-06 on); since the fourth stop of issue 42
                       also sample_dual_index (m3,) (the adjoint's rows,
                       last in sample_rows), sample_dual_bounce (n,),
                       sample_gain_vector and sample_gain_product (n,);
                       attrs sample_exact, sample_seed
                       (:mod:`hfrad.solve.samples`); with the sampled far
                       field, far_index (m,) and far_q (m,): its certificate
                       (:mod:`hfrad.formfactors.farfield`)
    /patches/...       vertices, faces, material, reflectance, emission,
                       areas, normals, centroids, group, triangle_patch
                       (only for clustered patches: the patch of each
                       triangle of ``faces``); attrs
                       material_names, group_names, materials (JSON)

Every dataset carries HDF5's Fletcher-32 checksum and the attributes a
SHA-256 digest (``attrs_sha256``), so a damaged file is refused with the name
of the damaged dataset instead of giving an answer from garbage. Both are
required on read from format version 2 on (every such file was written with
them): a file whose digest was deleted, or a dataset rewritten without its
checksum, is refused. Files written now also list their datasets (root
attribute ``datasets``, covered by the digest), so a deleted dataset or group
(the near field, the statistics) is refused too rather than silently
recomputed or dropped. The file is
written under a temporary name in the same folder and renamed when complete,
so a crash never leaves a partial ``.hfr`` behind.
"""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np
import scipy.sparse as sp

from .._version import __version__
from ..atomic import atomic_path
from ..errors import FileFormatError
from ..lowrank.factors import LowRank
from ..integrity import DIGEST, attrs_digest, checked_dataset, integrity_problem, seal
from ..validation import object_first
from .nearfield import NearFieldFactorization
from .quantized import QuantizedRows
from .stats import PassStatistics
from .woodbury import HFactorization

FORMAT = "hfrad-factorization"
#: 5: the per-solve samples may hold the adjoint's rows drawn by 1/A after the smoothed rows
#: (``sample_dual_index``): an older reader would take them for smoothed rows, so it must refuse.
FORMAT_VERSION = 5
#: From this format version on, checksums and the attributes' digest are required on read.
CHECKSUMS_SINCE = 2
#: Datasets that are recomputed, exactly, when absent (older files lack them): no damage when missing.
_RECOMPUTED = ("factors/capacitance_inverse", "factors/near_solution", "factors/near_solution_codes",
               "factors/near_solution_scale")

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
        _dataset(g, name, getattr(scene, name))
    if scene.is_clustered:  # patches that are clusters of the detail triangles `faces`
        _dataset(g, "triangle_patch", scene.triangle_patch)
    g.attrs["material_names"] = json.dumps(list(scene.material_names))
    g.attrs["group_names"] = json.dumps(list(scene.groups))
    # transmittance (glazing) only where non-zero: files of opaque scenes stay as they were
    g.attrs["materials"] = json.dumps([{"name": m.name, "reflectance": list(m.reflectance),
                                        "emission": list(m.emission),
                                        **({"transmittance": list(m.transmittance)} if m.is_glazing else {})}
                                       for m in scene.materials], default=_json_default)
    g.attrs["name"] = str(scene.name)


def hfr_bytes(fac, scene=None) -> int:
    """About the size of ``fac``'s .hfr file: its arrays (stored uncompressed) and the patches, plus headers."""

    def nbytes(a) -> int:
        if a is None:
            return 0
        if hasattr(a, "indptr"):                  # scipy sparse: data, indices, indptr
            return int(a.data.nbytes + a.indices.nbytes + a.indptr.nbytes)
        if hasattr(a, "codes"):                   # 16-bit rows and their scales
            return int(np.asarray(a.codes).nbytes + np.asarray(a.scale).nbytes)
        return int(np.asarray(a).nbytes) if isinstance(a, np.ndarray) else 0

    total = sum(nbytes(getattr(fac, name, None)) for name in
                ("perm", "Q", "V", "rho_max", "reflectance", "capacitance_inv", "N", "Z"))
    if getattr(fac, "stats", None) is not None:
        total += sum(nbytes(v) for v in fac.stats.state().values())
    scene = getattr(fac, "scene", None) if scene is None else scene
    if scene is not None:
        total += sum(nbytes(getattr(scene, name, None)) for name in
                     ("vertices", "faces", "material", "group", "reflectance", "emission", "parent",
                      "occluder_vertices", "occluder_faces", "triangle_patch"))
    return int(1.05 * total) + (64 << 10)


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
    # h5py crashes the process on a full disk: refuse before writing (atomic_path checks the room)
    with atomic_path(path, size=hfr_bytes(fac, scene)) as tmp:
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
            for name in ("perm", "Q", "V", "rho_max", "reflectance"):
                _dataset(g, name, getattr(fac, name))
            a["solver"] = getattr(fac, "solver", "woodbury")
            _dataset(g, "capacitance_inverse", fac.capacitance_inv)
            N = getattr(fac, "N", None)
            if N is not None:  # near-field split: sparse N (CSR, internal order)
                _dataset(g, "near_data", N.data)
                _dataset(g, "near_indices", N.indices)
                _dataset(g, "near_indptr", N.indptr)
                if isinstance(fac.Z, QuantizedRows):
                    _dataset(g, "near_solution_codes", fac.Z.codes)
                    _dataset(g, "near_solution_scale", fac.Z.scale)
                else:
                    _dataset(g, "near_solution", fac.Z)
            if fac.stats is not None:
                _write_stats(f.create_group("stats"), fac.stats)
            if scene is not None:
                _write_scene(f.create_group("patches"), scene)
            seal(f)
    return path


def _dataset(g: h5py.Group, name: str, data) -> None:
    """A dataset with HDF5's Fletcher-32 checksum (chunked; an empty array has nothing to check)."""
    checked_dataset(g, name, data)


#: The exact sampled rows of F (:class:`~hfrad.solve.samples.SampledRows`): arrays, and the dtype they are stored in.
_SAMPLE_ARRAYS = {"sample_index": np.int64, "smooth_index": np.int64, "sample_rows": np.float32,
                  "sample_reflectance": np.float64, "smooth_products": np.float32,
                  "sample_bounce": np.float32, "sample_dual_index": np.int64, "sample_dual_bounce": np.float32,
                  "sample_gain_vector": np.float64, "sample_gain_product": np.float64}
#: The sampled far field's certificate (:class:`~hfrad.formfactors.farfield.FarFieldCertificate`).
_FAR_ARRAYS = {"far_index": np.int64, "far_q": np.float64}


def _write_stats(g: h5py.Group, stats) -> None:
    state = stats.state()
    for name in ("row_sums", "col_sums", "sketch", "weights"):
        if name in state:
            _dataset(g, name, state[name])
    g.attrs["probes"], g.attrs["seed"] = state["probes"], state["seed"]
    if "sample_rows" in state:
        for name, dtype in _SAMPLE_ARRAYS.items():
            if name in state:
                _dataset(g, name, np.asarray(state[name], dtype))
        g.attrs["sample_exact"], g.attrs["sample_seed"] = state["sample_exact"], state["sample_seed"]
    for name, dtype in _FAR_ARRAYS.items():
        if name in state:
            _dataset(g, name, np.asarray(state[name], dtype))


def _read(g: h5py.Group, name: str, path: Path):
    """A dataset's data; FileFormatError naming the file and the dataset when it is missing or damaged."""
    where = f"{g.name.rstrip('/')}/{name}"
    try:
        return g[name][()]
    except KeyError:
        raise FileFormatError(f"{path}: dataset {where} is missing (truncated or corrupted file)") from None
    except (OSError, ValueError) as exc:
        raise FileFormatError(f"{path}: dataset {where} is damaged (checksum mismatch or unreadable data): "
                              f"{exc}") from exc


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


def _check_integrity(f: h5py.File, path: Path) -> None:
    """FileFormatError unless the digest, checksums and dataset list are intact (format 2 and later)."""
    if int(f.attrs["format_version"]) < CHECKSUMS_SINCE:  # format 1: nothing to check its data against
        raise FileFormatError(f"{path}: format version {int(f.attrs['format_version'])} carries no checksums, "
                              "so its data cannot be verified; run `hfrad precompute` again to write it anew")
    problem = integrity_problem(f, manifest_required=False,   # files of hfrad <= 0.1 list no datasets
                                may_be_missing=_RECOMPUTED)
    if problem is not None:
        raise FileFormatError(f"{path}: damaged .hfr file: {problem}")


def _metadata(f: h5py.File) -> dict:
    a = f.attrs
    return {"format_version": int(a["format_version"]), "hfrad_version": str(a["hfrad_version"]),
            "n_patches": int(a["n_patches"]), "rank": int(a["rank"]), "eps": float(a["eps"]),
            "relative": bool(a["relative"]), "achieved_error": float(a["achieved_error"]),
            "norm": float(a["norm"]), "method": str(a["method"]),
            "sigma_max": np.asarray(a["sigma_max"], np.float64),
            "error_bound": np.asarray(a["error_bound"], np.float64),
            "parameters": json.loads(a["parameters"]), "timings": json.loads(a["timings"]),
            "lowrank_info": json.loads(a["lowrank_info"]), "has_patches": "patches" in f,
            "solver": str(a.get("solver", "woodbury"))}


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
            _check_integrity(f, path)
            return _metadata(f)
        except FileFormatError:
            raise
        except (KeyError, ValueError, OSError) as exc:
            raise FileFormatError(f"{path}: corrupted .hfr header: {exc}") from exc


def _read_scene(g: h5py.Group, path: Path | None = None):
    from ..scene.scene import Material, Scene
    path = Path(g.file.filename) if path is None else path
    mats = tuple(Material(m["name"], tuple(m["reflectance"]), tuple(m["emission"]),
                          tuple(m.get("transmittance", (0.0, 0.0, 0.0))))
                 for m in json.loads(g.attrs["materials"]))
    optional = {k: _read(g, k, path) for k in ("parent", "occluder_vertices", "occluder_faces", "triangle_patch")
                if k in g}
    return Scene(vertices=_read(g, "vertices", path), faces=_read(g, "faces", path),
                 material=_read(g, "material", path), materials=mats, group=_read(g, "group", path),
                 groups=tuple(json.loads(g.attrs["group_names"])), reflectance=_read(g, "reflectance", path),
                 emission=_read(g, "emission", path), name=str(g.attrs["name"]), **optional)


def _read_stats(g: h5py.Group, path: Path) -> PassStatistics:
    names = ("row_sums", "col_sums", "sketch", "weights", *_SAMPLE_ARRAYS, *_FAR_ARRAYS)
    state = {k: _read(g, k, path) for k in names if k in g}
    state.update(probes=int(g.attrs["probes"]), seed=int(g.attrs["seed"]))
    if "sample_rows" in state:
        state.update(sample_exact=int(g.attrs["sample_exact"]), sample_seed=int(g.attrs["sample_seed"]))
    return PassStatistics.from_state(state)


def load_hfr(path) -> HFactorization:
    """Read an .hfr file back into an :class:`HFactorization` (with ``.scene`` if stored).

    Every dataset's checksum and the attributes' digest are verified.

    Raises
    ------
    FileNotFoundError
    FileFormatError
        Truncated or damaged file (names the file and the damaged dataset),
        or a newer format version (upgrade hfrad).
    """
    path = Path(path)
    with _open(path) as f:
        try:
            _check_integrity(f, path)
            meta = _metadata(f)
            g = f["factors"]
            perm, Q, V, rho_max, rho = (_read(g, k, path) for k in ("perm", "Q", "V", "rho_max", "reflectance"))
            # versions 1-2 stored Y (3 n k words) instead: not read, the LUs are recomputed
            cap = _read(g, "capacitance_inverse", path) if "capacitance_inverse" in g else None
            near = tuple(_read(g, k, path) for k in ("near_data", "near_indices", "near_indptr")) \
                if "near_data" in g else None
            # older files stored no Z: it is recomputed (a sparse LU per distinct channel)
            near_Z = _read(g, "near_solution", path) if "near_solution" in g else None
            if "near_solution_codes" in g:
                codes, scale = (_read(g, k, path) for k in ("near_solution_codes", "near_solution_scale"))
                if codes.ndim != 3 or scale.shape != codes.shape[:2]:
                    raise FileFormatError(f"{path}: near_solution_codes {codes.shape} and near_solution_scale "
                                          f"{scale.shape} do not match")
                near_Z = QuantizedRows(codes, scale)
            scene = _read_scene(f["patches"], path) if "patches" in f else None
            stats = _read_stats(f["stats"], path) if "stats" in f else None
        except FileFormatError:
            raise
        except Exception as exc:  # h5py raises KeyError/OSError/ValueError on damaged data
            raise FileFormatError(f"{path}: truncated or corrupted .hfr file: {exc}") from exc
    n, k = meta["n_patches"], meta["rank"]
    if Q.shape != (n, k) or V.shape != (n, k) or perm.shape != (n,) \
            or (cap is not None and cap.shape != (3, k, k)) \
            or (near_Z is not None and (len(near_Z.shape) != 3 or near_Z.shape[1:] != (n, k))):
        raise FileFormatError(f"{path}: inconsistent arrays (Q {Q.shape}, V {V.shape}, capacitance_inverse "
                              f"{None if cap is None else cap.shape}, near_solution "
                              f"{None if near_Z is None else near_Z.shape}, rank {k})")
    lr = LowRank(Q=Q, V=V, achieved_error=meta["achieved_error"], norm=meta["norm"], eps=meta["eps"],
                 relative=meta["relative"], method=meta["method"], info=meta["lowrank_info"])
    if near is None:
        fac = HFactorization(perm, Q, V, rho_max, rho, lr, capacitance=cap, sigma_max=meta["sigma_max"],
                             params=meta["parameters"], scene=scene, stats=stats)
    else:
        N = sp.csr_matrix(near, shape=(n, n))
        fac = NearFieldFactorization(perm, Q, V, N, rho_max, rho, lr, capacitance=cap, near_solution=near_Z,
                                     sigma_max=meta["sigma_max"], params=meta["parameters"], scene=scene,
                                     stats=stats)
    fac.timings = meta["timings"]
    return fac
