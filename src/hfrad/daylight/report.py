"""Files and pictures of a daylight year: hourly illuminance (HDF5, CSV), metrics (JSON, CSV), plans, carpet.

Every file is written atomically (:func:`hfrad.atomic.atomic_path`).
"""

from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path

import numpy as np

from ..atomic import atomic_path
from ..lighting import plan_image
from ..render.falsecolor import _font, falsecolor_image

__all__ = ["write_hourly", "write_metrics", "carpet_image", "save_png", "metric_plans"]


def write_hourly(path: "str | Path", result) -> Path:
    """The year's illuminance per sensor and hour: ``.h5`` (datasets ``illuminance``, ``direct_sun``
    (m, h) float32 lux, ``points``, ``normals`` (m, 3), ``month``, ``day``, ``hour`` (h,)) or ``.csv``
    (one row per hour: month, day, hour, then one column per sensor)."""
    path = Path(path)
    w = result.weather
    with atomic_path(path) as tmp:
        if path.suffix.lower() == ".h5":
            import h5py

            with h5py.File(tmp, "w") as f:
                f.create_dataset("illuminance", data=result.illuminance, compression="gzip")
                f.create_dataset("direct_sun", data=result.direct_sun, compression="gzip")
                for name, v in (("points", result.sensors.points), ("normals", result.sensors.normals),
                                ("month", w.month), ("day", w.day), ("hour", w.hour)):
                    f.create_dataset(name, data=v)
                f.attrs["unit"] = "lux"
                f.attrs["weather"] = str(w.path)
                f.attrs["hours"] = "middle of each record's hour, local standard time"
        else:
            buf = io.StringIO()
            wr = csv.writer(buf, lineterminator="\n")
            wr.writerow(["month", "day", "hour"] + [f"s{i}" for i in range(len(result.sensors))])
            for j in range(len(w)):
                wr.writerow([w.month[j], w.day[j], f"{w.hour[j]:g}"] + [f"{v:.1f}" for v in result.illuminance[:, j]])
            tmp.write_text(buf.getvalue(), encoding="utf-8")
    return path


def _clean(x):
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def write_metrics(folder: Path, result, metrics: dict, extra: dict) -> tuple[Path, Path]:
    """``metrics.json`` (grid summary) and ``sensors.csv`` (per sensor: position, DA, UDI, sun hours, mean)."""
    summary = {"sensors": len(result.sensors), "weather": str(result.weather.path), "place": result.weather.place,
               "sDA_percent": 100 * metrics["sDA"], "ASE_percent": 100 * metrics["ASE"],
               "DA_mean_percent": 100 * float(metrics["DA"].mean()),
               "UDI_mean_percent": {k: 100 * float(metrics[f"UDI_{k}"].mean()) for k in ("low", "useful", "high")},
               "mean_lux_occupied": float(metrics["mean_lux"].mean()),
               "occupied_hours": metrics["occupied_hours"], "settings": metrics["settings"], **extra}
    jpath = folder / "metrics.json"
    with atomic_path(jpath) as tmp:
        tmp.write_text(json.dumps(summary, indent=2, default=_clean) + "\n", encoding="utf-8")
    buf = io.StringIO()
    wr = csv.writer(buf, lineterminator="\n")
    keys = ("DA", "UDI_low", "UDI_useful", "UDI_high", "sun_hours", "mean_lux")
    wr.writerow(["x", "y", "z", *keys])
    for i, p in enumerate(result.sensors.points):
        wr.writerow([*(f"{v:.4g}" for v in p), *(f"{float(metrics[k][i]):.4g}" for k in keys)])
    cpath = folder / "sensors.csv"
    with atomic_path(cpath) as tmp:
        tmp.write_text(buf.getvalue(), encoding="utf-8")
    return jpath, cpath


def save_png(path: Path, image: np.ndarray) -> Path:
    from PIL import Image

    with atomic_path(path) as tmp:
        Image.fromarray(image).save(tmp, format="PNG")
    return path


def metric_plans(folder: Path, result, metrics: dict, *, scene=None) -> list[Path]:
    """False-colour plans (grids only): DA300, UDI useful, hours of direct sun, mean occupied illuminance.

    With ``scene``, desk tops near the work plane are outlined (:func:`hfrad.lighting.plan.desk_outlines`).
    """
    s = result.sensors
    if not s.is_grid:
        return []
    st = metrics["settings"]
    pct = dict(vmax=100.0, label="%")
    plans = [("plan_DA.png", 100 * metrics["DA"], f"DA{st['threshold_lux']:g}: % of occupied hours; "
              f"sDA {100 * metrics['sDA']:.0f}%", pct),
             ("plan_UDI.png", 100 * metrics["UDI_useful"], f"UDI {st['udi_lux'][0]:g}-{st['udi_lux'][1]:g} lx: "
              "% of occupied hours", pct),
             ("plan_sun_hours.png", metrics["sun_hours"].astype(float), f"occupied hours of direct sun > "
              f"{st['sun_threshold_lux']:g} lx; ASE {100 * metrics['ASE']:.0f}%", dict(label="h")),
             ("plan_mean_lux.png", metrics["mean_lux"], "mean occupied lux, scale tops at 3000", dict(vmax=3000.0))]     # the window's edge would flatten the room
    out = []
    for name, v, title, opts in plans:
        out.append(save_png(folder / name, plan_image(s, v, title=title, scene=scene, **opts)))
    return out


def carpet_image(illuminance: np.ndarray, day_of_year: np.ndarray, hour: np.ndarray, *, title: str,
                 vmax: float | None = None, px_day: int = 2, px_hour: int = 12) -> np.ndarray:
    """(h, w, 3) uint8: a 365 x 24 carpet (days to the right, hours of the day downward) of the grid mean.

    Parameters
    ----------
    illuminance : (m, h) lux; its mean over the sensors is drawn
    day_of_year : (h,) int 0..364; hour : (h,) float, mid-hour (local standard time)
    """
    from PIL import Image, ImageDraw

    grid = np.zeros((24, 365))
    grid[np.floor(hour).astype(int) % 24, day_of_year] = np.asarray(illuminance, np.float64).mean(axis=0)
    values = np.repeat(np.repeat(grid, px_hour, axis=0), px_day, axis=1)
    head, left = 30, 30
    h, w = values.shape
    values = np.pad(values, ((head, 16), (left, 0)))
    valid = np.zeros(values.shape, bool)
    valid[head:head + h, left:] = True
    img = falsecolor_image(values, valid, width=values.shape[1] + 80, unit="lux", vmax=vmax,
                           percentile=99.0)
    pic = Image.fromarray(img)
    draw = ImageDraw.Draw(pic)
    font = _font(11)
    draw.text((4, 4), title, fill=(255, 255, 255), font=_font(12))
    for hh in range(0, 25, 6):
        draw.text((2, head + hh * px_hour - 6), f"{hh:02d}", fill=(200, 200, 200), font=font)
    start = np.cumsum([0, 31, 28, 31, 30, 31, 30, 31, 31, 30, 31, 30])
    for m, d0 in enumerate(start):
        draw.text((left + d0 * px_day + 2, head + h + 2), "JFMAMJJASOND"[m], fill=(200, 200, 200), font=font)
    return np.asarray(pic)
