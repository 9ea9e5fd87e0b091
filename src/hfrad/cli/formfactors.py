"""``hfrad formfactors SCENE -o F.npz``: the dense form-factor matrix of a small scene."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from . import common


def write_npz(path: Path, scene, F) -> None:
    """Write F and the patch data (user order) to ``path`` via a temporary name + rename."""
    import numpy as np

    from ..atomic import atomic_path

    path = Path(path)
    if path.suffix != ".npz":
        path = path.with_name(path.name + ".npz")
    with atomic_path(path, suffix=".npz") as tmp:
        np.savez(tmp, F=F, area=np.asarray(scene.areas), centroid=np.asarray(scene.centroids),
                 normal=np.asarray(scene.normals), material=np.asarray(scene.material, dtype=np.int64),
                 material_names=np.array(scene.material_names, dtype=str))


def register(app: typer.Typer) -> None:
    @app.command()
    def formfactors(
        scene: str = typer.Argument(..., help="Scene file (.obj, .ply, .gltf, .glb) or built-in name (cornell, ...)."),
        output: Path = typer.Option(..., "--output", "-o", help="Output .npz: F, area, centroid, normal, material, material_names."),
        max_edge: Optional[float] = common.MaxEdgeOption,
        patches: Optional[int] = common.PatchesOption,
        unit_scale: float = common.UnitScaleOption,
        samples: int = typer.Option(4, "--samples", help="Visibility rays per patch pair (1, 4, 9, 16, ...; 1 = centroid to centroid)."),
        float32: bool = typer.Option(False, "--float32", help="Store F in single precision (half the memory)."),
        keep_duplicates: bool = common.KeepDuplicatesOption,
        quiet: bool = common.QuietOption,
    ) -> None:
        """Dense form-factor matrix F (visibility included), in the scene's patch order.

        F[i, j] is the fraction of the energy leaving patch i that reaches patch j.
        Memory: n^2 x 8 bytes (x 4 with --float32); larger scenes are refused:
        use `hfrad precompute`, which streams F in column blocks instead.
        """
        import numpy as np

        from ..formfactors import check_dense_memory, form_factor_matrix
        from ..scene.load import load_scene

        dtype = np.float32 if float32 else np.float64
        with common.user_errors():
            s = load_scene(scene, unit_scale=unit_scale, max_edge=max_edge, patches=patches,
                           keep_duplicates=keep_duplicates)
            check_dense_memory(s.n_patches, dtype)
            with common.progress_bar(f"form factors ({s.n_patches} patches)", quiet) as progress:
                F = form_factor_matrix(s, samples=samples, dtype=dtype, progress=progress)
            write_npz(output, s, F)
        if not quiet:
            common.console.print(f"wrote {output} ({s.n_patches} x {s.n_patches})", highlight=False)
