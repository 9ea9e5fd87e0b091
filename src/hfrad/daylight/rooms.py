"""A sidelit room: a box with one glazed window, for tests, examples and benchmarks.

The room spans ``x`` 0..width, ``y`` (up) 0..height, ``z`` 0..depth; the
window is in the wall at ``z = depth``, which faces south with hfrad's
default north (``-z``). Every face's front (its normal) looks into the room.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from ..scene.patches import subdivide
from ..scene.scene import Material, Scene

__all__ = ["sidelit_room"]


def _quad(corners, inward) -> list[list[float]]:
    c = [np.asarray(p, float) for p in corners]
    n = np.cross(c[1] - c[0], c[2] - c[0])
    if n @ np.asarray(inward, float) < 0:
        c = c[::-1]
    return [c[0], c[1], c[2], c[0], c[2], c[3]]


def sidelit_room(width: float = 4.0, depth: float = 6.0, height: float = 3.0, *, sill: float = 0.9,
                 head: float = 2.4, margin: float = 0.4, wall: float = 0.5, floor: float = 0.2,
                 ceiling: float = 0.8, glazing: tuple[float, float] = (0.08, 0.7), max_edge: float = 0.5,
                 window: bool = True) -> Scene:
    """A box room with a window (module docstring), subdivided to ``max_edge`` metres.

    Parameters
    ----------
    width, depth, height : float, metres
    sill, head : float, metres above the floor: the window's bottom and top
    margin : float, metres of wall left and right of the window
    wall, floor, ceiling : float, grey reflectances
    glazing : (reflectance, transmittance) of the pane at normal incidence
    max_edge : float, metres: longest patch edge
    window : bool
        False: the opening is wall (a closed box).

    Returns
    -------
    Scene with materials ``floor``, ``ceiling``, ``wall``, ``glass``.
    """
    W, D, H = float(width), float(depth), float(height)
    if not (0 <= sill < head <= H and 0 <= 2 * margin < W and min(W, D, H) > 0):
        raise InputError(f"sidelit room: need 0 <= sill < head <= height and 2 margin < width, got sill {sill}, "
                         f"head {head}, height {H}, margin {margin}, width {W}")
    tris, mats = [], []

    def add(corners, inward, m):
        tris.extend(_quad(corners, inward))
        mats.extend([m, m])

    add([(0, 0, 0), (W, 0, 0), (W, 0, D), (0, 0, D)], (0, 1, 0), 0)          # floor
    add([(0, H, 0), (W, H, 0), (W, H, D), (0, H, D)], (0, -1, 0), 1)         # ceiling
    add([(0, 0, 0), (W, 0, 0), (W, H, 0), (0, H, 0)], (0, 0, 1), 2)          # north wall
    add([(0, 0, 0), (0, 0, D), (0, H, D), (0, H, 0)], (1, 0, 0), 2)          # west wall
    add([(W, 0, 0), (W, 0, D), (W, H, D), (W, H, 0)], (-1, 0, 0), 2)         # east wall
    x0, x1 = margin, W - margin
    south = (0, 0, -1)
    for (a, b, y0, y1) in ((0, W, 0, sill), (0, W, head, H), (0, x0, sill, head), (x1, W, sill, head)):
        if b > a and y1 > y0:
            add([(a, y0, D), (b, y0, D), (b, y1, D), (a, y1, D)], south, 2)
    add([(x0, sill, D), (x1, sill, D), (x1, head, D), (x0, head, D)], south, 3 if window else 2)
    V = np.array(tris, float)
    F = np.arange(len(V)).reshape(-1, 3)
    rho_g, tau_g = glazing
    materials = (Material("floor", (floor,) * 3), Material("ceiling", (ceiling,) * 3), Material("wall", (wall,) * 3),
                 Material("glass", (rho_g,) * 3, transmittance=(tau_g,) * 3))
    scene = Scene(V, F, np.array(mats), materials, name="sidelit room")
    return subdivide(scene, max_edge=max_edge)
