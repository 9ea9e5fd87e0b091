"""The patch scene: triangles with reflectance and emission, the input of the pipeline.

A :class:`Scene` is an immutable set of triangular patches. Each patch carries a
material (reflectance and emitted exitance per RGB channel) and a group name.
Geometry-derived arrays (areas, normals, centroids) are computed once and
returned read-only, like trimesh's cached properties.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from ..errors import InputError, SceneError
from ..validation import MAX_EXITANCE, as_real_array

#: Sizes (largest side of the bounding box, metres) a scene may have. Form factors are checked
#: to be independent of the unit from 1e-40 to 1e40 m (tests/test_robust_inputs.py) and break
#: beyond 1e75 (areas and distances squared leave float64's range); outside this range a
#: scene is refused with the size it has, rather than reported as "every face is degenerate".
SIZE_RANGE = (1e-30, 1e30)

#: How far from the origin, in multiples of its size, a scene may lie. Float64 coordinates there
#: keep 2.2e-16 x 1e7 = 2e-9 of the scene's size: the geometry the form factors see (centred in
#: float64, then cast in float32 rays in the scene's own frame) stays exact to that. A site of
#: 100 m in coordinates of 1e6 m (ratio 1e4) is fine; a 1 m room 1e13 m away (ratio 1e13) is refused.
MAX_OFFSET_RATIO = 1e7


@dataclass(frozen=True)
class Material:
    """A Lambertian material.

    Attributes
    ----------
    name : str
    reflectance : (3,) float in [0, 1)
        Diffuse reflectance (albedo) per RGB channel.
    emission : (3,) float >= 0, W/m^2
        Emitted exitance per RGB channel.
    transmittance : (3,) float in [0, 1], reflectance + transmittance <= 1
        Visible transmittance per RGB channel: 0 for an opaque surface, above
        0 for glazing (Radiance ``glass``/``trans``, IFC windows). Today's
        radiosity has no sky: the transmitted light leaves the scene (a
        window is as dark as an opening, plus its reflectance). Kept for the
        daylight work (docs/buildings.md).
    """

    name: str
    reflectance: tuple[float, float, float]
    emission: tuple[float, float, float] = (0.0, 0.0, 0.0)
    transmittance: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @property
    def is_emitter(self) -> bool:
        return max(self.emission) > 0.0

    @property
    def is_glazing(self) -> bool:
        """True when the material lets light through (a window)."""
        return max(self.transmittance) > 0.0


def _readonly(a: np.ndarray) -> np.ndarray:
    a = np.ascontiguousarray(a)
    a.flags.writeable = False
    return a


@dataclass(frozen=True, eq=False)
class Scene:
    """Patches with materials, in the user's patch order.

    A patch is one triangle, or (after :func:`hfrad.scene.cluster.cluster`) a
    set of triangles of one material: ``faces`` are then the *detail*
    triangles, ``triangle_patch`` says which patch each belongs to, and every
    per-patch quantity (``areas``, ``normals``, ``centroids``, ``material``,
    ``reflectance``, ``emission``, ``n_patches``) describes the whole set.

    Parameters
    ----------
    vertices : (v, 3) float, metres
    faces : (t, 3) int
        Vertex indices of each triangle, counter-clockwise seen from the front
        (the side the normal points to, the side that emits and reflects).
        One triangle per patch unless ``triangle_patch`` is given.
    material : (n,) int
        Index into ``materials`` for each patch.
    materials : tuple of Material
    group : (n,) int, optional
        Index into ``groups`` (OBJ ``g``/``o`` names); all zero if absent.
    groups : tuple of str, optional
    reflectance, emission : (n, 3) float, optional
        Per-patch overrides; default to the patch's material values.
    parent : (t,) int, optional
        Index of the input face each triangle was cut from (identity if absent).
    triangle_patch : (t,) int, optional
        The patch (0..n-1) each triangle belongs to; every patch has at least
        one triangle. Identity (one triangle per patch) if absent.
    occluder_vertices, occluder_faces : optional
        The un-subdivided mesh used for ray casting. Patches lie on its faces,
        so visibility is exact with it and much cheaper than with the patches.
    name : str
        Where the scene came from (file path or built-in name).
    warnings : tuple of str
        What the loader fixed or assumed (dropped faces, default reflectance).
    """

    vertices: np.ndarray
    faces: np.ndarray
    material: np.ndarray
    materials: tuple[Material, ...]
    group: np.ndarray | None = None
    groups: tuple[str, ...] = ("default",)
    reflectance: np.ndarray | None = None
    emission: np.ndarray | None = None
    parent: np.ndarray | None = None
    occluder_vertices: np.ndarray | None = None
    occluder_faces: np.ndarray | None = None
    name: str = "scene"
    warnings: tuple[str, ...] = field(default_factory=tuple)
    triangle_patch: np.ndarray | None = None

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        set_(self, "vertices", _readonly(np.asarray(self.vertices, dtype=np.float64).reshape(-1, 3)))
        set_(self, "faces", _readonly(np.asarray(self.faces, dtype=np.int64).reshape(-1, 3)))
        t = len(self.faces)
        if self.triangle_patch is not None:
            tp = np.asarray(self.triangle_patch, dtype=np.int64).reshape(-1)
            if tp.shape != (t,):
                raise SceneError(f"{self.name}: triangle_patch has {tp.size} entries for {t} triangles")
            if np.array_equal(tp, np.arange(t)):
                tp = None  # one triangle per patch: store nothing
            set_(self, "triangle_patch", None if tp is None else _readonly(tp))
        n = t if self.triangle_patch is None else int(self.triangle_patch.max(initial=-1)) + 1
        set_(self, "material", _readonly(np.asarray(self.material, dtype=np.int64).reshape(n)))
        group = np.zeros(n, np.int64) if self.group is None else self.group
        set_(self, "group", _readonly(np.asarray(group, dtype=np.int64).reshape(n)))
        mats = self.materials
        if self.reflectance is None:
            rho = np.array([m.reflectance for m in mats], dtype=np.float64).reshape(-1, 3)
            set_(self, "reflectance", rho[self.material] if n else np.zeros((0, 3)))
        if self.emission is None:
            em = np.array([m.emission for m in mats], dtype=np.float64).reshape(-1, 3)
            set_(self, "emission", em[self.material] if n else np.zeros((0, 3)))
        set_(self, "reflectance", _readonly(np.asarray(self.reflectance, np.float64).reshape(n, 3)))
        set_(self, "emission", _readonly(np.asarray(self.emission, np.float64).reshape(n, 3)))
        parent = np.arange(t) if self.parent is None else self.parent
        set_(self, "parent", _readonly(np.asarray(parent, dtype=np.int64).reshape(t)))
        if self.occluder_faces is None:
            set_(self, "occluder_vertices", self.vertices)
            set_(self, "occluder_faces", self.faces)
        else:
            set_(self, "occluder_vertices", _readonly(np.asarray(self.occluder_vertices, np.float64)))
            set_(self, "occluder_faces", _readonly(np.asarray(self.occluder_faces, np.int64)))
        set_(self, "warnings", tuple(self.warnings))
        self._check()

    def _check(self) -> None:
        if not np.isfinite(self.vertices).all():
            bad = int(np.flatnonzero(~np.isfinite(self.vertices).all(axis=1))[0])
            raise SceneError(f"{self.name}: vertex {bad} has a non-finite coordinate")
        if len(self.faces) and (self.faces.min() < 0 or self.faces.max() >= len(self.vertices)):
            raise SceneError(f"{self.name}: face vertex index out of range 0..{len(self.vertices) - 1}")
        if len(self.material) and (self.material.min() < 0 or self.material.max() >= len(self.materials)):
            raise SceneError(f"{self.name}: material index out of range")
        if self.triangle_patch is not None:
            tp = self.triangle_patch
            if tp.min() < 0:
                raise SceneError(f"{self.name}: triangle {int(np.argmin(tp))} has a negative patch index")
            empty = np.flatnonzero(np.bincount(tp, minlength=self.n_patches) == 0)
            if len(empty):
                raise SceneError(f"{self.name}: patch {int(empty[0])} has no triangle "
                                 "(triangle_patch must use every patch index 0..n-1)")
        for m in self.materials:
            rho, em = np.asarray(m.reflectance), np.asarray(m.emission)
            if not (np.isfinite(rho).all() and (rho >= 0).all() and (rho < 1).all()):
                raise SceneError(f"{self.name}: material '{m.name}' reflectance {tuple(rho.tolist())} "
                                 "must be in [0, 1) (a reflectance of 1 or more creates energy)")
            if not (np.isfinite(em).all() and (em >= 0).all()):
                raise SceneError(f"{self.name}: material '{m.name}' emission {tuple(em.tolist())} must be finite and >= 0")
            tau = np.asarray(m.transmittance, dtype=np.float64)
            if not (tau.shape == (3,) and np.isfinite(tau).all() and (tau >= 0).all() and (rho + tau <= 1).all()):
                raise SceneError(f"{self.name}: material '{m.name}' transmittance {tuple(tau.tolist())} must be "
                                 "three values >= 0 with reflectance + transmittance <= 1")
        self._check_extent()
        self._check_exitance()
        # per-patch overrides are checked too: a NaN would reach LAPACK (which runs unchecked)
        bad = ~(np.isfinite(self.reflectance) & (self.reflectance >= 0) & (self.reflectance < 1)).all(axis=1)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise SceneError(f"{self.name}: patch {i} reflectance {tuple(self.reflectance[i].tolist())} must be finite "
                             "and in [0, 1)")
        bad = ~(np.isfinite(self.emission) & (self.emission >= 0)).all(axis=1)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise SceneError(f"{self.name}: patch {i} emission {tuple(self.emission[i].tolist())} must be finite and >= 0")

    def _check_extent(self) -> None:
        """Refuse a scene too small, too large or too far from the origin to compute with (with the reason)."""
        if not len(self.faces):
            return
        v = self.vertices  # per column: contiguous reductions, not a strided one over axis 0 of (n, 3)
        lo, hi = np.array([v[:, k].min() for k in range(3)]), np.array([v[:, k].max() for k in range(3)])
        size = float((hi - lo).max())
        if not (SIZE_RANGE[0] <= size <= SIZE_RANGE[1]) or float(np.abs(np.r_[lo, hi]).max()) > MAX_OFFSET_RATIO * size:
            # the fast bounds (all vertices) fail: judge by the vertices the faces use (stray ones do not count)
            used = self.vertices[np.unique(self.faces)]
            lo, hi = used.min(axis=0), used.max(axis=0)
            size = float((hi - lo).max())
        if size == 0.0:
            return  # a point: every face is degenerate, which the loader reports
        if not (SIZE_RANGE[0] <= size <= SIZE_RANGE[1]):
            raise SceneError(f"{self.name}: the scene is {size:.3g} m across; hfrad computes with scenes "
                             f"between {SIZE_RANGE[0]:g} and {SIZE_RANGE[1]:g} m (areas and distances "
                             "squared would leave the range of floating point numbers): give the "
                             "coordinates' unit (--unit-scale / unit_scale) or rescale the file")
        far = float(np.abs(np.concatenate([lo, hi])).max())
        if far > MAX_OFFSET_RATIO * size:
            centre = 0.5 * (lo + hi)
            raise SceneError(f"{self.name}: the scene is {size:.3g} m across but lies {far:.3g} m from the "
                             f"origin ({far / size:.3g} times its size; at most {MAX_OFFSET_RATIO:g}): float64 "
                             f"coordinates there resolve only {np.spacing(far):.2g} m. Move it near the origin "
                             f"(subtract ({', '.join(f'{c:.6g}' for c in centre)}) from every vertex)")

    def _check_exitance(self) -> None:
        """Refuse emission above MAX_EXITANCE: float32 radiosity would overflow into inf/NaN (a black picture)."""
        over = self.emission > MAX_EXITANCE  # elementwise: no (n, 3) max over axis 1, a slow short-row reduction
        if over.any():
            i = int(np.flatnonzero(over.any(axis=1))[0])
            m = self.materials[int(self.material[i])].name if len(self.materials) else "?"
            raise SceneError(f"{self.name}: patch {i} (material '{m}') emits {tuple(self.emission[i].tolist())} W/m^2, "
                             f"above the largest exitance hfrad computes with, {MAX_EXITANCE:g} W/m^2 "
                             "(radiosity is stored in float32 and would overflow); express the emission "
                             "in a larger unit")

    # -- sizes -------------------------------------------------------------
    @property
    def n_patches(self) -> int:
        return len(self.material)

    @property
    def n_triangles(self) -> int:
        """Detail triangles (``len(faces)``); equals ``n_patches`` unless clustered."""
        return len(self.faces)

    @property
    def is_clustered(self) -> bool:
        """True when some patch has more than one triangle."""
        return self.triangle_patch is not None

    def __len__(self) -> int:
        return self.n_patches

    # -- cached geometry ---------------------------------------------------
    @cached_property
    def patch_of_triangle(self) -> np.ndarray:
        """(t,) int: the patch of each detail triangle (``arange(n)`` unless clustered)."""
        if self.triangle_patch is None:
            return _readonly(np.arange(self.n_triangles))
        return self.triangle_patch

    @cached_property
    def patch_triangles(self) -> tuple[np.ndarray, np.ndarray]:
        """CSR lists of each patch's triangles: ``(start (n + 1,), index (t,))``.

        The triangles of patch p are ``index[start[p]:start[p + 1]]``, in
        their order in ``faces``.
        """
        tp = self.patch_of_triangle
        index = np.argsort(tp, kind="stable")
        start = np.zeros(self.n_patches + 1, np.int64)
        np.cumsum(np.bincount(tp, minlength=self.n_patches), out=start[1:])
        return _readonly(start), _readonly(index)

    @cached_property
    def triangles(self) -> np.ndarray:
        """(t, 3, 3) float: corner coordinates of each detail triangle (of each patch unless clustered)."""
        return _readonly(self.vertices[self.faces])

    @cached_property
    def _cross(self) -> np.ndarray:
        t = self.triangles
        return np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])

    @cached_property
    def triangle_areas(self) -> np.ndarray:
        """(t,) float, m^2: areas of the detail triangles."""
        return _readonly(0.5 * np.linalg.norm(self._cross, axis=1))

    @cached_property
    def triangle_normals(self) -> np.ndarray:
        """(t, 3) float: unit normals of the detail triangles (zero if degenerate)."""
        length = np.linalg.norm(self._cross, axis=1, keepdims=True)
        return _readonly(np.divide(self._cross, length, out=np.zeros_like(self._cross), where=length > 0))

    def _per_patch(self, values: np.ndarray) -> np.ndarray:
        """Sum per-triangle ``values`` (t, ...) over each patch's triangles."""
        if self.triangle_patch is None:
            return values
        out = np.zeros((self.n_patches,) + values.shape[1:])
        np.add.at(out, self.triangle_patch, values)
        return out

    @cached_property
    def areas(self) -> np.ndarray:
        """(n,) float, m^2: patch areas (sum over a patch's triangles)."""
        return _readonly(self._per_patch(self.triangle_areas))

    @cached_property
    def area_vectors(self) -> np.ndarray:
        """(n, 3) float, m^2: sum of area x unit normal over each patch's triangles.

        Its length is the patch's area projected on its mean plane (= the area
        for a flat patch); projected on a direction d it is the patch's
        projected area seen from d when all its triangles face d.
        """
        return _readonly(self._per_patch(0.5 * self._cross))

    @cached_property
    def normals(self) -> np.ndarray:
        """(n, 3) float: unit area-weighted mean normals (zero for a degenerate patch)."""
        v = self.area_vectors
        length = np.linalg.norm(v, axis=1, keepdims=True)
        return _readonly(np.divide(v, length, out=np.zeros_like(v), where=length > 0))

    @cached_property
    def non_flatness(self) -> np.ndarray:
        """(n,) float in [0, 1]: 1 - |area vector| / area; 0 for a flat patch.

        For two halves folded by an angle a it is 1 - cos(a / 2); a patch
        whose triangles all lie within 30 degrees of its mean normal has at
        most 1 - cos(30 deg) = 0.134.
        """
        a = self.areas
        flat = np.divide(np.linalg.norm(self.area_vectors, axis=1), a, out=np.ones_like(a), where=a > 0)
        return _readonly(np.clip(1.0 - flat, 0.0, 1.0))

    @cached_property
    def centroids(self) -> np.ndarray:
        """(n, 3) float, metres: area-weighted centroids of the patches."""
        c = self.triangles.mean(axis=1)
        if self.triangle_patch is None:
            return _readonly(c)
        a = self.areas
        s = self._per_patch(c * self.triangle_areas[:, None])
        return _readonly(np.divide(s, a[:, None], out=np.zeros_like(s), where=a[:, None] > 0))

    @cached_property
    def bounds(self) -> np.ndarray:
        """(2, 3) float: min and max corner of the bounding box of the patches."""
        if not len(self.faces):
            return np.zeros((2, 3))
        in_use = np.zeros(len(self.vertices), bool)
        in_use[self.faces] = True  # a mask, not np.unique: no sort of the corners
        used = self.vertices[in_use]
        return _readonly(np.array([used.min(axis=0), used.max(axis=0)]))

    @property
    def total_area(self) -> float:
        return float(self.areas.sum())

    @property
    def material_names(self) -> tuple[str, ...]:
        return tuple(m.name for m in self.materials)

    @property
    def emitters(self) -> np.ndarray:
        """(n,) bool: patches with non-zero emission."""
        return self.emission.max(axis=1) > 0

    def material_index(self, name: str) -> int:
        """Index of the material called ``name``; SceneError listing the names if absent."""
        for i, m in enumerate(self.materials):
            if m.name == name:
                return i
        raise SceneError(f"{self.name}: no material named '{name}'; materials are: "
                         + ", ".join(self.material_names))

    # -- trimesh interoperability --------------------------------------------
    @classmethod
    def from_trimesh(cls, mesh, *, reflectance=(0.7, 0.7, 0.7), emission=(0.0, 0.0, 0.0),
                     name: str = "trimesh") -> "Scene":
        """A scene from a :class:`trimesh.Trimesh`: one patch per face, in face order.

        Parameters
        ----------
        mesh : trimesh.Trimesh
            Faces counter-clockwise seen from the front (trimesh's convention).
        reflectance : (3,) or (n, 3) float in [0, 1)
            One material for all faces, or one reflectance per face.
        emission : (3,) or (n, 3) float >= 0, W/m^2
            Emitted exitance, for all faces or per face.
        name : str

        Returns
        -------
        Scene
            One material ``"trimesh"`` (per-face values are stored as
            per-patch overrides).

        Raises
        ------
        SceneError
            Non-finite vertices, reflectance outside [0, 1), negative emission.
        """
        vertices = np.asarray(mesh.vertices, dtype=np.float64)
        faces = np.asarray(mesh.faces, dtype=np.int64)
        n = len(faces)
        try:
            rho = as_real_array(reflectance, "reflectance")
            em = as_real_array(emission, "emission")
        except InputError as exc:
            raise SceneError(f"{name}: {exc}") from None
        uniform = rho.shape == (3,) and em.shape == (3,)
        material = Material("trimesh", tuple(float(x) for x in (rho if rho.shape == (3,) else (0.0,) * 3)),
                            tuple(float(x) for x in (em if em.shape == (3,) else (0.0,) * 3)))
        rho_n, em_n = np.broadcast_to(rho, (n, 3)), np.broadcast_to(em, (n, 3))
        bad = ~(np.isfinite(rho_n) & (rho_n >= 0) & (rho_n < 1)).all(axis=1)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise SceneError(f"{name}: reflectance of face {i} {tuple(rho_n[i].tolist())} must be in [0, 1)")
        bad = ~(np.isfinite(em_n) & (em_n >= 0)).all(axis=1)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise SceneError(f"{name}: emission of face {i} {tuple(em_n[i].tolist())} must be finite and >= 0")
        return cls(vertices=vertices, faces=faces, material=np.zeros(n, np.int64), materials=(material,),
                   reflectance=None if uniform else rho_n, emission=None if uniform else em_n, name=name)

    def to_trimesh(self):
        """The patches as a :class:`trimesh.Trimesh` (one face per patch, patch order, no merging).

        Per-face ``reflectance`` and ``emission`` (n, 3) go into
        ``mesh.face_attributes``; the face colours show the reflectance.
        """
        import trimesh

        rgba = np.concatenate([np.clip(self.reflectance * 255.0 + 0.5, 0, 255),
                               np.full((self.n_patches, 1), 255.0)], axis=1).astype(np.uint8)
        mesh = trimesh.Trimesh(vertices=np.array(self.vertices), faces=np.array(self.faces),
                               face_colors=rgba, process=False)
        mesh.face_attributes["reflectance"] = np.array(self.reflectance)
        mesh.face_attributes["emission"] = np.array(self.emission)
        return mesh

    def remeshed(self, vertices: np.ndarray, faces: np.ndarray, owner: np.ndarray, *,
                 notes: tuple[str, ...] = ()) -> "Scene":
        """The same surfaces as new triangles: triangle k lies on patch ``owner[k]`` of this scene.

        Cutting patches into pieces, dropping some and reordering them all
        make a scene this way.

        Parameters
        ----------
        vertices : (v, 3) float, metres
        faces : (t, 3) int
            The new triangles, one patch each.
        owner : (t,) int
            The patch of this (unclustered) scene each triangle comes from: it
            takes that patch's material, group, reflectance, emission and
            parent face.
        notes : tuple of str
            Added to ``warnings`` (what was changed).

        Returns
        -------
        Scene
            Unclustered; same materials, groups, occluder mesh and name.

        Raises
        ------
        SceneError
            This scene is clustered (its patches are sets of triangles).
        """
        if self.is_clustered:
            raise SceneError(f"{self.name}: cannot remesh a clustered scene (patches are sets of triangles)")
        owner = np.asarray(owner, dtype=np.int64)
        return Scene(vertices=vertices, faces=faces, material=self.material[owner], materials=self.materials,
                     group=self.group[owner], groups=self.groups, reflectance=self.reflectance[owner],
                     emission=self.emission[owner], parent=self.parent[owner],
                     occluder_vertices=self.occluder_vertices, occluder_faces=self.occluder_faces,
                     name=self.name, warnings=self.warnings + tuple(notes))

    def replace(self, **changes) -> "Scene":
        """A copy with some fields changed (cached geometry is recomputed lazily)."""
        fields = {k: getattr(self, k) for k in self.__dataclass_fields__}
        fields.update(changes)
        return Scene(**fields)
