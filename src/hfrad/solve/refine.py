"""Patches refined where a first, coarse solution changes fast (``hfrad precompute --refine``).

A coarse exact-enough solve on the patches as cut (dense F with visibility,
Jacobi to a relative residual of 1e-4), then one level of conforming red-green
refinement of every patch on an edge across which the luminance jumps by more
than the threshold (:mod:`hfrad.scene.refine`). The dense F limits the coarse
scene to :data:`MAX_COARSE_PATCHES`.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from ..formfactors.blocks import form_factor_matrix
from ..progress import ProgressCallback
from ..scene.refine import marks_from_radiosity, refine_patches
from ..scene.scene import Scene
from .iterative import jacobi

#: The coarse solve holds the dense n x n F in float32: ``4 n^2`` bytes (256e6 at this limit).
MAX_COARSE_PATCHES = 8000


def refine_by_radiosity(scene: Scene, threshold: float, *, progress: ProgressCallback = None) -> tuple[Scene, int]:
    """One level of refinement where a coarse radiosity solution jumps by more than ``threshold``.

    Parameters
    ----------
    scene : Scene
        Unclustered patches (as cut by ``--patches`` / ``--max-edge``), at most
        :data:`MAX_COARSE_PATCHES`.
    threshold : float > 0
        Relative luminance jump |L_p - L_q| / max(L_p, L_q) across a patch edge
        that marks both patches (0.2 marks shadow edges and contact lines of the
        Cornell box, not the smooth gradients on its walls).
    progress : callable (done, total), optional
        Progress of the coarse form factors.

    Returns
    -------
    (Scene, int)
        The refined scene and the number of patches marked.
    """
    if scene.n_patches > MAX_COARSE_PATCHES:
        raise InputError(f"--refine solves the coarse scene densely: {scene.n_patches:,} patches is more than "
                         f"{MAX_COARSE_PATCHES:,}; ask for fewer --patches (refinement adds patches where needed)")
    if scene.is_clustered:
        raise InputError(f"--refine needs patches cut from faces, not clusters of triangles ({scene.name})")
    F = form_factor_matrix(scene, dtype=np.float32, progress=progress)
    B = jacobi(F, scene.reflectance, scene.emission, rtol=1e-4).radiosity
    marked = marks_from_radiosity(scene, B, threshold)
    return refine_patches(scene, marked), int(marked.sum())
