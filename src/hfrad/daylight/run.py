"""``daylight_year``: a factorized scene, a weather file and a sensor grid in, the year's files out."""

from __future__ import annotations

import time
from pathlib import Path

from ..errors import InputError
from ..progress import ProgressCallback
from .metrics import OCCUPANCY, daylight_metrics
from .model import DaylightModel
from .report import carpet_image, metric_plans, save_png, write_hourly, write_metrics
from .sky import sky_matrices
from .weather import read_weather

__all__ = ["daylight_year", "HOURLY_FORMATS"]

HOURLY_FORMATS = ("h5", "csv")


def daylight_year(fac, weather: "str | Path", sensors, output: "str | Path", *, mf: int = 1, north: float = 0.0,
                  ground: float = 0.2, angular: bool = True, hourly: str = "h5",
                  occupancy: tuple[float, float] = OCCUPANCY, udi: tuple[float, float] = (100.0, 2000.0),
                  progress: ProgressCallback = None, stages=None) -> dict:
    """Run a year of daylight at ``sensors`` and write its files into the folder ``output``.

    Parameters
    ----------
    fac : HFactorization with its scene (``hfrad.load``)
    weather : path of a TMY3 (.csv) or EPW (.epw) file
    sensors : SensorSet (a work-plane grid gets plans)
    output : folder, created if absent
    mf, north, ground, angular : see :class:`DaylightModel` and :func:`sky_matrices`
    hourly : {"h5", "csv"}: the format of the hourly illuminance file
    occupancy, udi : see :func:`daylight_metrics`
    progress : callable (done, total), optional; stages : callable(str), optional (names the stage begun)

    Returns
    -------
    dict: ``metrics`` (:func:`daylight_metrics`), ``result`` (:class:`AnnualResult`), ``files`` (paths),
    ``timings`` (seconds).

    Raises
    ------
    InputError, FileFormatError
        A bad option or weather file (checked before any ray is cast).
    """
    if hourly not in HOURLY_FORMATS:
        raise InputError(f"hourly format must be one of {', '.join(HOURLY_FORMATS)}, got {hourly!r}")
    out = Path(output)
    if out.exists() and not out.is_dir():
        raise InputError(f"output '{out}' exists and is not a folder")
    say = stages or (lambda s: None)
    w = read_weather(weather)
    t0 = time.perf_counter()
    say("sky")
    matrices = sky_matrices(w, mf, ground=ground)
    t1 = time.perf_counter()
    say("sky patches")
    model = DaylightModel(fac, mf=mf, north=north, angular=angular, progress=progress)
    say("sensors")
    dc = model.sensors(sensors, progress=progress)
    say("year")
    result = model.year(sensors, w, coefficients=dc, matrices=matrices, progress=progress)
    metrics = daylight_metrics(result.illuminance, result.direct_sun, w.hour, occupancy=occupancy, udi=udi)
    t2 = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    timings = {**model.timings, **result.timings, "sky_matrices_s": t1 - t0, "total_s": t2 - t0}
    files = [write_hourly(out / f"illuminance.{hourly}", result)]
    files += write_metrics(out, result, metrics, {"reinhart_mf": mf, "north_deg": north, "ground": ground,
                                                  "angular_glass": angular, "timings": timings})
    files += metric_plans(out, result, metrics, scene=fac.scene)
    files.append(save_png(out / "carpet.png", carpet_image(result.illuminance, w.day_of_year, w.hour,
                                                           title=f"{w.place}: grid mean illuminance, lux "
                                                                 "(days across, hours of the day down)")))
    return {"metrics": metrics, "result": result, "files": files, "timings": timings, "model": model}
