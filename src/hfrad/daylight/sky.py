"""Sky and sun matrices of a year from Radiance's ``gendaymtx`` (Perez all-weather), and the patches' geometry.

``gendaymtx`` (run through :mod:`pyradiance`, no shell) turns each record of
a weather tape into the radiance of Reinhart's sky patches: MF:1 is
Tregenza's 145 patches, MF:m splits each into m x m (the zenith cap stays
one), plus the ground as patch 0. Its output is visible radiance, W/(sr m^2)
in Radiance's units (``-O0``, the default; ``-O1`` would be solar radiance);
luminance is 179 lm/W x the weighted RGB (:data:`RADIANCE_LUMINANCE`).
``-s`` gives the sky alone (with the ground, which reflects sky and sun),
``-d`` the sun alone, spread over its 4 nearest patches so that
``sum_p L_p Omega_p`` is the direct-normal illuminance / 179. ``-d`` writes
the whole ground glow too (the same value as ``-s``): it is dropped from the
sun matrix, so that the ground counts once.

Patch geometry (Radiance's convention, as in ``reinhart.cal``): rows of
altitude ``alpha = 90 deg / (7 MF + 0.5)`` from the horizon up, 30, 30, 24,
24, 18, 12, 6 patches per row (x MF), the first of each row centred due
north, counting toward east; the zenith cap above; the ground below the
horizon (2 pi sr).
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from .weather import Weather

__all__ = ["SkyPatches", "sky_patches", "sky_matrices", "RADIANCE_LUMINANCE", "direction"]

#: lm/W x RGB weights of Radiance's luminance (47.4 R + 119.9 G + 11.6 B), its primaries
RADIANCE_LUMINANCE = 179.0 * np.array([0.265, 0.670, 0.065])
_ROWS = (30, 30, 24, 24, 18, 12, 6)
SUBDIVISIONS = (1, 2, 4)


def _hammersley(n: int) -> tuple[np.ndarray, np.ndarray]:
    """(n,), (n,) in (0, 1): ``(i + 1/2) / n`` and the base-2 radical inverse of ``i`` (shifted by 1 / 2n)."""
    i = np.arange(n)
    v = np.zeros(n)
    bit, x = 0.5, i.copy()
    while x.any():
        v += bit * (x & 1)
        x >>= 1
        bit /= 2
    return (i + 0.5) / n, v + 0.5 / n


class SkyPatches:
    """Reinhart patches (ground first, zenith last) with sample directions.

    Attributes
    ----------
    mf : int
    solid_angle : (p,) float, sr
    alt_range, azi_range : (p, 2) float, radians: each patch's altitude and azimuth span
    """

    def __init__(self, mf: int) -> None:
        if mf not in SUBDIVISIONS:
            raise InputError(f"Reinhart subdivision must be one of {SUBDIVISIONS}, got {mf!r}")
        self.mf = mf
        alpha = (np.pi / 2) / (7 * mf + 0.5)
        alt, azi = [(-np.pi / 2, 0.0)], [(0.0, 2 * np.pi)]                     # ground
        for i in range(7 * mf):
            n = _ROWS[i // mf] * mf
            for j in range(n):
                alt.append((alpha * i, alpha * (i + 1)))
                azi.append((2 * np.pi * (j - 0.5) / n, 2 * np.pi * (j + 0.5) / n))
        alt.append((alpha * 7 * mf, np.pi / 2))                                # zenith cap
        azi.append((0.0, 2 * np.pi))
        self.alt_range, self.azi_range = np.array(alt), np.array(azi)
        s = np.sin(self.alt_range)
        self.solid_angle = (self.azi_range[:, 1] - self.azi_range[:, 0]) * (s[:, 1] - s[:, 0])

    def __len__(self) -> int:
        return len(self.solid_angle)

    def samples(self, k: int) -> list[tuple[np.ndarray, np.ndarray]]:
        """Per patch, ``k^2`` directions (altitude, azimuth) radians, each of solid angle ``Omega_p / k^2``.

        A Hammersley set in (sin altitude, azimuth) over the patch: ``k^2`` points, each alone
        in its row and in its column of a ``k^2 x k^2`` grid of equal solid angles. A window's
        edge (close to a line of constant altitude or azimuth) then crosses the points one at a
        time, not a whole row of a ``k x k`` grid at once: the error of a patch seen in part
        falls as 1/k^2, not 1/k. The ground (2 pi sr, 80 times a sky patch at MF:1) gets
        ``(8k)^2`` points, so that a room's own floor or a neighbour's roof seen below the
        horizon is resolved as finely as the sky.
        """
        s = np.sin(self.alt_range)
        out = []
        for p in range(len(self)):
            n = (8 * k if p == 0 else k) ** 2
            u, v = _hammersley(n)
            sa = s[p, 0] + (s[p, 1] - s[p, 0]) * u
            az = self.azi_range[p, 0] + (self.azi_range[p, 1] - self.azi_range[p, 0]) * v
            out.append((np.arcsin(sa), az))
        return out

    def neighbours(self) -> np.ndarray:
        """(p, p) bool: patches that share an edge or a corner (the ground touches the lowest row, the
        zenith cap the highest; azimuths wrap around)."""
        lo, hi = self.alt_range[:, 0], self.alt_range[:, 1]
        centre = self.azi_range.mean(axis=1)
        half = 0.5 * (self.azi_range[:, 1] - self.azi_range[:, 0])
        tol = 1e-9
        rows_touch = (np.abs(hi[:, None] - lo[None, :]) < tol) | (np.abs(lo[:, None] - hi[None, :]) < tol)
        same_row = (np.abs(lo[:, None] - lo[None, :]) < tol) & (np.abs(hi[:, None] - hi[None, :]) < tol)
        gap = np.abs(np.angle(np.exp(1j * (centre[:, None] - centre[None, :]))))     # azimuth apart, wrapped
        near = gap <= half[:, None] + half[None, :] + 1e-6
        out = (rows_touch | same_row) & near
        np.fill_diagonal(out, False)
        return out


def sky_patches(mf: int = 1) -> SkyPatches:
    return SkyPatches(mf)


def direction(altitude: np.ndarray, azimuth: np.ndarray, north: float = 0.0) -> np.ndarray:
    """(..., 3) unit vectors in hfrad's y-up frame toward (altitude, azimuth) radians.

    North is ``-z`` turned ``north`` degrees toward ``+x`` (clockwise in a plan seen
    from above); east is north turned 90 degrees the same way; up is ``+y``.
    """
    t = np.radians(north)
    n = np.array([np.sin(t), 0.0, -np.cos(t)])
    e = np.array([np.cos(t), 0.0, np.sin(t)])
    ca = np.cos(altitude)[..., None]
    return ca * np.sin(azimuth)[..., None] * e + ca * np.cos(azimuth)[..., None] * n \
        + np.sin(altitude)[..., None] * np.array([0.0, 1.0, 0.0])


def _run(weather: Weather, mf: int, *, sun: bool, ground: float) -> np.ndarray:
    import pyradiance as pr

    try:
        out = pr.gendaymtx(weather.wea().encode(), header=True, outform="f", mfactor=mf,
                           sun_only=sun, sky_only=not sun, ground_color=[ground] * 3)
    except Exception as exc:    # pyradiance reports gendaymtx's own message
        last = (str(exc).strip().splitlines() or [type(exc).__name__])[-1]
        raise InputError(f"{weather.path}: gendaymtx failed ({last})") from None
    end = out.find(b"\n\n")
    head = out[:end].decode(errors="replace")
    fields = dict(line.split("=", 1) for line in head.splitlines() if "=" in line)
    rows, cols = int(fields["NROWS"]), int(fields["NCOLS"])
    data = np.frombuffer(out[end + 2:], dtype="<f4" if fields.get("BigEndian", "0") == "0" else ">f4")
    return data.reshape(rows, cols, 3).transpose(0, 2, 1).astype(np.float64)   # (p, 3, h)


def sky_matrices(weather: Weather, mf: int = 1, *, ground: float = 0.2) -> tuple[np.ndarray, np.ndarray]:
    """(sky, sun), each (p, 3, h) float, W/(sr m^2) visible: Perez skies (with ground) and suns of every hour.

    Parameters
    ----------
    weather : Weather
    mf : {1, 2, 4}
        Reinhart subdivision (146, 578, 2306 patches with the ground).
    ground : float
        Ground reflectance (gendaymtx ``-g``; 0.2 as Radiance's default).
    """
    SkyPatches(mf)
    if not (0.0 <= ground < 1.0):
        raise InputError(f"ground reflectance must be in [0, 1), got {ground}")
    sky, sun = _run(weather, mf, sun=False, ground=ground), _run(weather, mf, sun=True, ground=ground)
    # gendaymtx writes the same ground, (diffuse + direct x sin(altitude)) x rho_g / pi, with -s and
    # with -d: it is the whole ground glow. It is kept once, in the sky matrix.
    sun[0] = 0.0
    return sky, sun
