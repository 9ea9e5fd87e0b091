"""``hfrad lux FILE.hfr --layout LAYOUT.json -o LUX.json``: illuminance of catalogue luminaires on grids and sensors."""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

from ..errors import InputError
from . import common


def register(app: typer.Typer) -> None:
    @app.command()
    def lux(
        factorization: Path = typer.Argument(..., help="Factorization file from `hfrad precompute` (.hfr)."),
        layout: Optional[Path] = typer.Option(None, "--layout", help="Luminaire layout (.json or .toml): "
                                              "photometric files (IES, EULUMDAT), positions, aims, dimming."),
        output: Path = typer.Option(..., "-o", "--output", help="Result to write (.json): per-grid average, "
                                    "minimum, maximum, U0."),
        floor: Optional[str] = typer.Option(None, "--floor", help="Lay a work-plane grid over the outline of "
                                            "this material (default: 'floor' when the scene has it and no "
                                            "--sensors are given)."),
        spaces: Optional[Path] = typer.Option(None, "--spaces", help="Lay one work-plane grid per IfcSpace of "
                                              "this IFC file (default: the scene's own IFC file, when it was "
                                              "read from one and no --floor or --sensors are given)."),
        height: float = typer.Option(0.8, "--height", help="Work-plane height above the floor, m."),
        spacing: float = typer.Option(0.25, "--spacing", help="Grid spacing, m."),
        margin: float = typer.Option(0.0, "--margin", help="Border left out of the grid, m (EN 12464-1: 0.5)."),
        sensors: List[Path] = typer.Option([], "--sensors", help="Sensor file(s), one 'x y z nx ny nz' a line "
                                           "(as rtrace -I reads); repeatable."),
        background: str = typer.Option("none", "--background", help="none: only the luminaires light the "
                                       "scene; scene: the scene's own emitting patches too."),
        csv_out: Optional[Path] = typer.Option(None, "--csv", help="Also write every sensor's lux (.csv)."),
        plan: Optional[Path] = typer.Option(None, "--plan", help="Also draw the grid in false colour (.png), with metre "
                                                                 "ticks, the luminaires and the desk tops."),
        quiet: bool = common.QuietOption,
    ) -> None:
        """Illuminance (lux) on work planes and at sensors: direct light of each luminaire by ray casting,
        interreflections by one batched solve of all luminaires, gathered at the sensors.

        Exit codes: 0 done, 2 bad input (the message names the file or field).
        See docs/lighting.md.
        """
        import time

        from ..atomic import atomic_paths, check_outputs
        from ..lighting import (LightingModel, floor_grid, grid_stats, read_layout, read_sensors, save_plan,
                                write_csv, write_json)
        from ..lighting.limits import check_lighting_size
        from ..lighting.spaces import scene_ifc, space_grids
        from ..solve.bounds import solution_line

        with common.user_errors():
            if output.suffix.lower() != ".json":
                raise InputError(f"output must be a .json file, got '{output}'")
            if plan is not None and plan.suffix.lower() != ".png":
                raise InputError(f"--plan must be a .png file, got '{plan}'")
            if csv_out is not None and csv_out.suffix.lower() != ".csv":
                raise InputError(f"--csv must be a .csv file, got '{csv_out}'")
            check_outputs({"-o/--output": output, "--csv": csv_out, "--plan": plan},
                          {"factorization": factorization, "--layout": layout, "--spaces": spaces,
                           **{f"--sensors {p}": p for p in sensors}})
            for path in (output, csv_out, plan):
                common.check_output(path)   # a missing or read-only folder: refused before the work
            luminaires = read_layout(layout) if layout is not None else []
            fac = common.load_factorization(factorization)
            scene = fac.scene
            sets = [read_sensors(p) for p in sensors]
            if spaces is None and floor is None and not sets:
                spaces = scene_ifc(scene, strict=True)
            if spaces is not None:
                sets[0:0] = space_grids(spaces, height=height, spacing=spacing, margin=margin, scene=scene)
            elif floor is None and not sets:
                if "floor" not in scene.material_names:
                    raise InputError("give --floor MATERIAL or --sensors FILE: the scene has no 'floor' material")
                floor = "floor"
            if floor is not None:
                sets.insert(0, floor_grid(scene, height, spacing, material=floor, name="workplane", margin=margin))
            if plan is not None and not any(s.is_grid for s in sets):
                raise InputError("--plan needs a work-plane grid (--floor or --spaces)")
            check_lighting_size(scene.n_patches, len(luminaires), [len(s) for s in sets])
            t0 = time.perf_counter()
            with common.progress_bar("luminaires", quiet) as bar:
                model = LightingModel(fac, luminaires, background=background, progress=bar)
            responses = [model.sensors(s) for s in sets]
            pre = time.perf_counter() - t0
            w = model.dimming
            t1 = time.perf_counter()
            values = [r.illuminance(w) for r in responses]
            relight = time.perf_counter() - t1
            radiosity_error = model.radiosity_error(w)                   # once for every grid
            errors = [model.illuminance_error(r, radiosity_error) for r in responses]   # lux figure per sensor
            report = {"factorization": str(factorization), "layout": None if layout is None else str(layout),
                      "background": background,
                      "luminaires": [{"name": l.name, "catalogue": l.photometry.name, "dimming": l.dimming,
                                      "position": l.position.tolist(), "aim": l.aim.tolist()} for l in luminaires],
                      "grids": [{"name": s.name, "spacing_m": s.spacing, **grid_stats(v),
                                 "error_lux": {"maximum": float(e.max()), "average": float(e.mean())}}
                                for s, v, e in zip(sets, values, errors)],
                      "radiosity_error": radiosity_error.as_dict(),
                      "timings": {**model.timings, "precompute_s": pre, "relight_s": relight}}
            outs = [p for p in (output, csv_out, plan) if p is not None]
            with atomic_paths(*outs) as tmps:        # all written, or none
                tmp = dict(zip(outs, tmps))
                write_json(tmp[output], report)
                if csv_out is not None:
                    write_csv(tmp[csv_out], sets, values, direct=[r.direct @ w for r in responses])
                if plan is not None:
                    save_plan(tmp[plan], *[(s, v) for s, v in zip(sets, values) if s.is_grid][0],
                              luminaires=luminaires, scene=scene)
        common.console.print(f"  {solution_line(radiosity_error)}", highlight=False)
        for s, v, e in zip(sets, values, errors):
            st = grid_stats(v)
            u0 = "-" if st["U0"] is None else f"{st['U0']:.3f}"
            common.console.print(f"  {s.name} ({st['sensors']} sensors): average {st['average']:.1f} lx, "
                                 f"min {st['minimum']:.1f}, max {st['maximum']:.1f}, U0 {u0}; "
                                 f"interreflected light's error at most {e.max():.2g} lx (average {e.mean():.2g})",
                                 highlight=False)
        extra = "".join(f" and {p}" for p in (csv_out, plan) if p is not None)
        common.console.print(f"wrote {output}{extra}: precompute {pre:.2f} s, relighting {relight * 1e3:.2f} ms",
                             highlight=False)
