"""The daylight year's cost at many sensors (issue 44's timing goals), hfrad alone.

The example's office (examples/daylight/: 4.5 x 7 x 3 m, one south window,
the room of :func:`hfrad.daylight.sidelit_room`, 0.5 m patches), pvlib's
Greensboro TMY3, a work plane 0.8 m over the floor at ``--spacing`` (0.08 m:
5,016 sensors). Timed in order:

- the precompute: the factorization, then the sky patches' first hits and the
  one batched solve (:class:`DaylightModel`);
- the year at the sensors: gendaymtx's sky and sun matrices, the sensors'
  coefficients (first hits by rays, the gather operator), the direct sun by
  rays, the products, the metrics. Goal: <= 1 min on 2 cores;
- a design change: walls 0.5 -> 0.3 (``with_reflectance``, the sensors'
  coefficients ``relit``, the year again with the direct sun kept). Goal: <= 2 min.

Each step's wall and CPU seconds (``time.process_time``: all threads of the process) are
recorded: on a machine shared with other work the wall time is inflated, while an idle
2-core run needs between CPU / 2 and CPU seconds of wall time.

Usage::

    python benchmarks/bench_daylight.py [--spacing 0.08] [--name daylight-5000]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import check_load, machine, machine_line, print_table, write_json  # noqa: E402


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--spacing", type=float, default=0.08)
    p.add_argument("--eps", type=float, default=0.01)
    p.add_argument("--name", default="daylight-5000")
    args = p.parse_args()
    import pvlib

    import hfrad
    from hfrad.daylight import DaylightModel, daylight_metrics, read_weather, sidelit_room
    from hfrad.daylight.sky import sky_matrices
    from hfrad.lighting import floor_grid, gather_operator

    check_load()
    m = machine()
    print(machine_line(m))
    weather = read_weather(Path(pvlib.__file__).parent / "data" / "723170TYA.CSV")
    scene = sidelit_room(4.5, 7.0, 3.0, sill=0.9, head=2.6, margin=0.5, wall=0.5, floor=0.2, ceiling=0.8,
                         max_edge=0.5)
    hfrad.factorize(sidelit_room(max_edge=3.0), eps=args.eps)        # numba's compilation, not timed
    t, cpu = {}, {}

    def timed(key, fn):
        t0, c0 = time.perf_counter(), time.process_time()
        out = fn()
        t[key], cpu[key] = time.perf_counter() - t0, time.process_time() - c0
        print(f"  {key}: {t[key]:.1f} s (CPU {cpu[key]:.1f} s)", flush=True)
        return out

    fac = timed("factorize_s", lambda: hfrad.factorize(scene, eps=args.eps))
    model = timed("sky_patches_and_solve_s", lambda: DaylightModel(fac))
    sensors = floor_grid(scene, 0.8, args.spacing)
    print(f"{scene.n_patches} patches, {len(sensors)} sensors", flush=True)
    sky, sun = timed("sky_matrices_s", lambda: sky_matrices(weather, 1))
    gather = timed("gather_operator_s", lambda: gather_operator(scene, sensors.points, sensors.normals,
                                                                 caster=model.tracer.caster))
    dc = timed("sensor_coefficients_s", lambda: model.sensors(sensors, gather=gather))
    res = timed("year_s", lambda: model.year(sensors, weather, coefficients=dc, matrices=(sky, sun)))
    met = timed("metrics_s", lambda: daylight_metrics(res.illuminance, res.direct_sun, weather.hour))
    t.update({f"year_{k}": v for k, v in res.timings.items()})
    year_steps = ("sky_matrices_s", "gather_operator_s", "sensor_coefficients_s", "year_s", "metrics_s")
    design_steps = ("with_reflectance_s", "relit_s", "year_again_s", "metrics_again_s")
    t["year_total_s"] = sum(t[k] for k in year_steps)
    cpu["year_total_s"] = sum(cpu[k] for k in year_steps)
    rho = np.array(fac.reflectance)
    walls = np.asarray(scene.material) == scene.material_names.index("wall")
    rho[walls] *= 0.6
    model2 = timed("with_reflectance_s", lambda: model.with_reflectance(rho))
    dc2 = timed("relit_s", lambda: dc.relit(model2))
    res2 = timed("year_again_s", lambda: model2.year(sensors, weather, coefficients=dc2, matrices=(sky, sun),
                                                     direct_sun=res.direct_sun))
    met2 = timed("metrics_again_s", lambda: daylight_metrics(res2.illuminance, res2.direct_sun, weather.hour))
    t["design_change_total_s"] = sum(t[k] for k in design_steps)
    cpu["design_change_total_s"] = sum(cpu[k] for k in design_steps)
    rows = [{"step": k, "seconds": v, "CPU seconds": cpu.get(k)} for k, v in t.items()]
    print_table(f"daylight year, {len(sensors)} sensors, {scene.n_patches} patches (CPU: all threads of the process)",
                rows, ["step", "seconds", "CPU seconds"])
    summary = {"sensors": len(sensors), "patches": scene.n_patches, "rank": fac.rank,
               "sDA": met["sDA"], "ASE": met["ASE"], "mean_DA": float(met["DA"].mean()),
               "walls_0.3": {"sDA": met2["sDA"], "ASE": met2["ASE"], "mean_DA": float(met2["DA"].mean())}}
    print(summary)
    path = write_json(args.name, {"machine": m, "args": vars(args), "timings": t, "cpu_seconds": cpu,
                                      "summary": summary})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
