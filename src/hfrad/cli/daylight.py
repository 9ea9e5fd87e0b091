"""``hfrad daylight FILE.hfr --weather FILE -o DIR``: a year of sky and sun through the windows, LM-83 metrics."""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

from ..errors import InputError
from . import common


def register(app: typer.Typer) -> None:
    @app.command()
    def daylight(
        factorization: Path = typer.Argument(..., help="Factorization file from `hfrad precompute` (.hfr) of a "
                                             "scene with glazing (materials with a transmittance)."),
        weather: Path = typer.Option(..., "--weather", help="Weather file: TMY3 (.csv) or EPW (.epw)."),
        output: Path = typer.Option(..., "-o", "--output", help="Folder for the results: illuminance.h5, "
                                    "metrics.json, sensors.csv, plan_*.png, carpet.png."),
        floor: Optional[str] = typer.Option(None, "--floor", help="Lay a work-plane grid over the outline of "
                                            "this material (default 'floor' when no --sensors are given)."),
        height: float = typer.Option(0.8, "--height", help="Work-plane height above the floor, m."),
        spacing: float = typer.Option(0.5, "--spacing", help="Grid spacing, m."),
        margin: float = typer.Option(0.0, "--margin", help="Border left out of the grid, m."),
        sensors: List[Path] = typer.Option([], "--sensors", help="Sensor file (one 'x y z nx ny nz' a line) "
                                           "instead of a grid."),
        north: float = typer.Option(0.0, "--north", help="Degrees from -z toward +x (clockwise in plan) "
                                    "where north lies."),
        mf: int = typer.Option(1, "--mf", help="Reinhart sky subdivision: 1 (146 patches), 2, 4."),
        ground: float = typer.Option(0.2, "--ground", help="Ground reflectance outside."),
        udi_upper: float = typer.Option(2000.0, "--udi-upper", help="Top of useful daylight, lux (2000 or 3000)."),
        hourly: str = typer.Option("h5", "--hourly", help="Hourly illuminance file: h5 or csv."),
        angular: bool = typer.Option(True, "--angular/--no-angular", help="Angle dependence of clear glass."),
        quiet: bool = common.QuietOption,
    ) -> None:
        """Climate-based daylight: sDA300/50%, ASE1000,250h, UDI, DA over LM-83's occupied hours (8-18 h).

        The sky (Perez, Radiance's gendaymtx) and the sun enter through glazing; one batched solve gives the
        interreflections of all sky patches. Exit codes: 0 done, 2 bad input. See docs/daylight.md.
        """
        from ..daylight import daylight_year, read_weather
        from ..lighting import floor_grid, read_sensors

        with common.user_errors():
            if output.exists() and not output.is_dir():
                raise InputError(f"-o/--output '{output}' exists and is not a folder")
            if hourly not in ("h5", "csv"):
                raise InputError(f"--hourly must be h5 or csv, got {hourly!r}")
            if mf not in (1, 2, 4):
                raise InputError(f"--mf must be 1, 2 or 4, got {mf}")
            if not (udi_upper > 100):
                raise InputError(f"--udi-upper must be above 100 lux, got {udi_upper:g}")
            read_weather(weather)                      # a bad weather file is named before the .hfr is read
            fac = common.load_factorization(factorization)
            scene = fac.scene
            if floor is not None and sensors:
                raise InputError("give --floor or --sensors, not both")
            if len(sensors) > 1:
                raise InputError("give one --sensors file")
            if sensors:
                grid = read_sensors(sensors[0])
            else:
                if floor is None and "floor" not in scene.material_names:
                    raise InputError("give --floor MATERIAL or --sensors FILE: the scene has no 'floor' material")
                grid = floor_grid(scene, height, spacing, material=floor or "floor", name="workplane",
                                  margin=margin)
            if not any(m.is_glazing for m in scene.materials):
                common.console.print("note: the scene has no glazing; daylight enters only through openings",
                                     highlight=False)
            with common.progress_bar("daylight", quiet) as bar:
                stage = (lambda s: bar.note(s)) if bar is not None else None
                run = daylight_year(fac, weather, grid, output, mf=mf, north=north, ground=ground,
                                    angular=angular, hourly=hourly, udi=(100.0, udi_upper),
                                    progress=bar, stages=stage)
        m = run["metrics"]
        common.console.print(f"  {len(grid)} sensors, {m['occupied_hours']} occupied hours: sDA300/50% "
                             f"{100 * m['sDA']:.1f}%, ASE1000,250h {100 * m['ASE']:.1f}%, mean DA300 "
                             f"{100 * m['DA'].mean():.1f}%, UDI 100-{udi_upper:g} {100 * m['UDI_useful'].mean():.1f}%",
                             highlight=False)
        t = run["timings"]
        common.console.print(f"wrote {len(run['files'])} files to {output}: total {t['total_s']:.1f} s (year's "
                             f"products {t['products_s']:.2f} s)", highlight=False)
