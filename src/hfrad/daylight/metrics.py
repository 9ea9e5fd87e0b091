"""Climate-based daylight metrics over the occupied hours (IES LM-83-12).

Occupied hours are 8:00 to 18:00 local standard time every day of the year
(LM-83: 3,650 hours): the records whose middle lies in [8, 18).

- **DA300** (daylight autonomy): per sensor, the fraction of occupied hours with at least 300 lux.
- **sDA300/50%** (spatial daylight autonomy): the share of sensors with DA300 >= 50%.
- **ASE1000,250h** (annual sunlight exposure): the share of sensors that receive more than 1000 lux
  of *direct sun alone* (no sky, no interreflections) for more than 250 occupied hours.
- **UDI** (useful daylight illuminance): per sensor, the fractions of occupied hours below 100 lux
  (too dark), from 100 to ``upper`` lux (useful; 2000 by default, some use 3000) and above (too bright).
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError

__all__ = ["occupied_hours", "daylight_metrics", "OCCUPANCY"]

#: LM-83's occupied hours, local standard time
OCCUPANCY = (8.0, 18.0)


def occupied_hours(hour: np.ndarray, occupancy: tuple[float, float] = OCCUPANCY) -> np.ndarray:
    """(h,) bool: records whose mid-hour lies in ``[start, end)``."""
    a, b = occupancy
    if not (0 <= a < b <= 24):
        raise InputError(f"occupancy must be two hours 0 <= start < end <= 24, got {occupancy}")
    hour = np.asarray(hour, float)
    return (hour >= a) & (hour < b)


def daylight_metrics(illuminance: np.ndarray, direct_sun: np.ndarray, hour: np.ndarray, *,
                     occupancy: tuple[float, float] = OCCUPANCY, threshold: float = 300.0,
                     autonomy: float = 0.5, sun_threshold: float = 1000.0, sun_hours: float = 250.0,
                     udi: tuple[float, float] = (100.0, 2000.0)) -> dict:
    """The metrics of the module docstring for m sensors over h hours.

    Parameters
    ----------
    illuminance, direct_sun : (m, h) float, lux
    hour : (h,) float, mid-hour in local standard time

    Returns
    -------
    dict with per-sensor arrays (m,) ``DA`` (fraction), ``sun_hours`` (occupied hours of direct
    sun above ``sun_threshold``), ``UDI_low``, ``UDI_useful``, ``UDI_high`` (fractions),
    ``mean_lux`` (over occupied hours), and the scalars ``sDA`` and ``ASE`` (fractions of
    sensors) and ``occupied_hours``.
    """
    lo, hi = udi
    if not (0 < lo < hi):
        raise InputError(f"UDI bounds must be 0 < low < high lux, got {udi}")
    occ = occupied_hours(hour, occupancy)
    if not occ.any():
        raise InputError(f"no occupied hour in {occupancy}")
    E = np.asarray(illuminance)[:, occ]
    S = np.asarray(direct_sun)[:, occ]
    da = (E >= threshold).mean(axis=1)
    sun = (S > sun_threshold).sum(axis=1)
    return {"DA": da, "sun_hours": sun, "UDI_low": (E < lo).mean(axis=1),
            "UDI_useful": ((E >= lo) & (E <= hi)).mean(axis=1), "UDI_high": (E > hi).mean(axis=1),
            "mean_lux": E.mean(axis=1), "sDA": float((da >= autonomy).mean()), "ASE": float((sun > sun_hours).mean()),
            "occupied_hours": int(occ.sum()),
            "settings": {"occupancy": list(occupancy), "threshold_lux": threshold, "autonomy": autonomy,
                         "sun_threshold_lux": sun_threshold, "sun_hours": sun_hours, "udi_lux": list(udi)}}
