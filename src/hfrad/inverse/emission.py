"""A design as an emission file (``hfrad-emission``), for ``hfrad render/solve --emission-file`` and ``hfrad view``."""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from ..io.emission import EmitterSetting, emission_overrides
from ..scene.load import set_emission
from .design import DesignResult
from .spec import DesignSpec, SpecError


def check_nameable(spec: DesignSpec) -> None:
    """SpecError unless every emitter is one material or group name (what an emission file can set)."""
    for i, e in enumerate(spec.emitters):
        if e.scene_name is None:
            raise SpecError(f"emitters[{i}] ({e.name!r}): not selected by one material or group name; an "
                            "emission file (--emission-out) can only set whole materials or groups")


def emission_settings(result: DesignResult, scene) -> list[EmitterSetting]:
    """The designed emission as emission-file entries (material or group name -> exitance).

    With ``background: none`` the scene's other emitting materials come first,
    switched off (``on: false``, their exitance kept); the designed emitters
    follow, so they win where a name overlaps.

    Raises
    ------
    InputError
        The design is infeasible (there is no emission to write).
    SpecError
        An emitter was not selected by a single
        material or group name (an emission file can name nothing else), or
        the file would not reproduce the design when read back (a group named
        like a material; a background set on other than whole materials).
    """
    if not result.feasible or result.exitance is None:
        raise InputError("no feasible design to write as an emission file (the result names the "
                         "conflicting goals)")
    out = []
    if result.spec.background == "none":
        for m in scene.materials:
            if m.is_emitter:
                out.append(EmitterSetting(m.name, tuple(float(x) for x in m.emission), on=False))
    check_nameable(result.spec)
    for e, rep in zip(result.spec.emitters, result.report["emitters"]):
        out.append(EmitterSetting(e.scene_name, tuple(float(x) for x in rep["exitance_W_m2"])))
    # the file must reproduce the design exactly when read back (as --emission-file reads it)
    lit = set_emission(scene, emission_overrides(out)).emission
    if not np.allclose(lit, result.exitance, rtol=1e-12, atol=0.0):
        bad = int(np.flatnonzero(~np.isclose(lit, result.exitance, rtol=1e-12, atol=0.0).all(axis=1))[0])
        raise SpecError(f"the design cannot be written as an emission file: read back, it would give patch "
                         f"{bad} another emission (a group named like a material, or a background that is "
                         "not set by whole materials)")
    return out
