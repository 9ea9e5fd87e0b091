"""Sizes of a lighting run, checked against memory before any work.

The stored state of :class:`hfrad.lighting.LightingModel` with ``L``
luminaires on ``n`` patches and ``m`` sensors is, in bytes::

    patches:  n L (8 direct + 24 + 24 first-bounce exitance and radiosity, three channels) x 2 (the solve's copies)
    sensors:  m n 4 (the float32 gather operator G) + m L 24 (direct, response, indirect) + m 200 (points, rays)

and an area-source luminaire spreads over ``(size / spacing)^2`` points. The
gather operator casts up to ``m n s^2`` rays (``s = 2``), so its work is
bounded too: at most :data:`MAX_GATHER_RAYS` (minutes on a few cores; a
million sensors on a 722-patch office would cast 2.9e9 and run for a quarter
of an hour). The checks raise :class:`~hfrad.errors.MemoryLimitError` or
:class:`~hfrad.errors.InputError` with the numbers, as the precompute's do.
"""

from __future__ import annotations

import math

from ..errors import InputError
from ..memory import require

__all__ = ["check_lighting_size", "check_grid_size", "check_area_points", "MAX_AREA_POINTS", "MAX_GATHER_RAYS"]

#: most rays one gather operator may cast (m sensors x n patches x 4)
MAX_GATHER_RAYS = 1e9
#: most points one luminous opening may be spread over (a 3 m x 3 m opening at 0.1 m: 900)
MAX_AREA_POINTS = 100_000
_PATCH_BYTES = 2 * (8 + 24 + 24)
_SENSOR_BYTES = 200


def check_lighting_size(n_patches: int, n_luminaires: int, sensors: "list[int]") -> None:
    """MemoryLimitError unless the model's arrays for these counts fit in memory (module docstring)."""
    m = int(sum(sensors))
    nbytes = (n_patches * n_luminaires * _PATCH_BYTES + m * n_patches * 4 + m * n_luminaires * 24
              + m * _SENSOR_BYTES)
    fix = "use fewer sensors (a larger grid spacing), fewer luminaires or a coarser factorization"
    require(nbytes, f"lighting {n_patches:,} patches with {n_luminaires:,} luminaires and {m:,} sensors", fix)
    rays = 4.0 * m * n_patches
    if rays > MAX_GATHER_RAYS:
        raise InputError(f"{m:,} sensors on {n_patches:,} patches: their gather operator would cast up to "
                         f"{rays:.2g} rays, more than the {MAX_GATHER_RAYS:.0e} allowed; {fix}")


def check_grid_size(count: float, spacing: float) -> None:
    """MemoryLimitError before a grid of ``count`` points (spacing m) is laid, if its points cannot fit."""
    require(float(count) * _SENSOR_BYTES, f"a sensor grid of {count:,.0f} points (spacing {spacing:g} m)",
            "use a larger grid spacing")


def check_area_points(name: str, length: float, width: float, spacing: float) -> None:
    """InputError if an opening ``length x width`` (m) needs more than :data:`MAX_AREA_POINTS` points."""
    count = math.ceil(max(abs(length), 1e-300) / spacing) * math.ceil(max(abs(width), 1e-300) / spacing)
    if count > MAX_AREA_POINTS:
        raise InputError(f"luminaire {name!r}: its luminous opening {abs(length):g} m x {abs(width):g} m "
                         f"needs {count:,} area-source points at {spacing:g} m; at most {MAX_AREA_POINTS:,} "
                         "(is the opening given in the right units?)")
