"""Per-grid illuminance statistics (EN 12464-1 terms), CSV / JSON tables and a false-colour plan.

For the m sensors of a grid: ``average`` (the arithmetic mean: grid cells are
equal), ``minimum``, ``maximum``, ``U0 = Emin / Eavg`` (EN 12464-1's
uniformity) and ``Ud = Emin / Emax``.
"""

from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path

import numpy as np

from ..atomic import atomic_path
from ..errors import InputError
from ..render.falsecolor import colorbar_width, falsecolor_image
from .sensors import SensorSet

__all__ = ["grid_stats", "write_csv", "write_json", "plan_image", "save_plan"]


def grid_stats(lux: np.ndarray) -> dict:
    """``{"average", "minimum", "maximum", "U0", "Ud", "sensors"}`` of (m,) illuminances (lux).

    U0 and Ud are None when the average (maximum) is 0.
    """
    E = np.asarray(lux, np.float64).reshape(-1)
    if not len(E):
        raise InputError("no sensors to summarise")
    avg, lo, hi = float(E.mean()), float(E.min()), float(E.max())
    return {"sensors": int(len(E)), "average": avg, "minimum": lo, "maximum": hi,
            "U0": lo / avg if avg > 0 else None, "Ud": lo / hi if hi > 0 else None}


def write_csv(path: "str | Path", sensors, lux, *, direct=None) -> Path:
    """One row per sensor: ``grid,x,y,z,nx,ny,nz,lux`` (and ``direct_lux``), atomically.

    ``sensors`` is a :class:`SensorSet` with its (m,) ``lux`` (and ``direct``),
    or lists of them (several grids in one table).
    """
    if isinstance(sensors, SensorSet):
        sensors, lux, direct = [sensors], [lux], None if direct is None else [direct]
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["grid", "x", "y", "z", "nx", "ny", "nz", "lux"] + (["direct_lux"] if direct is not None else []))
    for k, (s, E) in enumerate(zip(sensors, lux)):
        for i, (p, n) in enumerate(zip(s.points, s.normals)):
            row = [s.name, *(f"{v:.6g}" for v in p), *(f"{v:.6g}" for v in n), f"{E[i]:.6g}"]
            if direct is not None:
                row.append(f"{direct[k][i]:.6g}")
            w.writerow(row)
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_text(buf.getvalue(), encoding="utf-8")
    return path


def _clean(x):
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {k: _clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_clean(v) for v in x]
    return x


def write_json(path: "str | Path", report: dict) -> Path:
    """``report`` as indented JSON (non-finite numbers as null), atomically."""
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(_clean(report), indent=2, allow_nan=False) + "\n", encoding="utf-8")
    return path


def plan_image(sensors: SensorSet, lux: np.ndarray, *, pixels_per_cell: int | None = None, vmax: float | None = None,
               title: str | None = None, label: str | None = None, luminaires=(), scene=None) -> np.ndarray:
    """(h, w, 3) uint8: the grid seen from above in false colour (viridis), with a lux colour bar.

    x runs to the right, z downwards (a plan of a y-up scene seen from
    above), with metre ticks along the top and the left; the grid's extent is
    outlined in white, cells without a sensor are black. The statistics of
    :func:`grid_stats` are printed on top (or ``title``); ``label`` replaces
    "lux" on the colour bar for other quantities (daylight metrics in %).
    See :mod:`hfrad.lighting.plan` for what else is drawn.

    Parameters
    ----------
    luminaires : sequence of Luminaire, optional
        Drawn at their positions with their luminous openings' outlines and names.
    scene : Scene, optional
        Its upward faces near the work plane's height (desk tops) are outlined.

    Raises
    ------
    InputError
        The sensors are not a grid (a sensor file has no plan).
    """
    from PIL import Image, ImageDraw

    from ..render.falsecolor import _font
    from .plan import (BOTTOM, LEFT, TOP, PlanFrame, desk_outlines, draw_axes, draw_overlay, extent,
                       luminaire_outline, near)

    if not sensors.is_grid:
        raise InputError(f"sensors {sensors.name!r} are not a grid; a plan image needs a work-plane grid")
    nx, nz = sensors.shape
    ppc = pixels_per_cell or max(4, min(40, 480 // max(nx, nz)))
    x0, z0 = sensors.origin
    rect = (x0, z0, x0 + nx * sensors.spacing, z0 + nz * sensors.spacing)
    desks = [d for d in desk_outlines(scene, float(np.median(sensors.points[:, 1]))) if near(rect, d.reshape(-1, 2))]
    shown = [l for l in luminaires if near(rect, luminaire_outline(l))]
    box = extent(rect, shown, desks)
    m_px = sensors.spacing / ppc
    head = 36 + TOP
    frame = PlanFrame(box[0], box[1], m_px, LEFT, head)
    w = LEFT + int(math.ceil((box[2] - box[0]) / m_px)) + 1
    h = head + int(math.ceil((box[3] - box[1]) / m_px)) + 1 + BOTTOM
    values = np.zeros((h, w))
    valid = np.zeros((h, w), bool)
    c0, r0 = (int(round(v)) for v in frame.pixel(x0, z0))
    cells = np.zeros((nz, nx))
    inside = np.zeros((nz, nx), bool)
    cells[sensors.cells[:, 1], sensors.cells[:, 0]] = lux
    inside[sensors.cells[:, 1], sensors.cells[:, 0]] = True
    values[r0:r0 + nz * ppc, c0:c0 + nx * ppc] = np.repeat(np.repeat(cells, ppc, axis=0), ppc, axis=1)
    valid[r0:r0 + nz * ppc, c0:c0 + nx * ppc] = np.repeat(np.repeat(inside, ppc, axis=0), ppc, axis=1)
    img = falsecolor_image(values, valid, width=w + colorbar_width(max(w, 360)), unit="lux", vmax=vmax, label=label)
    st = grid_stats(lux)
    text = title or (f"{sensors.name}: avg {st['average']:.0f} lx, min {st['minimum']:.0f}, "
                     f"max {st['maximum']:.0f}, U0 {st['U0']:.2f}" if st["U0"] is not None else sensors.name)
    grid_text = (f"grid x {rect[0]:.2f}..{rect[2]:.2f} m, z {rect[1]:.2f}..{rect[3]:.2f} m, "
                 f"{sensors.spacing:g} m cells" + _luminaire_count(len(shown), len(luminaires)))
    pic = Image.fromarray(img)
    draw = ImageDraw.Draw(pic)
    draw.text((4, 3), text, fill=(255, 255, 255), font=_font(12))
    draw.text((4, 19), grid_text, fill=(200, 200, 200), font=_font(11))
    draw_axes(draw, frame, box, _font(10))
    draw_overlay(draw, frame, rect, shown, desks, _font(10))
    return np.asarray(pic)


def _luminaire_count(shown: int, total: int) -> str:
    if not total:
        return ""
    return f"; {total} luminaires" if shown == total else f"; {shown} of {total} luminaires (the rest farther off the grid)"


def save_plan(path: "str | Path", sensors: SensorSet, lux: np.ndarray, **options) -> Path:
    """Write :func:`plan_image` as a PNG, atomically."""
    from PIL import Image

    path = Path(path)
    if path.suffix.lower() != ".png":
        raise InputError(f"plan image must be a .png file, got '{path}'")
    img = plan_image(sensors, lux, **options)
    with atomic_path(path) as tmp:
        Image.fromarray(img).save(tmp, format="PNG")
    return path
