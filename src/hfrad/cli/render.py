"""``hfrad render FILE.hfr -o image.png``: a picture of the radiosity for the scene's (or new) emission."""

from __future__ import annotations

import time
from pathlib import Path
from typing import List, Optional

import typer

from ..errors import InputError
from ..render.image import DEFAULT_SAMPLES
from . import common
from .solve import EmissionFileOption, EmissionScaleOption


def register(app: typer.Typer) -> None:
    @app.command()
    def render(
        factorization: Path = typer.Argument(..., help="Factorization file from `hfrad precompute` (.hfr)."),
        output: Path = typer.Option(..., "-o", "--output", help="Picture to write (.png)."),
        emission: Optional[List[str]] = common.EmissionOption,
        emission_scale: float = EmissionScaleOption,
        emission_file: Optional[Path] = EmissionFileOption,
        camera: str = typer.Option("auto", "--camera",
                                   help="auto (three-quarter view, or the inside view where that would show a building's "
                                        "outside), front (along -z, the Cornell box view), "
                                        "inside (from within the largest enclosed space, down its longest "
                                        "level line: a building's inside; hfrad info prints it) "
                                        "or x,y,z:tx,ty,tz[:fov_degrees]."),
        width: int = typer.Option(512, "--width", min=1, help="Picture width, pixels (at most 16,384, and "
                                                              "~256 bytes a pixel of memory)."),
        height: int = typer.Option(512, "--height", min=1, help="Picture height, pixels (at most 16,384)."),
        exposure: Optional[float] = typer.Option(
            None, "--exposure", help="Exposure in EV: pixel = clip(B/pi * 2^EV, 0, 1), then sRGB. "
                                     "Default: --auto-exposure."),
        auto_exposure: bool = typer.Option(
            True, "--auto-exposure/--no-auto-exposure",
            help="Map the 99th percentile of non-emitting surfaces' luminance to 0.8 (ignored with --exposure)."),
        flat: bool = typer.Option(False, "--flat", help="One colour per patch (shows the patches)."),
        falsecolor: bool = typer.Option(False, "--falsecolor", help="False colour of luminance-weighted "
                                                                    "radiosity, with a colour bar."),
        unit: str = typer.Option("W/m2", "--unit", help="False-colour unit: W/m2, or lux (683 lm/W x luminance)."),
        samples: int = typer.Option(DEFAULT_SAMPLES, "--samples", help="Rays a pixel, a stratified k x k grid (1, 4, 9, 16, ... "
                                                         "up to 64): anti-aliased edges; 1 turns it off. Time "
                                                         "grows with the count."),
    ) -> None:
        """Solve for the scene's emitters (or --emission) and draw the radiosity as a PNG.

        Pixels show radiance B/pi (W/m^2/sr) of the first surface seen from the
        front; walls seen from behind are transparent, so a camera outside a
        closed room looks in.
        """
        import numpy as np

        from ..render import Camera, render_image, save_png
        from ..render.image import check_size
        from .solve import exitance_from_options

        with common.user_errors():
            if output.suffix.lower() != ".png":
                raise InputError(f"output must be a .png file, got '{output}'")
            if falsecolor:
                from ..render.falsecolor import check_unit
                check_unit(unit)
            if exposure is not None:
                from ..render.tonemap import MAX_EXPOSURE
                if not (np.isfinite(exposure) and abs(exposure) <= MAX_EXPOSURE):
                    raise InputError(f"--exposure must be a finite number of EV within +-{MAX_EXPOSURE:g}; got {exposure}")
            Camera.parse(camera, np.array([[0.0, 0, 0], [1, 1, 1]]))  # fail on a bad spec before the solve
            check_size(width, height, falsecolor=falsecolor, samples=samples)   # and on a picture too large for memory
            common.check_output(output)
            fac = common.load_factorization(factorization)
            scene = fac.scene
            E = exitance_from_options(scene, emission, emission_scale, emission_file)
            t0 = time.perf_counter()
            B = fac.solve(E)
            t_solve = time.perf_counter() - t0
            t1 = time.perf_counter()
            image = render_image(scene.replace(emission=E), B, camera=camera, width=width, height=height,
                                 exposure=exposure, auto_exposure=auto_exposure, flat=flat,
                                 falsecolor=falsecolor, unit=unit, samples=samples)
            t_render = time.perf_counter() - t1
            save_png(image, output)
        common.console.print(f"wrote {output}: {width}x{height}, {scene.n_patches:,} patches; "
                             f"solve {t_solve * 1e3:.1f} ms, render {t_render:.2f} s", highlight=False)
