"""Emitters under the viewer's control and the radiosity they produce.

Radiosity is linear in the exitance, channel by channel:

    B_c = (I - R_c F)^{-1} E_c,   E_c = sum_g on_g * I_g * colour_{g,c} * 1_g,

with ``1_g`` the patches of emitter g (a material or group; where two
emitters share patches the later one wins, as with repeated ``--emission``).
So the viewer solves once, with one batched Woodbury solve
(``fac.solve`` on an (n, 3, m) stack of unit exitances, O(n k m)), and every
slider move after that is the weighted sum ``B = sum_g w_g U_g``: O(n m),
exact up to rounding. The batched solve is repeated only when the set of
emitters changes (a material made an emitter, an emission file loaded).
``direct=True`` re-solves ``fac.solve(E)`` on every change instead (the
benchmark compares both).
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from ..errors import InputError
from ..io.emission import EmitterSetting
from ..scene.load import patches_named

#: Intensity (W/m^2) given to a material that is made an emitter from the page.
DEFAULT_INTENSITY = 10.0


@dataclasses.dataclass(frozen=True)
class Emitter:
    """One light: a material or group emitting ``intensity * color`` W/m^2 when on.

    Attributes
    ----------
    name : str
        Material (looked up first) or group name.
    intensity : float >= 0, W/m^2
        The largest channel of the exitance.
    color : (3,) float in [0, 1]
        Relative RGB exitance; its largest channel is 1 (white is (1, 1, 1)).
    on : bool
    """

    name: str
    intensity: float
    color: tuple[float, float, float] = (1.0, 1.0, 1.0)
    on: bool = True

    def __post_init__(self) -> None:
        if not (np.isfinite(self.intensity) and self.intensity >= 0):
            raise InputError(f"emitter '{self.name}': intensity must be a finite number >= 0 W/m^2, "
                             f"got {self.intensity}")
        c = np.asarray(self.color, dtype=np.float64).reshape(-1)
        if c.shape != (3,) or not (np.isfinite(c).all() and (c >= 0).all() and (c <= 1).all()):
            raise InputError(f"emitter '{self.name}': color must be three numbers in [0, 1], got {self.color}")
        object.__setattr__(self, "color", tuple(float(x) for x in c))
        object.__setattr__(self, "intensity", float(self.intensity))

    @property
    def exitance(self) -> tuple[float, float, float]:
        """(3,) float, W/m^2, whether on or not."""
        return tuple(self.intensity * c for c in self.color)

    def setting(self) -> EmitterSetting:
        """The emission-file entry of this emitter."""
        return EmitterSetting(self.name, self.exitance, self.on)

    @classmethod
    def from_exitance(cls, name: str, exitance, on: bool = True) -> "Emitter":
        """Split an RGB exitance into intensity (largest channel) and colour."""
        e = np.asarray(exitance, dtype=np.float64).reshape(3)
        peak = float(e.max())
        color = tuple(e / peak) if peak > 0 else (1.0, 1.0, 1.0)
        return cls(name, peak, color, on)

    @classmethod
    def from_setting(cls, setting: EmitterSetting) -> "Emitter":
        return cls.from_exitance(setting.name, setting.exitance, setting.on)


def scene_emitters(scene) -> tuple[list[Emitter], list[str]]:
    """One emitter per material that emits in the scene, and warnings.

    The exitance is the area-weighted mean over the material's emitting
    patches; a material whose patches emit different amounts (possible in
    PLY files) gets a warning, as the viewer lights it uniformly.
    """
    out, warnings = [], []
    E = np.asarray(scene.emission)
    for m, name in enumerate(scene.material_names):
        mask = scene.material == m
        if not E[mask].any():
            continue
        a = scene.areas[mask]
        mean = (E[mask] * a[:, None]).sum(axis=0) / max(a.sum(), 1e-300)
        if not np.allclose(E[mask], mean, rtol=1e-6, atol=0):
            warnings.append(f"material '{name}' emits unevenly; the viewer lights it with its mean "
                            f"exitance {np.round(mean, 4).tolist()} W/m^2")
        out.append(Emitter.from_exitance(name, mean))
    return out, warnings


class Lighting:
    """Radiosity of a set of emitters, by superposition of batched unit solves.

    Parameters
    ----------
    fac : HFactorization
        With its scene (``fac.scene``), e.g. from ``hfrad.load``.

    Attributes
    ----------
    names : tuple of str
        Emitters the unit solutions are for, in order.
    basis_seconds : float
        Time of the last batched solve.
    """

    def __init__(self, fac) -> None:
        self.fac = fac
        self.scene = fac.scene
        self.names: tuple[str, ...] = ()
        self._masks = np.zeros((self.scene.n_patches, 0), bool)
        self._basis = np.zeros((self.scene.n_patches, 3, 0))
        self.basis_seconds = 0.0

    def masks(self, names) -> np.ndarray:
        """(n, m) bool: the patches each emitter lights (a later name wins on shared patches).

        Raises
        ------
        SceneError
            An unknown name (the message lists the scene's materials and groups).
        """
        masks = np.stack([patches_named(self.scene, nm) for nm in names], axis=1) if names else \
            np.zeros((self.scene.n_patches, 0), bool)
        taken = np.zeros(self.scene.n_patches, bool)
        for g in range(len(names) - 1, -1, -1):
            masks[:, g] &= ~taken
            taken |= masks[:, g]
        return masks

    def _prepare(self, names: tuple[str, ...]) -> None:
        if names == self.names:
            return
        masks = self.masks(names)
        unit = np.repeat(masks[:, None, :].astype(np.float64), 3, axis=1)   # (n, 3, m) unit exitances
        t0 = time.perf_counter()
        basis = self.fac.solve(unit) if names else np.zeros((self.scene.n_patches, 3, 0))
        self.basis_seconds = time.perf_counter() - t0
        self.names, self._masks, self._basis = names, masks, np.ascontiguousarray(basis)

    @staticmethod
    def _weights(emitters) -> np.ndarray:
        """(3, m) float: emitted exitance per channel and emitter, W/m^2."""
        if not emitters:
            return np.zeros((3, 0))
        return np.array([e.exitance if e.on else (0.0, 0.0, 0.0) for e in emitters]).T

    def exitance(self, emitters) -> np.ndarray:
        """(n, 3) float, W/m^2: the exitance the emitters produce, user patch order."""
        names = tuple(e.name for e in emitters)
        masks = self._masks if names == self.names else self.masks(names)
        return masks.astype(np.float64) @ self._weights(emitters).T

    def radiosity(self, emitters, *, direct: bool = False) -> np.ndarray:
        """(n, 3) float, W/m^2: radiosity of the emitters.

        Parameters
        ----------
        emitters : sequence of Emitter
        direct : bool
            Solve ``fac.solve(E)`` now instead of combining the unit solutions.

        Notes
        -----
        O(n m) per call once the unit solutions exist for these emitters'
        names; a new set of names costs one batched solve, O(n k m).
        """
        if direct:
            return self.fac.solve(self.exitance(emitters))
        self._prepare(tuple(e.name for e in emitters))
        return np.einsum("ncm,cm->nc", self._basis, self._weights(emitters), optimize=False)
