"""Pictures of the patches: radiosity with the patch edges drawn over it.

Run:  PYTHONPATH=src python examples/patch_wireframe.py [--patches 3000] [-o out] [--refine 0.3]
(into out/ by default; `-o docs/images` regenerates the committed pictures on purpose)

Writes ``cornell-patches.png`` (the built-in Cornell box) and, when
../shared/scenes is present, ``mcguire-cornell-patches.png``
(CornellBox-Original.obj, duplicates merged). The radiosity is an exact dense
solve of (I - diag(rho) F) B = E per channel, so what is seen is the form
factors and the patches, not a factorization error. Edges are where the patch
seen by a pixel differs from its right or lower neighbour's. With ``--refine T``
it also writes ``cornell-refined-patches.png``: the built-in box cut to a third
of the patches, refined once where that coarse solution jumps by more than T
(``hfrad precompute --refine``), solved again.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from hfrad.formfactors import form_factor_matrix
from hfrad.render import render_radiance, save_png
from hfrad.render.tonemap import tonemap
from hfrad.scene.load import load_scene

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "scenes"


def exact_radiosity(scene) -> np.ndarray:
    """(n, 3) W/m^2: dense solve per channel (small scenes)."""
    F = form_factor_matrix(scene)
    B = np.empty((scene.n_patches, 3))
    for c in range(3):
        B[:, c] = np.linalg.solve(np.eye(scene.n_patches) - scene.reflectance[:, c, None] * F, scene.emission[:, c])
    return B


def wireframe_picture(scene, B, camera: str, size: int = 768) -> np.ndarray:
    """(size, size, 3) uint8: smooth radiosity, patch boundaries in dark grey."""
    radiance, face = render_radiance(scene, B, camera, width=size, height=size)
    lit = face >= 0
    lit[lit] = ~scene.emitters[face[lit]]
    lum = radiance @ np.array([0.2126, 0.7152, 0.0722])
    exposure = float(np.log2(0.8 / max(np.quantile(lum[lit], 0.99), 1e-12))) if lit.any() else 0.0
    image = tonemap(radiance, exposure=exposure)
    edge = np.zeros(face.shape, bool)
    edge[:, :-1] |= face[:, :-1] != face[:, 1:]
    edge[:-1, :] |= face[:-1, :] != face[1:, :]
    image[edge] = (image[edge] * 0.25).astype(np.uint8)
    return image


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--patches", type=int, default=3000)
    # default: a folder of its own (git-ignored), never over the committed docs/images pictures;
    # `-o docs/images` regenerates those on purpose (benchmarks/README.md)
    p.add_argument("-o", "--output", type=Path, default=Path("out"))
    p.add_argument("--refine", type=float, default=None)
    args = p.parse_args()
    args.output.mkdir(parents=True, exist_ok=True)
    jobs = [("cornell", "cornell-patches.png", "front")]
    original = SHARED / "cornell-box" / "CornellBox-Original.obj"
    if original.exists():
        jobs.append((str(original), "mcguire-cornell-patches.png", "0,1,3.9:0,1,0"))
    if args.refine is not None:
        from hfrad.solve.refine import refine_by_radiosity

        coarse = load_scene("cornell", patches=args.patches // 3)
        scene, marked = refine_by_radiosity(coarse, args.refine)
        B = exact_radiosity(scene)
        path = save_png(wireframe_picture(scene, B, "front"), args.output / "cornell-refined-patches.png")
        print(f"wrote {path} ({coarse.n_patches} patches, {marked} marked, {scene.n_patches} after refining)")
        return
    for source, name, camera in jobs:
        scene = load_scene(source, patches=args.patches)
        B = exact_radiosity(scene)
        path = save_png(wireframe_picture(scene, B, camera), args.output / name)
        print(f"wrote {path} ({scene.n_patches} patches; {'; '.join(scene.warnings) or 'no warnings'})")


if __name__ == "__main__":
    main()
