"""hfrad: radiosity with infinite bounces, re-solved in milliseconds.

The pipeline of Aguerre & Fernández (2016), hierarchical factorization (HF)
of the form-factor matrix plus Sherman-Morrison-Woodbury::

    import hfrad
    scene = hfrad.load_scene("cornell", patches=3000)      # patches, materials, lights
    fac = hfrad.factorize(scene, eps=0.02)                 # form factors + HF, once
    B = fac.solve(scene.emission)                          # (n, 3) radiosity, O(nk)
    fac.error_estimate()                                   # error figures, per channel
    hfrad.save(fac, "cornell.hfr"); fac = hfrad.load("cornell.hfr")

A form-factor matrix you already have: ``hfrad.factorize_matrix(F, reflectance)``.
Where and how the precompute runs: ``backend=hfrad.LocalBackend(processes=4)`` or
``hfrad.DaskBackend(workers=4)``, ``checkpoint=hfrad.Checkpoint(path)``, and expert
knobs in ``options=hfrad.PrecomputeOptions(block_size=...)``.
The whole API is described in docs/api.md.

Names are imported lazily so that ``import hfrad`` stays fast.
"""

from __future__ import annotations

import importlib

from ._version import __version__

_EXPORTS = {
    "Scene": "hfrad.scene.scene",
    "Material": "hfrad.scene.scene",
    "load_scene": "hfrad.scene.load",
    "builtin_scene": "hfrad.scene.builtin",
    "subdivide": "hfrad.scene.patches",
    "factorize": "hfrad.pipeline",
    "factorize_matrix": "hfrad.pipeline",
    "LocalBackend": "hfrad.precompute.backends",
    "DaskBackend": "hfrad.precompute.backends",
    "Checkpoint": "hfrad.precompute.backends",
    "PrecomputeOptions": "hfrad.precompute.options",
    "HFactorization": "hfrad.solve.woodbury",
    "ErrorEstimate": "hfrad.solve.bounds",
    "SolutionError": "hfrad.solve.samples",
    "form_factor_matrix": "hfrad.formfactors.blocks",
    "iter_column_blocks": "hfrad.formfactors.blocks",
    "render_image": "hfrad.render.image",
    "save_png": "hfrad.render.image",
    "write_radiosity": "hfrad.io.export",
    "design": "hfrad.inverse",
    "InputError": "hfrad.errors",
    "SceneError": "hfrad.errors",
    "FactorizationError": "hfrad.errors",
    "FileFormatError": "hfrad.errors",
    "MemoryLimitError": "hfrad.errors",
    "AccuracyWarning": "hfrad.errors",
}


def load(path) -> "HFactorization":  # noqa: F821 - resolved lazily
    """Read a factorization written by :func:`save` or ``hfrad precompute`` (.hfr)."""
    from .solve.hfr import load_hfr

    return load_hfr(path)


def save(factorization, path) -> "Path":  # noqa: F821
    """Write a factorization (with its scene) to an .hfr file, atomically; same as ``factorization.save(path)``."""
    from .solve.hfr import save_hfr

    return save_hfr(factorization, path)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'hfrad' has no attribute {name!r}")


__all__ = sorted([*_EXPORTS, "load", "save", "__version__"])
