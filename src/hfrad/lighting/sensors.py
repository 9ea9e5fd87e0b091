"""Sensor points and work-plane grids.

A sensor file has one sensor a line, ``x y z nx ny nz`` (position in metres,
the direction the sensor faces), as Radiance's ``rtrace -I`` reads it; blank
lines and ``#`` comments are skipped. A work plane is a grid of sensors facing
up at a height above a rectangle or above a floor's outline, cell centres
``spacing`` apart (EN 12464-1 grids). hfrad's scenes are y-up: heights are y,
plans are (x, z).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..atomic import atomic_path
from ..errors import FileFormatError, InputError
from .limits import check_grid_size

__all__ = ["SensorSet", "read_sensors", "write_sensors", "rectangle_grid", "floor_grid", "plan_grid"]


@dataclass(frozen=True, eq=False)
class SensorSet:
    """Named sensors; a grid also knows its cells (for the plan image).

    Attributes
    ----------
    name : str
    points : (m, 3) float, metres
    normals : (m, 3) float, unit
    cells : (m, 2) int or None
        (column along x, row along z) of each sensor in the plan grid.
    shape : (nx, nz) or None
    origin : (2,) float or None
        (x, z) of the corner of cell (0, 0).
    spacing : float or None, metres
    """

    name: str
    points: np.ndarray
    normals: np.ndarray
    cells: np.ndarray | None = None
    shape: tuple | None = None
    origin: tuple | None = None
    spacing: float | None = None

    def __post_init__(self) -> None:
        P = np.asarray(self.points, np.float64).reshape(-1, 3)
        N = np.asarray(self.normals, np.float64).reshape(-1, 3)
        if P.shape != N.shape:
            raise InputError(f"sensors {self.name!r}: {len(P)} points but {len(N)} normals")
        if not (np.isfinite(P).all() and np.isfinite(N).all()):
            raise InputError(f"sensors {self.name!r}: a position or normal is not finite")
        length = np.linalg.norm(N, axis=1)
        if (length == 0).any():
            raise InputError(f"sensors {self.name!r}: sensor {int(np.flatnonzero(length == 0)[0])} has a zero normal")
        object.__setattr__(self, "points", P)
        off = np.abs(length - 1.0) > 1e-12                 # unit normals are kept bit for bit (file round trips)
        N = N.copy()
        N[off] /= length[off, None]
        object.__setattr__(self, "normals", N)

    def __len__(self) -> int:
        return len(self.points)

    @property
    def is_grid(self) -> bool:
        return self.cells is not None


def read_sensors(path: "str | Path", name: str | None = None) -> SensorSet:
    """Sensors of a file of ``x y z nx ny nz`` lines.

    Raises
    ------
    FileNotFoundError
    FileFormatError
        A line without six numbers (names the line), a zero normal, or no sensors.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such sensor file")
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as exc:
        raise FileFormatError(f"{path}: not a text sensor file (byte {exc.start} is not UTF-8); expected "
                              "lines 'x y z nx ny nz'") from None
    if "\0" in text:
        raise FileFormatError(f"{path}: a binary file, not a text sensor file of lines 'x y z nx ny nz'")
    rows = []
    for i, line in enumerate(text.splitlines(), 1):
        s = line.split("#", 1)[0].strip()
        if not s:
            continue
        parts = s.replace(",", " ").split()
        try:
            vals = [float(x) for x in parts]
        except ValueError:
            raise FileFormatError(f"{path}:{i}: expected six numbers 'x y z nx ny nz', got {s!r}") from None
        if len(vals) != 6 or not all(math.isfinite(v) for v in vals):
            raise FileFormatError(f"{path}:{i}: expected six finite numbers 'x y z nx ny nz', got {s!r}")
        if vals[3] == vals[4] == vals[5] == 0:
            raise FileFormatError(f"{path}:{i}: the sensor's normal (nx ny nz) is zero")
        rows.append(vals)
    if not rows:
        raise FileFormatError(f"{path}: no sensors (expected lines 'x y z nx ny nz')")
    a = np.array(rows)
    return SensorSet(name or path.stem, a[:, :3], a[:, 3:])


def write_sensors(path: "str | Path", sensors: SensorSet) -> Path:
    """Write ``x y z nx ny nz`` lines (full float precision, round-trips exactly), atomically."""
    path = Path(path)
    text = "".join(" ".join(repr(float(v)) for v in row) + "\n"
                   for row in np.hstack([sensors.points, sensors.normals]))
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return path


def _check_grid(spacing: float, height: float, margin: float = 0.0) -> None:
    if not (isinstance(spacing, (int, float)) and math.isfinite(spacing) and spacing > 0):
        raise InputError(f"grid spacing must be a finite number > 0 m, got {spacing!r}")
    if not (isinstance(height, (int, float)) and math.isfinite(height)):
        raise InputError(f"grid height must be a finite number (m), got {height!r}")
    if not (isinstance(margin, (int, float)) and math.isfinite(margin) and margin >= 0):
        raise InputError(f"grid margin must be a finite number >= 0 m, got {margin!r}")


