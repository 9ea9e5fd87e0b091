"""Closed-form view factors from the thermal-radiation catalogue.

Reference values for testing the numerical form factors. Every function
returns F_{1->2}, the fraction of the diffuse energy leaving surface 1 that
reaches surface 2 (dimensionless, in [0, 1]). Lengths in any consistent unit.

References
----------
.. [1] J. R. Howell, "A Catalog of Radiation Heat Transfer Configuration
   Factors", 3rd ed., University of Texas at Austin (configurations C-11,
   C-13, C-14, C-41), http://www.thermalradiation.net/indexCat.html
.. [2] J. R. Howell, M. P. Menguc, K. Daun, R. Siegel, "Thermal Radiation Heat
   Transfer", 7th ed., CRC Press, 2021, appendix C.
"""

from __future__ import annotations

import math

from ..errors import InputError

__all__ = [
    "parallel_rectangles",
    "parallel_rectangles_offset",
    "perpendicular_rectangles",
    "coaxial_disks",
]


def _positive(**values: float) -> None:
    for name, v in values.items():
        if not (v > 0 and math.isfinite(v)):
            raise InputError(f"{name} must be a positive finite length, got {v}")


def parallel_rectangles(width: float, depth: float, distance: float) -> float:
    """Two equal, parallel, directly opposed rectangles (catalogue C-11 [1]_).

    With X = width / distance and Y = depth / distance:

        F = 2 / (pi X Y) { ln sqrt((1+X^2)(1+Y^2) / (1+X^2+Y^2))
                           + X sqrt(1+Y^2) atan(X / sqrt(1+Y^2))
                           + Y sqrt(1+X^2) atan(Y / sqrt(1+X^2))
                           - X atan X - Y atan Y }

    Examples
    --------
    >>> round(parallel_rectangles(1.0, 1.0, 1.0), 6)
    0.199825
    """
    _positive(width=width, depth=depth, distance=distance)
    X, Y = width / distance, depth / distance
    x1, y1 = 1 + X * X, 1 + Y * Y
    return 2 / (math.pi * X * Y) * (
        0.5 * math.log(x1 * y1 / (1 + X * X + Y * Y))
        + X * math.sqrt(y1) * math.atan(X / math.sqrt(y1))
        + Y * math.sqrt(x1) * math.atan(Y / math.sqrt(x1))
        - X * math.atan(X) - Y * math.atan(Y))


def parallel_rectangles_offset(rect1: tuple[float, float, float, float],
                               rect2: tuple[float, float, float, float], distance: float) -> float:
    """Two parallel rectangles with sides aligned, in general position (catalogue C-13 [1]_).

    Parameters
    ----------
    rect1 : (x1, x2, y1, y2)
        Surface 1, the rectangle [x1, x2] x [y1, y2] in its plane.
    rect2 : (xi1, xi2, eta1, eta2)
        Surface 2, [xi1, xi2] x [eta1, eta2] in the parallel plane.
    distance : float
        Distance z between the planes.

    Notes
    -----
    F_{1->2} = 1 / ((x2-x1)(y2-y1)) sum_{l,k,j,i=1,2} (-1)^(i+j+k+l) G(x_i, y_j, eta_k, xi_l),

        G = 1/(2 pi) { (y-eta) sqrt((x-xi)^2+z^2) atan((y-eta) / sqrt((x-xi)^2+z^2))
                     + (x-xi) sqrt((y-eta)^2+z^2) atan((x-xi) / sqrt((y-eta)^2+z^2))
                     - z^2/2 ln((x-xi)^2 + (y-eta)^2 + z^2) }

    Covers unequal directly opposed (concentric) rectangles and offset ones.

    Examples
    --------
    >>> abs(parallel_rectangles_offset((0, 2, 0, 1), (0, 2, 0, 1), 1.5)
    ...     - parallel_rectangles(2, 1, 1.5)) < 1e-12
    True
    """
    x1, x2, y1, y2 = map(float, rect1)
    s1, s2, e1, e2 = map(float, rect2)
    _positive(distance=distance, width1=x2 - x1, depth1=y2 - y1, width2=s2 - s1, depth2=e2 - e1)
    z2 = distance * distance

    def G(x, y, eta, xi):
        u, v = x - xi, y - eta
        su, sv = math.sqrt(u * u + z2), math.sqrt(v * v + z2)
        return (v * su * math.atan(v / su) + u * sv * math.atan(u / sv)
                - 0.5 * z2 * math.log(u * u + v * v + z2)) / (2 * math.pi)

    total = 0.0
    for l, xi in enumerate((s1, s2), 1):
        for k, eta in enumerate((e1, e2), 1):
            for j, y in enumerate((y1, y2), 1):
                for i, x in enumerate((x1, x2), 1):
                    total += (-1) ** (i + j + k + l) * G(x, y, eta, xi)
    return total / ((x2 - x1) * (y2 - y1))


def perpendicular_rectangles(edge: float, width1: float, width2: float) -> float:
    """Two rectangles at 90 degrees sharing a common edge (catalogue C-14 [1]_).

    Surface 1 is ``edge`` x ``width1``, surface 2 is ``edge`` x ``width2``;
    with H = width2 / edge and W = width1 / edge:

        F = 1/(pi W) { W atan(1/W) + H atan(1/H) - sqrt(H^2+W^2) atan(1/sqrt(H^2+W^2))
              + 1/4 ln[ (1+W^2)(1+H^2)/(1+W^2+H^2)
                        * (W^2 (1+W^2+H^2) / ((1+W^2)(W^2+H^2)))^(W^2)
                        * (H^2 (1+H^2+W^2) / ((1+H^2)(H^2+W^2)))^(H^2) ] }

    Examples
    --------
    >>> round(perpendicular_rectangles(1.0, 1.0, 1.0), 6)
    0.200044
    """
    _positive(edge=edge, width1=width1, width2=width2)
    H, W = width2 / edge, width1 / edge
    h2, w2 = H * H, W * W
    r = math.sqrt(h2 + w2)
    log_term = (math.log((1 + w2) * (1 + h2) / (1 + w2 + h2))
                + w2 * math.log(w2 * (1 + w2 + h2) / ((1 + w2) * (w2 + h2)))
                + h2 * math.log(h2 * (1 + h2 + w2) / ((1 + h2) * (h2 + w2))))
    return (W * math.atan(1 / W) + H * math.atan(1 / H) - r * math.atan(1 / r) + 0.25 * log_term) / (math.pi * W)


def coaxial_disks(radius1: float, radius2: float, distance: float) -> float:
    """Disk 1 to a parallel coaxial disk 2 (catalogue C-41 [1]_).

    With R1 = radius1 / distance, R2 = radius2 / distance and
    X = 1 + (1 + R2^2) / R1^2:

        F = 1/2 (X - sqrt(X^2 - 4 (R2 / R1)^2))

    Examples
    --------
    >>> round(coaxial_disks(1.0, 1.0, 1.0), 6)
    0.381966
    """
    _positive(radius1=radius1, radius2=radius2, distance=distance)
    R1, R2 = radius1 / distance, radius2 / distance
    X = 1 + (1 + R2 * R2) / (R1 * R1)
    return 0.5 * (X - math.sqrt(X * X - 4 * (R2 / R1) ** 2))
