"""A pinhole camera and its primary rays.

Conventions: right-handed world, ``up`` is usually +y, the image's first row is
its top. A pixel (i, j) looks through the centre of its square,

    d = normalize(forward + x * tan(fov/2) * aspect * right + y * tan(fov/2) * up'),
    x = 2 (j + 1/2) / W - 1,   y = 1 - 2 (i + 1/2) / H,

with ``fov`` the *vertical* field of view and ``aspect = W / H``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import InputError

#: Field of view of the named views, degrees (the classic Cornell box camera is ~39.3).
DEFAULT_FOV = 40.0
_MARGIN = 1.05  # framing slack so the scene does not touch the image border


#: Smallest half-size a framed box is given (a point scene still gets a camera).
_TINY = 1e-300

#: Field of view of the inside view, degrees (wider: a room seen from within).
INSIDE_FOV = 60.0

#: Candidate positions per axis of the bounding box, and rays cast from each, for the inside view.
_INSIDE_GRID = 7
_INSIDE_RAYS = 96

#: A candidate is inside a room if this fraction of its rays hits the front of a face.
_ENCLOSED = 0.9


@dataclass(frozen=True)
class Camera:
    """A pinhole camera.

    Parameters
    ----------
    position, target : (3,) float, metres
        Eye point and the point it looks at (the image centre).
    up : (3,) float
        Approximate up direction; made orthogonal to the view direction.
    fov : float, degrees
        Vertical field of view, in (0, 180).
    """

    position: tuple[float, float, float]
    target: tuple[float, float, float]
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)
    fov: float = DEFAULT_FOV

    def __post_init__(self) -> None:
        p, t, u = (np.asarray(v, dtype=np.float64).reshape(3) for v in (self.position, self.target, self.up))
        if not (np.isfinite(p).all() and np.isfinite(t).all() and np.isfinite(u).all()):
            raise InputError(f"camera position, target and up must be finite, got {tuple(p.tolist())}, "
                             f"{tuple(t.tolist())}, {tuple(u.tolist())}")
        if np.linalg.norm(t - p) == 0:
            raise InputError(f"camera target must differ from its position, both are {tuple(p.tolist())}")
        if not 0 < self.fov < 180:
            raise InputError(f"camera fov must be in (0, 180) degrees, got {self.fov}")
        f = (t - p) / np.linalg.norm(t - p)
        if np.linalg.norm(np.cross(f, u)) < 1e-9 * max(np.linalg.norm(u), 1e-300):
            raise InputError(f"camera up {tuple(u.tolist())} is parallel to the view direction {tuple(f.round(6).tolist())}; "
                             "give another up vector")
        object.__setattr__(self, "position", tuple(map(float, p)))
        object.__setattr__(self, "target", tuple(map(float, t)))
        object.__setattr__(self, "up", tuple(map(float, u)))

    # -- frame ------------------------------------------------------------------
    def basis(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Orthonormal (forward, right, up) of the image plane."""
        p, t, u = np.array(self.position), np.array(self.target), np.array(self.up)
        forward = (t - p) / np.linalg.norm(t - p)
        right = np.cross(forward, u)
        right /= np.linalg.norm(right)
        return forward, right, np.cross(right, forward)

    def rays(self, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """Primary rays through pixel centres.

        Returns
        -------
        origins : (height * width, 3) float
            All equal to ``position``.
        directions : (height * width, 3) float, unit
            Row-major, first row at the top of the image.
        """
        col, row = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
        return self.rays_at(col.ravel(), row.ravel(), width, height)

    def rays_at(self, col: np.ndarray, row: np.ndarray, width: int, height: int
                ) -> tuple[np.ndarray, np.ndarray]:
        """Rays through continuous pixel positions (``col``, ``row``) in pixel units.

        Pixel (i, j) covers ``col`` in [j, j + 1) and ``row`` in [i, i + 1);
        its centre is (j + 0.5, i + 0.5). Returns (r, 3) origins and unit directions.
        """
        forward, right, up = self.basis()
        half_h = math.tan(math.radians(self.fov) / 2)
        half_w = half_h * width / height
        x = (np.asarray(col, dtype=np.float64) * (2.0 / width) - 1.0) * half_w
        y = (1.0 - np.asarray(row, dtype=np.float64) * (2.0 / height)) * half_h
        d = forward[None] + x[:, None] * right[None] + y[:, None] * up[None]
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        origins = np.broadcast_to(np.array(self.position), d.shape)
        return np.ascontiguousarray(origins), d

    # -- named views --------------------------------------------------------------
    @classmethod
    def front(cls, bounds: np.ndarray, *, aspect: float = 1.0, fov: float = DEFAULT_FOV) -> "Camera":
        """Straight view along -z onto the scene's bounding box, from the +z side.

        For the Cornell box (x, z in [-1, 1], y in [0, 2]) this is the classic
        camera: position ~(0, 1, 3.9), target (0, 1, 0), looking in through the
        open (here: back-facing, hence transparent) front wall.
        """
        lo, hi = np.asarray(bounds, dtype=np.float64)
        # a flat box keeps a sliver of depth relative to its size (an absolute floor blacked out small scenes)
        centre, half = (lo + hi) / 2, np.maximum((hi - lo) / 2, 1e-9 * max(float(np.max(hi - lo)) / 2, _TINY))
        tan_v = math.tan(math.radians(fov) / 2)
        # the front face of the box must fit both vertically and horizontally
        dist = _MARGIN * max(half[1] / tan_v, half[0] / (tan_v * aspect)) + half[2]
        return cls(tuple(centre + [0.0, 0.0, dist]), tuple(centre), (0.0, 1.0, 0.0), fov)

    @classmethod
    def auto(cls, bounds: np.ndarray, *, aspect: float = 1.0, fov: float = DEFAULT_FOV,
             azimuth: float = 30.0, elevation: float = 20.0) -> "Camera":
        """Three-quarter view of the bounding sphere of ``bounds``.

        The camera sits ``azimuth`` degrees to the right of +z (around +y) and
        ``elevation`` degrees above the horizontal plane through the bounding
        box centre, far enough for the whole bounding sphere to fit the image.
        Walls seen from behind are transparent in :func:`~hfrad.render.render_image`,
        so closed rooms show their inside like a cut-away drawing.
        """
        lo, hi = np.asarray(bounds, dtype=np.float64)
        centre = (lo + hi) / 2
        radius = max(float(np.linalg.norm(hi - lo)) / 2, _TINY)
        half_v = math.radians(fov) / 2
        half_fov = min(half_v, math.atan(math.tan(half_v) * aspect))  # the narrower of the two
        dist = _MARGIN * radius / math.sin(half_fov)
        az, el = math.radians(azimuth), math.radians(elevation)
        offset = dist * np.array([math.sin(az) * math.cos(el), math.sin(el), math.cos(az) * math.cos(el)])
        return cls(tuple(centre + offset), tuple(centre), (0.0, 1.0, 0.0), fov)

    @classmethod
    def inside(cls, scene) -> "Camera | None":
        """A view from within the largest enclosed space of ``scene``, down its longest free line.

        Candidate positions fill the bounding box (a 7 x 7 x 7 grid); from each,
        96 rays in directions spread evenly over the sphere are cast. A position
        is inside a room when at least 90% of them hit the front of a face (from
        outside, or inside a solid, rays escape or meet backs). Of those, the one
        with the largest median distance to the surfaces is the room's middle;
        the camera looks along the most nearly level of its rays with the
        longest free run (the length of a nave, not the height of a vault),
        standing half-way between that middle and the wall behind it.

        Parameters
        ----------
        scene : Scene

        Returns
        -------
        Camera or None
            None when no position is enclosed (an open scene: use ``auto``).
        """
        from .raycast import patch_caster

        if not scene.n_patches:
            return None
        lo, hi = np.asarray(scene.bounds, dtype=np.float64)
        g = (np.arange(_INSIDE_GRID) + 0.5) / _INSIDE_GRID
        grid = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
        points = lo + grid * (hi - lo)
        dirs = _sphere(_INSIDE_RAYS)
        caster = patch_caster(scene)
        try:
            o = np.repeat(points, len(dirs), axis=0)
            d = np.tile(dirs, (len(points), 1))
            face, dist, _ = caster.intersect(o, d)
            tri_n = np.asarray(scene.triangle_normals)
            front = (face >= 0) & (np.einsum("rd,rd->r", tri_n[np.maximum(face, 0)], d) < 0)
            front = front.reshape(len(points), len(dirs))
            dist = np.where(front, dist.reshape(front.shape), 0.0)
            enclosed = front.mean(axis=1) >= _ENCLOSED
            if not enclosed.any():
                return None
            size = np.where(enclosed, np.median(dist, axis=1), -1.0)
            k = int(np.argmax(size))
            level = np.abs(dirs[:, 1]) < 0.35  # within about 20 degrees of horizontal (y up)
            run = np.where(level & front[k], dist[k], -1.0)
            j = int(np.argmax(run))
            back = caster.intersect(points[k:k + 1], -dirs[j:j + 1])[1]
        finally:
            caster.close()
        behind = float(back[0]) if np.isfinite(back[0]) else 0.0
        position = points[k] - 0.5 * behind * dirs[j]
        target = points[k] + 0.5 * float(dist[k, j]) * dirs[j]
        return cls(tuple(position), tuple(target), (0.0, 1.0, 0.0), INSIDE_FOV)

    @classmethod
    def first_view(cls, scene, *, aspect: float = 1.0) -> "Camera":
        """The three-quarter view (:meth:`auto`), or the inside view where that shows a building's outside.

        A room modelled with one-sided walls facing in (the Cornell box) is seen
        through the backs of its near walls, so the three-quarter view shows its
        inside. A building with outer walls (Sponza, Šibenik) shows those: when
        most pixels of a small trial picture hit faces turned away from the
        scene's centre, the inside view (:meth:`inside`) is taken instead.
        """
        from .raycast import trace_camera

        cam = cls.auto(scene.bounds, aspect=aspect)
        if not scene.n_patches:
            return cam
        face, _, _ = trace_camera(scene, cam, 48, max(1, round(48 / aspect)))
        hit = face[face >= 0]
        if not hit.size:
            return cam
        tri = np.asarray(scene.triangles)[hit]
        centre = 0.5 * (scene.bounds[0] + scene.bounds[1])
        outward = np.einsum("pd,pd->p", np.asarray(scene.triangle_normals)[hit], tri.mean(axis=1) - centre) > 0
        if outward.mean() <= 0.5:
            return cam
        inside = cls.inside(scene)
        return inside if inside is not None else cam

    def spec(self) -> str:
        """The ``x,y,z:tx,ty,tz:fov`` string :meth:`parse` reads back (for ``--camera``)."""
        def xyz(v) -> str:
            return ",".join(f"{float(x):.4g}" for x in v)
        return f"{xyz(self.position)}:{xyz(self.target)}:{self.fov:g}"

    @classmethod
    def parse(cls, spec: "str | Camera", bounds: np.ndarray, *, aspect: float = 1.0, scene=None) -> "Camera":
        """A camera from ``'auto'``, ``'front'``, ``'inside'`` or ``'x,y,z:tx,ty,tz[:fov]'``.

        ``'inside'`` needs ``scene`` (:meth:`inside`) and falls back to ``'auto'``
        for a scene with no enclosed space. With ``scene``, ``'auto'`` is
        :meth:`first_view`: the inside view where the three-quarter view would
        show the outside of a building.

        Raises
        ------
        InputError
            For any other string, quoting it and the accepted forms.
        """
        if isinstance(spec, Camera):
            return spec
        text = str(spec).strip()
        if text == "inside" and scene is not None:
            cam = cls.inside(scene)
            return cam if cam is not None else cls.auto(bounds, aspect=aspect)
        if text == "auto" and scene is not None:
            return cls.first_view(scene, aspect=aspect)
        if text in ("auto", "inside"):  # no scene to look inside yet (a spec checked early)
            return cls.auto(bounds, aspect=aspect)
        if text == "front":
            return cls.front(bounds, aspect=aspect)
        parts = text.split(":")
        pos = tgt = ()
        fov = DEFAULT_FOV
        if len(parts) in (2, 3):
            try:
                pos = tuple(float(v) for v in parts[0].split(","))
                tgt = tuple(float(v) for v in parts[1].split(","))
                fov = float(parts[2]) if len(parts) == 3 else DEFAULT_FOV
            except ValueError:              # a part that is not a number
                pos = ()
        if len(pos) != 3 or len(tgt) != 3:
            raise InputError(f"camera must be 'auto', 'front', 'inside' or 'x,y,z:tx,ty,tz[:fov_degrees]', got '{text}'")
        return cls(pos, tgt, (0.0, 1.0, 0.0), fov)


def _sphere(n: int) -> np.ndarray:
    """(n, 3) unit vectors spread evenly over the sphere (a Fibonacci lattice)."""
    k = np.arange(n) + 0.5
    y = 1.0 - 2.0 * k / n
    r = np.sqrt(np.maximum(0.0, 1.0 - y * y))
    phi = k * math.pi * (3.0 - math.sqrt(5.0))
    return np.column_stack([r * np.cos(phi), y, r * np.sin(phi)])