def rectangle_grid(x: tuple[float, float], z: tuple[float, float], height: float, spacing: float, *,
                   name: str = "workplane", margin: float = 0.0) -> SensorSet:
    """Sensors facing up (+y) at ``y = height`` over ``x0..x1`` by ``z0..z1``, cell centres ``spacing`` apart.

    ``margin`` (metres) is left out at every edge (EN 12464-1's 0.5 m border
    zone, when wanted). The cells cover the rectangle exactly: their number
    is ``ceil(width / spacing)``, their size width / count (<= spacing).
    """
    _check_grid(spacing, height, margin)
    x0, x1 = float(x[0]) + margin, float(x[1]) - margin
    z0, z1 = float(z[0]) + margin, float(z[1]) - margin
    if not (x1 > x0 and z1 > z0):
        raise InputError(f"grid rectangle is empty: x {x0:g}..{x1:g}, z {z0:g}..{z1:g} (after a margin of {margin:g})")
    check_grid_size(math.ceil((x1 - x0) / spacing) * math.ceil((z1 - z0) / spacing), spacing)
    nx = max(1, int(math.ceil((x1 - x0) / spacing - 1e-9)))
    nz = max(1, int(math.ceil((z1 - z0) / spacing - 1e-9)))
    dx, dz = (x1 - x0) / nx, (z1 - z0) / nz
    I, J = np.meshgrid(np.arange(nx), np.arange(nz), indexing="ij")
    cells = np.stack([I.ravel(), J.ravel()], axis=1)
    P = np.stack([x0 + (cells[:, 0] + 0.5) * dx, np.full(len(cells), float(height)),
                  z0 + (cells[:, 1] + 0.5) * dz], axis=1)
    N = np.tile([0.0, 1.0, 0.0], (len(P), 1))
    return SensorSet(name, P, N, cells, (nx, nz), (x0, z0), float(max(dx, dz)))


def _inside_triangles(pts: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """(p,) bool: 2-D points inside any of the 2-D triangles (t, 3, 2), edges included."""
    inside = np.zeros(len(pts), bool)
    rows = max(1, (1 << 22) // max(1, min(len(tri), 4096)))   # points per pass: (rows, 4096) arrays of ~32 MB
    if len(pts) > rows:
        for start in range(0, len(pts), rows):
            inside[start:start + rows] = _inside_triangles(pts[start:start + rows], tri)
        return inside
    for start in range(0, len(tri), 4096):
        t = tri[start:start + 4096]
        a, b, c = t[:, 0], t[:, 1], t[:, 2]

        def side(p1, p2):
            return ((p2[None, :, 0] - p1[None, :, 0]) * (pts[:, None, 1] - p1[None, :, 1])
                    - (p2[None, :, 1] - p1[None, :, 1]) * (pts[:, None, 0] - p1[None, :, 0]))
        s1, s2, s3 = side(a, b), side(b, c), side(c, a)
        tol = 1e-12
        pos = (s1 >= -tol) & (s2 >= -tol) & (s3 >= -tol)
        neg = (s1 <= tol) & (s2 <= tol) & (s3 <= tol)
        inside |= (pos | neg).any(axis=1)
    return inside


def floor_grid(scene, height: float, spacing: float, *, material: str = "floor", name: str = "workplane",
               margin: float = 0.0) -> SensorSet:
    """A work plane over the outline of the scene's floor (its patches of ``material``) at ``height`` above it.

    The grid covers the floor's bounding box in plan (x, z); a sensor is kept
    when its plan position lies on a floor triangle (so L-shaped rooms get an
    L-shaped grid) and, with a ``margin``, so do the 16 points at that
    distance around it (the border zone follows the outline). ``height`` is
    measured from the floor's lowest point.

    Raises
    ------
    InputError
        No such material, or no sensor falls on the floor.
    """
    if material not in scene.material_names:
        raise InputError(f"floor material {material!r} is not in the scene; its materials are: "
                         + ", ".join(scene.material_names))
    mi = scene.material_names.index(material)
    patch = np.asarray(scene.patch_of_triangle)
    tri = np.asarray(scene.triangles)[scene.material[patch] == mi]
    if not len(tri):
        raise InputError(f"the scene has no {material!r} patch to lay a grid on")
    y0 = float(tri[..., 1].min())
    return plan_grid(tri[..., [0, 2]], y0 + height, spacing, name=name, margin=margin, what=f"the {material!r} outline")


def plan_grid(plan: np.ndarray, y: float, spacing: float, *, name: str = "workplane", margin: float = 0.0,
              what: str = "the outline") -> SensorSet:
    """Sensors facing up at ``y`` over an outline given as plan triangles (t, 3, 2) of (x, z).

    The grid of :func:`rectangle_grid` over the outline's bounding box, a
    sensor kept when it lies on a triangle and, with a ``margin``, so do the
    16 points at that distance around it (:func:`floor_grid`, IfcSpace grids).

    Raises
    ------
    InputError
        No sensor falls on the outline.
    """
    lo, hi = plan.reshape(-1, 2).min(axis=0), plan.reshape(-1, 2).max(axis=0)
    full = rectangle_grid((lo[0], hi[0]), (lo[1], hi[1]), y, spacing, name=name, margin=margin)
    xz = full.points[:, [0, 2]]
    keep = _inside_triangles(xz, plan)
    if margin > 0:                         # the border zone follows the outline: the points margin away inside too
        for a in np.radians(np.arange(0, 360, 22.5)):
            keep &= _inside_triangles(xz + margin * np.array([np.cos(a), np.sin(a)]), plan)
    if not keep.any():
        raise InputError(f"no grid point of spacing {spacing:g} m falls on {what}")
    return SensorSet(name, full.points[keep], full.normals[keep], full.cells[keep], full.shape, full.origin,
                     full.spacing)
