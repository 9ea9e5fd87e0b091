"""The design specification: which patches may emit, what the targets must achieve.

A spec is a JSON (or TOML) document, or the same structure as a dict::

    {
      "emitters": [
        {"name": "ceiling", "material": "light", "max": 50.0, "color": [1, 1, 1]},
        {"name": "lamp", "group": "desk_lamp", "max": 20.0}
      ],
      "targets": [
        {"name": "desk", "material": "desk", "quantity": "irradiance_lux", "min": 500, "uniformity": 0.6},
        {"name": "walls", "material": "wall", "quantity": "radiosity", "max": 40}
      ],
      "objective": "min_power",
      "background": "scene"
    }

Every emitter and target selects patches by ``material``, ``group`` (a name,
or a list of names) or ``patches`` (indices in the user's patch order); when
several are given it takes the patches that match all of them (``"group":
"desk_1", "material": "desk"`` is the top of desk 1). An emitter's unknown is one intensity scale ``s >= 0``: its
patches emit ``s * color`` W/m^2 per channel, ``s <= max``. ``background``
says what happens to the scene's own emission on patches no emitter selects:
``"scene"`` (default) keeps it as a fixed contribution (daylight through a
window), ``"none"`` switches it off.

Every problem is reported as a :class:`SpecError` naming the field, e.g.
``spec.json: targets[1].quantity: unknown quantity 'lux'; expected one of ...``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from ..errors import InputError
from ..jsonfile import read_document
from ..render.falsecolor import photometric

#: quantity -> (unit printed in results, description)
QUANTITIES = {
    "radiosity": ("W/m^2", "luminance-weighted radiosity (as `hfrad render --falsecolor`)"),
    "irradiance": ("W/m^2", "luminance-weighted irradiance"),
    "irradiance_lux": ("lux", "illuminance, 683 lm/W x luminance-weighted irradiance "
                              "(as `hfrad render --falsecolor --unit lux`)"),
}
OBJECTIVES = ("min_power", "least_squares")
BACKGROUNDS = ("scene", "none")
GOALS = ("min", "max", "mean", "uniformity")

_SELECTORS = ("material", "group", "patches")
_EMITTER_KEYS = {"name", "max", "color", *_SELECTORS}
_TARGET_KEYS = {"name", "quantity", *GOALS, *_SELECTORS}
_TOP_KEYS = {"emitters", "targets", "objective", "background", "description"}


class SpecError(InputError):
    """A design spec is malformed; the message names the field (``targets[1].quantity``)."""


@dataclass(frozen=True)
class Emitter:
    """One designed light: patches that emit ``intensity * color`` W/m^2.

    Attributes
    ----------
    name : str
    patches : (p,) int, user patch order
    color : (3,) float >= 0, exitance per unit intensity, W/m^2 per channel
    max : float, upper bound of the intensity (inf when absent)
    scene_name : str or None
        The material or group name that selects exactly these patches (when
        the emitter was given by one name), for emission files.
    """

    name: str
    patches: np.ndarray
    color: np.ndarray
    max: float
    scene_name: str | None = None


@dataclass(frozen=True)
class Target:
    """Patches whose ``quantity`` must meet goals (None = no such goal).

    ``min``/``max`` hold on every patch; ``mean`` is the area-weighted mean
    (a lower bound for ``min_power``, the value fitted by ``least_squares``);
    ``uniformity`` is min / mean >= value (EN 12464-1's U0).
    """

    name: str
    patches: np.ndarray
    quantity: str
    min: float | None = None
    max: float | None = None
    mean: float | None = None
    uniformity: float | None = None

    @property
    def unit(self) -> str:
        return QUANTITIES[self.quantity][0]

    def goals(self) -> dict[str, float]:
        return {g: getattr(self, g) for g in GOALS if getattr(self, g) is not None}


@dataclass(frozen=True)
class DesignSpec:
    """A validated spec, bound to one scene (patch indices resolved)."""

    emitters: tuple[Emitter, ...]
    targets: tuple[Target, ...]
    objective: str = "min_power"
    background: str = "scene"


def read_spec(path: "str | Path") -> dict:
    """The raw spec of a ``.json`` or ``.toml`` file (not yet validated).

    Raises
    ------
    FileNotFoundError
        No such file.
    SpecError
        Not valid JSON/TOML (the parser's line and column are quoted).
    """
    return read_document(path, what="spec", error=SpecError)


def parse_spec(spec: "Mapping[str, Any] | str | Path", scene, *, source: str | None = None) -> DesignSpec:
    """Validate a spec against ``scene`` and resolve its selections to patch indices.

    Parameters
    ----------
    spec : dict, or path of a .json / .toml file
    scene : Scene
        The scene the factorization carries (``fac.scene``): material and group
        names and the number of patches come from it.
    source : str, optional
        Name used in messages (default: the file name, or ``spec``).

    Returns
    -------
    DesignSpec

    Raises
    ------
    SpecError
        The first problem found, naming the field: an unknown key, material,
        group or quantity; a negative or non-finite bound; min > max; an
        emitter without light (colour of zero luminance); two emitters that
        select the same patch; an objective the goals cannot drive.
    """
    if isinstance(spec, (str, Path)):
        source = source or str(spec)
        spec = read_spec(spec)
    where = source or "spec"
    if not isinstance(spec, Mapping):
        raise SpecError(f"{where}: expected an object with 'emitters' and 'targets', got {type(spec).__name__}")
    _unknown_keys(spec, _TOP_KEYS, where, "")
    objective = spec.get("objective", "min_power")
    if objective not in OBJECTIVES:
        raise SpecError(f"{where}: objective: unknown objective {objective!r}; expected one of "
                        + ", ".join(OBJECTIVES))
    background = spec.get("background", "scene")
    if background not in BACKGROUNDS:
        raise SpecError(f"{where}: background: expected one of {', '.join(BACKGROUNDS)}, got {background!r}")
    emitters = tuple(_emitter(e, scene, where, f"emitters[{i}]") for i, e in enumerate(_list(spec, "emitters", where)))
    targets = tuple(_target(t, scene, where, f"targets[{i}]") for i, t in enumerate(_list(spec, "targets", where)))
    for kind, items in (("emitters", emitters), ("targets", targets)):
        names = [x.name for x in items]
        dup = next((x for x in names if names.count(x) > 1), None)
        if dup is not None:
            raise SpecError(f"{where}: {kind}: the name {dup!r} is used twice; names must be unique")
    owner = np.full(scene.n_patches, -1)
    for i, e in enumerate(emitters):
        taken = owner[e.patches] >= 0
        if taken.any():
            j = int(owner[e.patches[taken][0]])
            raise SpecError(f"{where}: emitters[{i}]: selects patch {int(e.patches[taken][0])}, already "
                            f"selected by emitters[{j}] ({emitters[j].name!r}); an emitter's patches must "
                            "not overlap another's")
        owner[e.patches] = i
    if objective == "least_squares" and not any(t.mean is not None for t in targets):
        raise SpecError(f"{where}: objective: least_squares fits the targets' 'mean' goals, but no "
                        "target has one; add \"mean\": VALUE to a target or use min_power")
    return DesignSpec(emitters, targets, objective, background)


# -- helpers ---------------------------------------------------------------------------------------
def _list(spec: Mapping, key: str, where: str) -> list:
    value = spec.get(key)
    if not isinstance(value, list) or not value:
        raise SpecError(f"{where}: {key}: expected a non-empty list, got {value!r}")
    return value


def _unknown_keys(obj: Mapping, allowed: set, where: str, field: str) -> None:
    for key in obj:
        if key not in allowed:
            prefix = f"{field}." if field else ""
            raise SpecError(f"{where}: {prefix}{key}: unknown key; expected one of {', '.join(sorted(allowed))}")


def _number(obj: Mapping, key: str, where: str, field: str, *, low: float = 0.0,
            high: float = math.inf, open_low: bool = False) -> float | None:
    if key not in obj or obj[key] is None:
        return None
    value = obj[key]
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise SpecError(f"{where}: {field}.{key}: expected a finite number, got {value!r}")
    if value < low or (open_low and value == low) or value > high:
        lo = "(" if open_low else "["
        raise SpecError(f"{where}: {field}.{key}: {value!r} is outside {lo}{low:g}, {high:g}]"
                        + (" (a negative bound has no meaning here)" if value < 0 else ""))
    return float(value)


def _select(obj: Mapping, scene, where: str, field: str) -> np.ndarray:
    """Patch indices chosen by material, group and/or patches (the intersection when several are given)."""
    given = [k for k in _SELECTORS if k in obj]
    if not given:
        raise SpecError(f"{where}: {field}: select patches with material, group or patches (none given)")
    n = scene.n_patches
    mask = np.ones(n, bool)
    for key in given:
        mask &= _selector_mask(key, obj[key], scene, where, field)
    if not mask.any():
        raise SpecError(f"{where}: {field}: {' and '.join(f'{k} {obj[k]!r}' for k in given)} select no patch "
                        "of this scene")
    return np.flatnonzero(mask)


def _selector_mask(key: str, value: Any, scene, where: str, field: str) -> np.ndarray:
    n = scene.n_patches
    mask = np.zeros(n, bool)
    if key == "patches":
        if not isinstance(value, list) or not value or not all(isinstance(v, int) and not isinstance(v, bool)
                                                               for v in value):
            raise SpecError(f"{where}: {field}.patches: expected a non-empty list of patch indices, got {value!r}")
        idx = np.asarray(value, dtype=np.int64)
        bad = idx[(idx < 0) | (idx >= n)]
        if bad.size:
            raise SpecError(f"{where}: {field}.patches: index {int(bad[0])} is outside 0..{n - 1}")
        mask[idx] = True
        return mask
    names = [value] if isinstance(value, str) else value
    if not isinstance(names, list) or not names or not all(isinstance(v, str) for v in names):
        raise SpecError(f"{where}: {field}.{key}: expected a name or a list of names, got {value!r}")
    table, index = (scene.material_names, scene.material) if key == "material" else (scene.groups, scene.group)
    for name in names:
        if name not in table:
            shown = ", ".join(table[:30]) + (" ..." if len(table) > 30 else "")
            raise SpecError(f"{where}: {field}.{key}: unknown {key} {name!r}; the scene's {key}s are: {shown}")
        mask |= index == table.index(name)
    return mask


def _name(obj: Mapping, where: str, field: str) -> str:
    name = obj.get("name", field)
    if not isinstance(name, str) or not name:
        raise SpecError(f"{where}: {field}.name: expected a non-empty string, got {name!r}")
    return name


def _entry(obj: Any, allowed: set, scene, where: str, field: str) -> tuple[str, np.ndarray]:
    """Name and patches of an emitter or target, after checking it is an object with known keys."""
    if not isinstance(obj, Mapping):
        raise SpecError(f"{where}: {field}: expected an object, got {obj!r}")
    _unknown_keys(obj, allowed, where, field)
    return _name(obj, where, field), _select(obj, scene, where, field)


def _emitter(obj: Any, scene, where: str, field: str) -> Emitter:
    name, patches = _entry(obj, _EMITTER_KEYS, scene, where, field)
    upper = _number(obj, "max", where, field)
    color = obj.get("color", [1.0, 1.0, 1.0])
    if (not isinstance(color, list) or len(color) != 3
            or not all(isinstance(c, (int, float)) and not isinstance(c, bool) and math.isfinite(c) and c >= 0
                       for c in color)):
        raise SpecError(f"{where}: {field}.color: expected three finite numbers >= 0 (R, G, B), got {color!r}")
    if not photometric(np.asarray(color, float)) > 0:
        raise SpecError(f"{where}: {field}.color: {color!r} has zero luminance; it cannot light anything visible")
    given = [k for k in _SELECTORS if k in obj]
    scene_name = obj[given[0]] if given in (["material"], ["group"]) and isinstance(obj[given[0]], str) else None
    return Emitter(name, patches, np.asarray(color, dtype=np.float64), math.inf if upper is None else upper,
                   scene_name)


def _target(obj: Any, scene, where: str, field: str) -> Target:
    name, patches = _entry(obj, _TARGET_KEYS, scene, where, field)
    quantity = obj.get("quantity", "irradiance_lux")
    if quantity not in QUANTITIES:
        raise SpecError(f"{where}: {field}.quantity: unknown quantity {quantity!r}; expected one of "
                        + ", ".join(QUANTITIES))
    lo = _number(obj, "min", where, field)
    hi = _number(obj, "max", where, field)
    mean = _number(obj, "mean", where, field)
    u = _number(obj, "uniformity", where, field, high=1.0, open_low=True)
    if lo is not None and hi is not None and lo > hi:
        raise SpecError(f"{where}: {field}.min: {lo:g} is above {field}.max {hi:g}")
    return Target(name, patches, quantity, lo, hi, mean, u)
