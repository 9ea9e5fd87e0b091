"""``hfrad design SPEC.json FILE.hfr -o RESULT.json``: emitter intensities that meet lighting goals."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from ..errors import InputError
from . import common

#: exit code when the spec is valid but no design meets it (the result JSON says why)
EXIT_INFEASIBLE = 1


def register(app: typer.Typer) -> None:
    @app.command()
    def design(
        spec: Path = typer.Argument(..., help="Design spec (.json or .toml): emitters, targets, objective."),
        factorization: Path = typer.Argument(..., help="Factorization file from `hfrad precompute` (.hfr)."),
        output: Path = typer.Option(..., "-o", "--output", help="Result to write (.json)."),
        render: Optional[Path] = typer.Option(None, "--render", help="Also draw the designed lighting (.png)."),
        emission_out: Optional[Path] = typer.Option(
            None, "--emission-out", help="Also write the designed emission as an emission file (.json) for "
                                         "`hfrad render/solve --emission-file` and `hfrad view`."),
        camera: str = typer.Option("auto", "--camera", help="Camera of --render: auto, front or "
                                                            "x,y,z:tx,ty,tz[:fov_degrees]."),
        falsecolor: bool = typer.Option(False, "--falsecolor", help="--render in false colour with a colour bar."),
        unit: str = typer.Option("lux", "--unit", help="False-colour unit of --render: W/m2 or lux."),
        show: str = typer.Option("radiosity", "--show", help="What --render draws: radiosity (what the eye "
                                 "sees), or irradiance (light arriving; with --falsecolor --unit lux: illuminance)."),
        width: int = typer.Option(640, "--width", min=1, help="--render width, pixels (at most 16,384)."),
        height: int = typer.Option(480, "--height", min=1, help="--render height, pixels (at most 16,384)."),
        method: str = typer.Option("auto", "--method", help="auto (fewer solves), forward (one solve per "
                                   "emitter) or adjoint (one transposed solve per target row the goals need)."),
        plan: Optional[Path] = typer.Option(None, "--plan", help="Luminaire specs: also draw the first grid's "
                                            "designed illuminance in false colour (.png)."),
        quiet: bool = common.QuietOption,
    ) -> None:
        """Find the least-power (or best-fitting) emitter intensities that meet the spec's goals.

        One batched solve gives every target's response to every emitter
        (O(m n k) for m emitters; or one transposed solve per goal row, when
        fewer), then SciPy solves an LP (HiGHS) or a bounded least-squares
        problem; the answer is checked with an independent solve. Spec format:
        docs/design.md. A spec with "luminaires" (a layout of catalogue
        luminaires) and "grids" (work planes with lux goals) designs their
        dimming instead: docs/lighting.md.
        Exit codes: 0 designed, 1 no design meets the spec (RESULT.json names the
        conflicting goals), 2 bad input (the message names the file or field).
        """
        import numpy as np

        from ..inverse import design as run_design
        from ..inverse import parse_spec
        from ..atomic import atomic_paths, check_outputs

        with common.user_errors():
            common.check_choice(method, "--method", ("auto", "forward", "adjoint"))
            if output.suffix.lower() != ".json":
                raise InputError(f"output must be a .json file, got '{output}'")
            for path in (output, emission_out, render, plan):
                common.check_output(path)   # a missing or read-only folder: refused before the solves
            from ..inverse.luminaires import spec_input_files
            from ..inverse.spec import read_spec
            raw = read_spec(spec)
            check_outputs({"-o/--output": output, "--emission-out": emission_out, "--render": render, "--plan": plan},
                          {"SPEC": spec, "FACTORIZATION": factorization, **spec_input_files(raw, spec.parent)})
            if emission_out is not None and emission_out.suffix.lower() != ".json":
                raise InputError(f"--emission-out must be a .json file, got '{emission_out}'")
            if render is not None:
                from ..render import Camera
                if render.suffix.lower() != ".png":
                    raise InputError(f"--render must be a .png file, got '{render}'")
                if falsecolor:
                    from ..render.falsecolor import check_unit
                    check_unit(unit)
                if show not in ("radiosity", "irradiance"):
                    raise InputError(f"--show must be radiosity or irradiance, got {show!r}")
                Camera.parse(camera, np.array([[0.0, 0, 0], [1, 1, 1]]))  # fail on a bad camera before solving
                from ..render.image import check_size
                check_size(width, height, falsecolor=falsecolor)          # and on a picture too large
            if plan is not None and plan.suffix.lower() != ".png":
                raise InputError(f"--plan must be a .png file, got '{plan}'")
            fac = common.load_factorization(factorization)
            from ..inverse.luminaires import is_lighting_spec
            if is_lighting_spec(raw):
                if emission_out is not None or (render is not None and show != "radiosity"):
                    raise InputError("a luminaire spec takes --plan and --render (radiosity); --emission-out "
                                     "and --show irradiance are for patch emitters")
                result = _design_luminaires(spec, fac, output, plan, render, camera, falsecolor, unit, width,
                                            height, quiet)
                _lighting_summary(result.report, output, plan)
                if not result.feasible:
                    raise typer.Exit(EXIT_INFEASIBLE)
                return
            parsed = parse_spec(spec, fac.scene)
            if emission_out is not None:
                from ..inverse.emission import check_nameable
                check_nameable(parsed)
            with common.progress_bar("design", quiet) as bar:
                result = run_design(fac, parsed, method=method, progress=bar)
            image = None
            if render is not None and result.radiosity is not None:
                from ..inverse.transfer import irradiance_field
                from ..render import render_image, save_png
                drawn = result.radiosity if show == "radiosity" else \
                    irradiance_field(fac, result.radiosity, result.exitance)
                image = render_image(fac.scene.replace(emission=result.exitance), drawn,
                                     camera=camera, width=width, height=height, falsecolor=falsecolor, unit=unit)
            emission = emission_out if emission_out is not None and result.feasible else None
            outs = [p for p in (output, emission, render if image is not None else None) if p is not None]
            with atomic_paths(*outs) as tmps:         # all written, or none
                tmp = dict(zip(outs, tmps))
                tmp[output].write_text(result.to_json() + "\n", encoding="utf-8")
                if emission is not None:
                    from ..inverse.emission import emission_settings
                    from ..io.emission import write_emission
                    write_emission(tmp[emission], emission_settings(result, fac.scene))
                if image is not None:
                    save_png(image, tmp[render])
        _summary(result.report, output, render)
        if not result.feasible:
            raise typer.Exit(EXIT_INFEASIBLE)


def _design_luminaires(spec: Path, fac, output: Path, plan, render, camera, falsecolor, unit, width, height,
                       quiet: bool):
    """The luminaire design of a spec with "luminaires" (inside user_errors)."""
    from ..atomic import atomic_paths
    from ..inverse.luminaires import design_lighting, parse_lighting_spec

    parsed = parse_lighting_spec(spec, fac.scene)
    if plan is not None and not any(g.sensors.is_grid for g in parsed.grids):
        raise InputError("--plan needs a grid (floor or rectangle) in the spec")
    with common.progress_bar("luminaires", quiet) as bar:
        result = design_lighting(fac, parsed, progress=bar)
    image = None
    if result.feasible and render is not None:
        from ..render import render_image, save_png
        image = render_image(fac.scene, result.model.radiosity(result.dimming), camera=camera, width=width,
                             height=height, falsecolor=falsecolor, unit=unit)
    drawn = result.feasible and plan is not None
    outs = [p for p in (output, plan if drawn else None, render if image is not None else None) if p is not None]
    with atomic_paths(*outs) as tmps:                 # all written, or none
        tmp = dict(zip(outs, tmps))
        tmp[output].write_text(result.to_json() + "\n", encoding="utf-8")
        if drawn:
            from ..lighting import save_plan
            dimmed = [l.replace(dimming=max(float(d), 0.0)) for l, d in zip(parsed.luminaires, result.dimming)]
            save_plan(tmp[plan], *[(g.sensors, lux) for g, lux in zip(parsed.grids, result.illuminance())
                                   if g.sensors.is_grid][0], scene=fac.scene, luminaires=dimmed)
        if image is not None:
            save_png(image, tmp[render])
    return result


def _lighting_summary(r: dict, output: Path, plan: Optional[Path]) -> None:
    say = common.console.print
    if r["total_power_W"] is not None:
        for e in r["luminaires"][:12]:
            say(f"  {e['name']} ({e['catalogue']}): dimming {e['dimming']:.3f}, {e['power_W']:.3g} W",
                highlight=False)
        if len(r["luminaires"]) > 12:
            say(f"  ... {len(r['luminaires']) - 12} more luminaires", highlight=False)
        for g in r["grids"]:
            a = g["achieved"]
            u = "-" if a["U0"] is None else f"{a['U0']:.3f}"
            err = "" if "error_lux" not in g else \
                f"; interreflected light's error at most {g['error_lux']['maximum']:.2g} lx"
            say(f"  {g['name']} ({g['sensors']} sensors): average {a['average']:.1f} lx, min {a['minimum']:.1f}, "
                f"max {a['maximum']:.1f}, U0 {u}{err}", highlight=False)
        if "radiosity_error" in r:
            say(f"  {_solution_words(r['radiosity_error'])}", highlight=False)
    head = "designed" if r["feasible"] else f"[bold red]not feasible[/] ({r['status']})"
    say(f"{head}: {r['message']}", highlight=False)
    t = r["timings"]
    v = r.get("verified") or {}
    check = f"; verified by a full solve (max deviation {v['max_relative_deviation']:.1e})" if v else ""
    total = "" if r["total_power_W"] is None else f"{r['total_power_W']:.4g} W of {r['full_power_W']:.4g} W; "
    say(f"wrote {output}" + (f" and {plan}" if plan is not None and r["feasible"] else "")
        + f": {total}precompute {t['precompute_s']:.2f} s, design {t['design_s'] * 1e3:.1f} ms"
        + (f", relighting {t['relight_s'] * 1e3:.3f} ms" if t.get("relight_s") else "") + check, highlight=False)


def _summary(r: dict, output: Path, render: Optional[Path]) -> None:
    say = common.console.print
    if r["emitters"][0]["intensity"] is not None:
        shown = 12                                       # all of them are in the JSON
        for e in r["emitters"][:shown]:
            say(f"  {e['name']}: intensity {e['intensity']:.4g}, {e['power_W']:.4g} W", highlight=False)
        if len(r["emitters"]) > shown:
            lit = sum(e["intensity"] > 0 for e in r["emitters"])
            say(f"  ... {len(r['emitters']) - shown} more emitters ({lit} of {len(r['emitters'])} on; "
                f"{r['total_power_W']:.4g} W in all)", highlight=False)
        for t in r["targets"]:
            a = t["achieved"]
            u = "-" if a["uniformity"] is None else f"{a['uniformity']:.3f}"
            margin = ", ".join(f"{g} {m:+.3g}" for g, m in t.get("margin", {}).items())
            err = "" if t.get("mean_error") is None else f"; error of the mean at most {t['mean_error']:.2g}"
            say(f"  {t['name']} ({t['quantity']}, {t['unit']}): min {a['min']:.4g}, mean {a['mean']:.4g}, "
                f"max {a['max']:.4g}, uniformity {u}" + (f"; margin {margin}" if margin else "") + err,
                highlight=False)
        if "radiosity_error" in r:
            say(f"  {_solution_words(r['radiosity_error'])}", highlight=False)
    verified = r.get("verified") or {}
    check = (f"; verified by a full solve (max deviation {verified['max_relative_deviation']:.1e})"
             if verified else "")
    head = "designed" if r["feasible"] else f"[bold red]not feasible[/] ({r['status']})"
    say(f"{head}: {r['message']}", highlight=False)
    say(f"wrote {output}" + (f" and {render}" if render is not None and r["feasible"] else "")
        + f": {r['evaluations']} radiosity solves, {r['time_s'] * 1e3:.1f} ms{check}", highlight=False)


def _solution_words(error: dict) -> str:
    """A design's radiosity figure (its report's JSON) in the words of ``hfrad solve``."""
    from ..solve.bounds import solution_line
    from ..solve.samples import SolutionError

    return solution_line(SolutionError.from_dict(error))
