"""Inverse lighting design: emitter intensities that meet illumination goals (issue 13).

The layer above :mod:`hfrad.solve` and :mod:`hfrad.render`: it uses only a
factorization's public ``solve`` and the scene it carries. Radiosity is linear
in the emission, so one batched solve gives every target's response to every
emitter; SciPy then solves a small LP (least power) or bounded least-squares
problem. See :func:`design` and :mod:`hfrad.inverse.spec` for the spec format.
"""

from .design import DesignResult, design
from .spec import QUANTITIES, DesignSpec, SpecError, parse_spec, read_spec

__all__ = ["design", "DesignResult", "DesignSpec", "SpecError", "parse_spec", "read_spec", "QUANTITIES"]
