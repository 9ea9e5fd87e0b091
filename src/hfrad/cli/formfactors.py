"""``hfrad formfactors SCENE -o F.npz``: the dense form-factor matrix of a small scene."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import typer

from . import common


def npz_path(path: Path) -> Path:
    """``path``, with ``.npz`` appended unless it ends so (what ``numpy.savez`` would write)."""
    path = Path(path)
    return path if path.suffix == ".npz" else path.with_name(path.name + ".npz")


def write_npz(path: Path, scene, F) -> None:
    """Write F and the patch data (user order) to ``path`` via a temporary name + rename."""
    import numpy as np

    from ..atomic import atomic_path

    path = npz_path(path)
    with atomic_path(path, suffix=".npz") as tmp:
        np.savez(tmp, F=F, area=np.asarray(scene.areas), centroid=np.asarray(scene.centroids),
                 normal=np.asarray(scene.normals), material=np.asarray(scene.material, dtype=np.int64),
                 material_names=np.array(scene.material_names, dtype=str))


def register(app: typer.Typer) -> None:
    @app.command()
    @common.scene_options
    def formfactors(
        scene: str = typer.Argument(..., help="Scene file (.obj, .ply, .gltf, .glb, .rad, .ifc) or built-in name (cornell, ...)."),
        output: Path = typer.Option(..., "--output", "-o", help="Output .npz: F, area, centroid, normal, material, material_names."),
        scene_options: common.SceneOptions = None,
        samples: int = typer.Option(4, "--samples", help="Visibility rays per patch pair (1, 4, 9, 16, ... up to 1,024; 1 = centroid to centroid; 0 = no visibility)."),
        dtype: str = common.dtype_option("float64"),
        quiet: bool = common.QuietOption,
    ) -> None:
        """Dense form-factor matrix F (visibility included), in the scene's patch order.

        F[i, j] is the fraction of the energy leaving patch i that reaches patch j.
        Memory: n^2 x 8 bytes (4 with --dtype float32); larger scenes are refused:
        use `hfrad precompute`, which streams F in column blocks instead.
        """
        from ..formfactors import check_dense_memory, form_factor_matrix
        from .info import load_scene_from_options

        with common.user_errors():
            dt = common.check_dtype(dtype)
            common.check_samples(samples)
            common.check_output(npz_path(output))
            with common.stage_clock(quiet) as clock:
                s = load_scene_from_options(scene, **dataclasses.asdict(scene_options),
                                            need=lambda n: check_dense_memory(n, dt), on_stage=clock)   # before cutting
                clock.stop()
            check_dense_memory(s.n_patches, dt)
            clock("form factors")
            with common.progress_bar(f"form factors ({s.n_patches} patches)", quiet) as progress:
                F = form_factor_matrix(s, samples=samples, dtype=dt, progress=progress)
            clock("save")
            write_npz(output, s, F)
            clock.stop()
        if not quiet:
            common.console.print(f"wrote {output} ({s.n_patches} x {s.n_patches}); time: {clock.summary()}",
                                 highlight=False)
