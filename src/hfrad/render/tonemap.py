"""From radiance to display pixels: exposure, clipping, sRGB encoding.

A display value is ``clip(L * 2**EV, 0, 1)`` per channel, then encoded with the
sRGB opto-electronic transfer function (IEC 61966-2-1) and quantised to 8 bits.
``L`` is radiance in W/(m^2 sr) (radiosity / pi), so EV = 0 maps a radiance of
1 W/(m^2 sr) to full white. NaN and negative radiances display as black.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError

#: Rec. 709 / sRGB luminance weights of linear R, G, B.
LUMINANCE_WEIGHTS = np.array([0.2126, 0.7152, 0.0722])

#: Auto-exposure: this percentile of luminance ...
AUTO_PERCENTILE = 99.0
#: ... is mapped to this linear display value (leaves a little headroom below white).
AUTO_TARGET = 0.8


def luminance(rgb: np.ndarray) -> np.ndarray:
    """(...,) float: Rec. 709 luminance of linear RGB values (...,  3)."""
    return np.asarray(rgb, dtype=np.float64) @ LUMINANCE_WEIGHTS


def auto_exposure(radiance: np.ndarray, mask: np.ndarray | None = None, *,
                  percentile: float = AUTO_PERCENTILE, target: float = AUTO_TARGET) -> float:
    """Exposure in EV that maps a high percentile of luminance to ``target``.

    Parameters
    ----------
    radiance : (..., 3) float
        Linear values (pixels or patches).
    mask : (...) bool, optional
        Values to measure, e.g. pixels that show a non-emitting patch, so a
        bright light does not make the rest of the picture dark. When the mask
        selects nothing usable, all finite positive values are used instead.
    percentile : float in (0, 100]
    target : float > 0

    Returns
    -------
    float
        EV such that ``percentile(Y) * 2**EV == target``; 0 when there is no
        positive finite luminance at all.

    Examples
    --------
    >>> ev = auto_exposure(np.full((4, 3), 2.0))
    >>> bool(np.isclose(2.0 * 2**ev, AUTO_TARGET))
    True
    """
    Y = luminance(radiance)
    usable = np.isfinite(Y) & (Y > 0)
    sel = usable & mask if mask is not None else usable
    if not sel.any():
        sel = usable
    if not sel.any():
        return 0.0
    level = float(np.percentile(Y[sel], percentile))
    return float(np.log2(target / level)) if level > 0 else 0.0


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """sRGB OETF: linear values in [0, 1] -> encoded values in [0, 1] (NaN -> 0)."""
    x = np.clip(np.nan_to_num(np.asarray(linear, dtype=np.float64), nan=0.0), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def srgb_decode(encoded: np.ndarray) -> np.ndarray:
    """Inverse of :func:`srgb_encode`: encoded [0, 1] -> linear [0, 1]."""
    x = np.clip(np.asarray(encoded, dtype=np.float64), 0.0, 1.0)
    return np.where(x <= 0.04045, x / 12.92, np.power((x + 0.055) / 1.055, 2.4))


def to_uint8(values: np.ndarray) -> np.ndarray:
    """Values in [0, 1] -> uint8 with rounding (NaN -> 0)."""
    x = np.clip(np.nan_to_num(np.asarray(values, dtype=np.float64), nan=0.0), 0.0, 1.0)
    return np.rint(x * 255.0).astype(np.uint8)


#: Largest exposure, EV, either way (2^1000 ~ 1e301; beyond, 2^EV overflows a float).
MAX_EXPOSURE = 1000.0


def tonemap(radiance: np.ndarray, *, exposure: float = 0.0, encoding: str = "srgb") -> np.ndarray:
    """Linear radiance -> 8-bit display values.

    Parameters
    ----------
    radiance : (..., 3) float, W/(m^2 sr)
    exposure : float, EV
        Scale by 2**exposure before clipping to [0, 1].
    encoding : {'srgb', 'linear'}
        'srgb' applies the sRGB OETF (for PNG and screens); 'linear' stores the
        clipped linear value (e.g. glTF vertex colours, linear by spec).

    Returns
    -------
    (..., 3) uint8
    """
    if encoding not in ("srgb", "linear"):
        raise InputError(f"encoding must be 'srgb' or 'linear', got {encoding!r}")
    x = expose(radiance, exposure=exposure)
    return to_uint8(srgb_encode(x) if encoding == "srgb" else x)


def expose(radiance: np.ndarray, *, exposure: float = 0.0) -> np.ndarray:
    """(..., 3) float in [0, 1]: linear display values ``clip(L * 2**EV, 0, 1)`` (NaN -> 0, +inf -> 1).

    Anti-aliased pictures average these over a pixel's samples before encoding,
    so a light's edge blends with what is beside it instead of staying white.
    """
    if not (np.isfinite(exposure) and abs(exposure) <= MAX_EXPOSURE):
        raise InputError(f"exposure must be a finite number of EV within +-{MAX_EXPOSURE:g} (a factor 2^EV), "
                         f"got {exposure}")
    x = np.asarray(radiance, dtype=np.float64) * (2.0 ** exposure)
    return np.clip(np.nan_to_num(x, nan=0.0, posinf=1.0, neginf=0.0), 0.0, 1.0)
