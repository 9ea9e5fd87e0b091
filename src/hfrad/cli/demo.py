"""``hfrad demo``: the whole pipeline on the built-in Cornell box."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import typer

from . import common


def register(app: typer.Typer) -> None:
    @app.command()
    def demo(
        output: Path = typer.Option(Path("hfrad-demo"), "-o", "--output", help="Folder for the results."),
        patches: int = typer.Option(3000, "--patches", help="Patches of the Cornell box (the precompute's memory "
                                                           "for that many is checked before cutting)."),
        eps: float = typer.Option(0.02, "--eps", help="Target relative error of the factorization."),
        quiet: bool = common.QuietOption,
    ) -> None:
        """Build the Cornell box, precompute, solve, render a PNG and bake a GLB.

        Writes DIR/cornell.hfr, DIR/cornell.png, DIR/cornell.glb and
        DIR/cornell-blue.png (the same scene re-lit with a blue light, solved
        from the factorization in O(n k)). Memory: as `hfrad precompute`
        (hfrad.memory.precompute_bytes: 40 n b + (2 n k + 3 k^2) 4 + 16 n k
        bytes, b = 256), checked before cutting. Prints the error figure of each
        solution first (relative to the reflected light, from exact rows of F kept
        from the pass), then the factorization's a-priori bound for any light and
        the paper's eq. 5 estimate.
        """
        from ..io.export import write_radiosity
        from ..solve.bounds import solution_line
        from ..solve.hfr import save_hfr
        from ..pipeline import factorize
        from ..defaults import DEFAULT_BLOCK_SIZE
        from ..render import render_image, save_png
        from .info import load_scene_from_options

        out = common.console.print
        t0 = time.perf_counter()
        with common.user_errors():
            common.check_output_folder(output, ("cornell.hfr", "cornell.png", "cornell.glb", "cornell-blue.png"))
            need = lambda n: common.check_memory_for_precompute(n, min(DEFAULT_BLOCK_SIZE, n), "float32")  # noqa: E731
            with common.stage_clock(quiet, start=t0) as clock:
                scene = load_scene_from_options("cornell", patches=patches, need=need, on_stage=clock)
                clock.stop()
            out(f"Cornell box: {scene.n_patches:,} patches, {scene.emitters.sum()} emitting")
            with common.progress_bar("precompute (form factors + HF)", quiet) as bar:
                def status(info: dict) -> None:
                    if "estimate" in info and not quiet:
                        out(common.estimate_line(info["estimate"], info.get("pass_over_kernel")), highlight=False)

                t_fac = time.perf_counter()
                fac = factorize(scene, eps=eps, progress=bar, status=status)
                common.add_factorize_stages(clock, fac, time.perf_counter() - t_fac)
                if bar is not None:
                    bar.note(f"rank {fac.rank:,}")
            info = fac.lowrank.info
            clock("save")
            common.check_space_for_hfr(output / "cornell.hfr", fac)   # HDF5 cannot fail cleanly on a full disk
            save_hfr(fac, output / "cornell.hfr", timings={k: v for k, v in info.items() if k.startswith("time")})
            clock.stop()
            t_pre = clock.total()   # load to save: what the summary below accounts for
            precompute = clock.summary(t_pre)
            clock("solve")
            B = fac.solve(scene.emission)
            clock("error figures")
            # this solution's figure first (from the rows of F kept from the pass: no second pass)
            out(common.error_figures_line(fac, solution=fac.solution_error(scene.emission, B)), highlight=False)
            out(f"precompute: {precompute}; rank {fac.rank:,} of {fac.n_patches:,}, "
                f"achieved error {fac.relative_error:.4f} (target {eps})", highlight=False)
            clock("render and export")
            save_png(render_image(scene, B, camera="front"), output / "cornell.png")
            write_radiosity(scene, B, output / "cornell.glb", scene.emission)
            blue = scene.emission * np.array([0.1, 0.3, 1.0]) / 0.4  # relight: same lamp, blue
            clock("relight")
            B_blue, blue_error = fac.solve(blue, return_error=True)
            clock("error figures")
            out(f"relit blue: {solution_line(blue_error)}", highlight=False)
            clock("render and export")
            save_png(render_image(scene.replace(emission=blue), B_blue, camera="front"), output / "cornell-blue.png")
            clock.stop()
        out(f"wrote {output / 'cornell.png'}, {output / 'cornell-blue.png'}, {output / 'cornell.glb'}, "
            f"{output / 'cornell.hfr'}; time: {clock.summary()} (the first solve includes loading numba's "
            "compiled code; the relight is the solve's own cost)", highlight=False)
