"""False-colour pictures of radiosity with a labelled colour bar.

The mapped quantity is the *luminance-weighted radiosity* of each pixel's
surface point (interpolated like the shaded picture):

- ``unit='W/m2'``: Y_B = 0.2126 B_r + 0.7152 B_g + 0.0722 B_b, in W/m^2
  (Rec. 709 weights; equals B for grey light).
- ``unit='lux'``: 683 lm/W x Y_B, in lm/m^2. This reads each RGB channel's
  watts as if they had the photopic efficacy of 555 nm light times the
  channel's luminance weight: an approximation (real efficacy depends on the
  spectra behind R, G and B; Radiance's 179 lm/W white efficacy is the same
  idea with an equal-energy white). It is the luminous *exitance* of the
  surface, lm/m^2, which has the dimension of lux; for a Lambertian reflector
  of reflectance rho under illuminance E_v it equals rho E_v (light that
  surfaces emit themselves is included).

The colour scale is linear from 0 to the brightest non-emitting pixel, rounded
up to a tick; brighter pixels (lights) take the top colour.
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import InputError
from .tonemap import LUMINANCE_WEIGHTS, to_uint8

#: lm/W: luminous efficacy at 555 nm, the peak of the photopic curve.
LUMINOUS_EFFICACY = 683.0

UNITS = {"W/m2": ("W/m^2", 1.0), "lux": ("lux", LUMINOUS_EFFICACY)}

# viridis, sampled (display-encoded sRGB values)
_VIRIDIS = np.array([
    [0.267004, 0.004874, 0.329415], [0.282623, 0.140926, 0.457517], [0.253935, 0.265254, 0.529983],
    [0.206756, 0.371758, 0.553117], [0.163625, 0.471133, 0.558148], [0.127568, 0.566949, 0.550556],
    [0.134692, 0.658636, 0.517649], [0.266941, 0.748751, 0.440573], [0.477504, 0.821444, 0.318195],
    [0.741388, 0.873449, 0.149561], [0.993248, 0.906157, 0.143936],
])


def check_unit(unit: str) -> str:
    """``unit`` if it is one of :data:`UNITS`, else InputError naming them."""
    if unit not in UNITS:
        raise InputError(f"unit must be one of {', '.join(UNITS)}, got {unit!r}")
    return unit


def photometric(radiosity: np.ndarray, unit: str = "W/m2") -> np.ndarray:
    """(...,) float: luminance-weighted radiosity (...,  3) in ``unit`` (see module docstring)."""
    return (np.asarray(radiosity, dtype=np.float64) @ LUMINANCE_WEIGHTS) * UNITS[check_unit(unit)][1]


def colormap(t: np.ndarray) -> np.ndarray:
    """(..., 3) float display colours of ``t`` in [0, 1] (clipped; NaN -> 0)."""
    t = np.clip(np.nan_to_num(np.asarray(t, dtype=np.float64), nan=0.0), 0.0, 1.0)
    x = t * (len(_VIRIDIS) - 1)
    i = np.minimum(x.astype(np.int64), len(_VIRIDIS) - 2)
    f = (x - i)[..., None]
    return (1 - f) * _VIRIDIS[i] + f * _VIRIDIS[i + 1]


def nice_scale(vmax: float, ticks: int = 5) -> tuple[float, float]:
    """(top, step): a round tick step and the smallest multiple of it >= vmax."""
    if not (np.isfinite(vmax) and vmax > 0):
        return 1.0, 0.2
    raw = vmax / ticks
    mag = 10.0 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1, 2, 2.5, 5, 10) if m * mag >= raw * (1 - 1e-9))
    return step * math.ceil(vmax / step - 1e-9), step


def colorbar_width(width: int) -> int:
    """Pixels taken from the right of an image of ``width`` for the colour bar."""
    return int(min(max(72, width // 6), width // 2))


def _font(size: int):
    from PIL import ImageFont
    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # Pillow < 10.1: fixed bitmap font
        return ImageFont.load_default()


def _label(v: float) -> str:
    """A tick's label, short enough for the bar: "2500", "15k", "2.5M" (not "1.5e+04", which the
    bar's narrowest width cuts off)."""
    if abs(v) < 1e4:
        return f"{v:.4g}"
    if abs(v) < 1e6:
        return f"{v / 1e3:.3g}k"
    return f"{v / 1e6:.3g}M"


def falsecolor_image(values: np.ndarray, valid: np.ndarray, *, width: int, unit: str = "W/m2",
                     vmax: float | None = None, scale_mask: np.ndarray | None = None,
                     percentile: float = 100.0, label: str | None = None) -> np.ndarray:
    """A false-colour picture with a colour bar on its right.

    Parameters
    ----------
    values : (h, w) float, in ``unit``
        Per-pixel quantity (see :func:`photometric`); ``w`` is ``width`` minus
        :func:`colorbar_width`.
    valid : (h, w) bool
        Pixels that show a surface; the rest are black.
    width : int
        Width of the returned picture, colour bar included.
    unit : {'W/m2', 'lux'}
        Printed on the bar.
    vmax : float, optional
        Top of the scale; default: ``percentile`` of the pixels in
        ``scale_mask`` (else all valid pixels), rounded up to a tick.
    label : str, optional
        Printed on the bar instead of the unit's name (a quantity that is not a light level, e.g. "%").

    Returns
    -------
    (h, width, 3) uint8
    """
    from PIL import Image, ImageDraw

    label = label or UNITS[check_unit(unit)][0]
    values = np.asarray(values, dtype=np.float64)
    h, w = values.shape
    bar_w = width - w
    finite = valid & np.isfinite(values)
    if vmax is None:
        sel = finite & scale_mask if scale_mask is not None else finite
        if not sel.any():
            sel = finite
        vmax = float(np.percentile(values[sel], percentile)) if sel.any() else 1.0
    top, step = nice_scale(vmax)
    out = np.zeros((h, width, 3), np.uint8)
    out[:, :w] = np.where(finite[..., None], to_uint8(colormap(values / top)), 0)
    out[:, w:] = 32  # dark grey panel

    font_px = max(8, min(14, h // 30))
    font = _font(font_px)
    margin_top, margin_bottom = 2 * font_px + 6, font_px + 4
    y0, y1 = margin_top, max(margin_top + 2, h - margin_bottom)
    x0 = w + max(4, bar_w // 10)
    x1 = x0 + max(6, bar_w // 5)
    ys = np.arange(y0, y1)
    ramp = to_uint8(colormap(1.0 - (ys - y0) / max(1, y1 - 1 - y0)))  # top of the bar = top of the scale
    out[y0:y1, x0:x1] = ramp[:, None, :]
    img = Image.fromarray(out)
    draw = ImageDraw.Draw(img)
    draw.rectangle([x0 - 1, y0 - 1, x1, y1], outline=(200, 200, 200))
    draw.text((w + 3, 2), label, fill=(255, 255, 255), font=font)
    for k in range(int(round(top / step)) + 1):
        v = k * step
        y = y1 - 1 - (v / top) * (y1 - 1 - y0)
        draw.line([x1, y, x1 + 3, y], fill=(220, 220, 220))
        draw.text((x1 + 5, y - font_px / 2), _label(v), fill=(230, 230, 230), font=font)
    return np.asarray(img, dtype=np.uint8)
