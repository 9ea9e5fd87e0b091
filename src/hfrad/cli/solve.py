"""``hfrad solve FILE.hfr -o OUT``: radiosity for the scene's (or new) emission, in O(nk)."""

from __future__ import annotations

import json
import time
import warnings
from pathlib import Path
from typing import List, Optional

import numpy as np
import typer

from ..errors import InputError
from ..errors import AccuracyWarning
from . import common
from .info import parse_emit

EmissionScaleOption = typer.Option(1.0, "--emission-scale", help="Multiply every emission by this.")
EmissionFileOption = typer.Option(None, "--emission-file", help="Emission JSON (as `hfrad view` saves it; format in "
                                                                "docs/emission.md), applied before --emission.")


def exitance_from_options(scene, emission: Optional[List[str]], scale: float,
                          emission_file: Optional[Path] = None) -> np.ndarray:
    """(n, 3) exitance: the scene's emitters, overridden per material/group (file, then
    ``--emission``), scaled."""
    from ..errors import SceneError
    from ..io.emission import emission_overrides, read_emission
    from ..scene.load import set_emission

    if not (scale >= 0 and np.isfinite(scale)):
        raise InputError(f"--emission-scale must be a finite number >= 0; got {scale}")
    lit = set_emission(scene, emission_overrides(read_emission(emission_file))) if emission_file else scene
    lit = set_emission(lit, parse_emit(emission)) if emission else lit
    E = lit.emission * scale
    if not E.any():
        raise SceneError(f"{scene.name}: no emitter, nothing to solve; light the scene with "
                         "--emission NAME=R,G,B (a material or group name, see hfrad info)")
    return E


def register(app: typer.Typer) -> None:
    @app.command()
    def solve(
        factorization: Path = typer.Argument(..., help="Factorization file from `hfrad precompute` (.hfr)."),
        output: Path = typer.Option(..., "-o", "--output", help="Result: .ply, .glb, .npz or .csv (by extension)."),
        emission: Optional[List[str]] = common.EmissionOption,
        emission_scale: float = EmissionScaleOption,
        emission_file: Optional[Path] = EmissionFileOption,
        residual: bool = typer.Option(False, "--residual", help="Also compute the a-posteriori residual "
                                      "||(I - RF) B - E|| / ||E|| with the factorization's reflectance "
                                      "(recomputes the form factors: as slow as the precompute's form-factor stage)."),
        as_json: bool = typer.Option(False, "--json", help="Print one JSON object (error figures, rank, timings) "
                                     "on standard output instead of the summary line."),
        quiet: bool = common.QuietOption,
        colors: Optional[str] = typer.Option(None, "--colors", help="Vertex colours of exports: srgb or linear "
                                                                 "(default: linear in .glb as glTF requires, sRGB in .ply)."),
    ) -> None:
        """Solve (I - RF) B = E for the scene's emitters (or --emission) and write B.

        Memory: the factors (Q, V and three k x k inverses: (2 n k + 3 k^2) x 4
        bytes in float32) plus O(n).
        Prints the error figures of the answer (see docs/method.md).
        """
        from ..io.export import write_radiosity

        with common.user_errors():
            common.check_output(output)
            t0 = time.perf_counter()
            fac = common.load_factorization(factorization)
            t_load = time.perf_counter() - t0
            E = exitance_from_options(fac.scene, emission, emission_scale, emission_file)
            t1 = time.perf_counter()
            B = fac.solve(E)
            t_solve = time.perf_counter() - t1
            t1 = time.perf_counter()
            solution = fac.solution_error(E, B)
            t_figure = time.perf_counter() - t1
            write_radiosity(fac.scene, B, output, E, colors=colors)
            r = None
            if residual:
                with common.progress_bar("residual (form factors)", quiet or as_json) as bar:
                    r = fac.residual(E, B, progress=bar, processes=None)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", AccuracyWarning)   # a missing bound is printed as "none"
                figures = fac.error_estimate().as_dict()
        # the a-priori figures keep their names under "a_priori_"; error_bound is this solve's figure
        a_priori = {"a_priori_bound": figures.pop("error_bound"), "a_priori_norm": figures.pop("error_norm"),
                    "a_priori_kind": figures.pop("error_bound_kind"),
                    "a_priori_failure_probability": figures.pop("failure_probability")}
        report = {"output": str(output), "n_patches": fac.n_patches, "rank": fac.rank, **solution.as_dict(),
                  **a_priori, **figures, "solve_ms": t_solve * 1e3, "error_ms": t_figure * 1e3, "load_s": t_load}
        if r is not None:
            report.update(r.as_dict())
        if as_json:
            typer.echo(json.dumps(report))
            return
        # first the figure a user can rely on: this solution's guaranteed bound (--residual), else the a-priori
        # bound when it says something, else "no useful a-priori bound" and what to do
        lines = common.error_figures_line(fac, residual=r, solution=solution).splitlines()
        common.console.print(lines[0], highlight=False)
        if r is not None:
            common.console.print("a-posteriori residual ||(I - RF) B - E|| / ||E|| (R,G,B): "
                                 + ", ".join(f"{x:.3g}" for x in r.residual), highlight=False)
        common.console.print(
            f"wrote {output}: {fac.n_patches:,} patches, rank {fac.rank:,}; solve {t_solve * 1e3:.1f} ms "
            f"(load {t_load:.2f} s)", highlight=False)
        for line in lines[1:]:
            common.console.print(line, highlight=False)
