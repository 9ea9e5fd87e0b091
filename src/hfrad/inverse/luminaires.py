"""Inverse design with catalogue luminaires: dimming levels that meet work-plane goals at least power.

A lighting spec (JSON or TOML) names a luminaire layout and the grids to light::

    {
      "luminaires": "layout.json",
      "grids": [
        {"name": "workplane", "floor": "floor", "height": 0.8, "spacing": 0.25, "margin": 0.5,
         "mean": 500, "uniformity": 0.6},
        {"name": "desks", "sensors": "desk-sensors.txt", "min": 300}
      ],
      "objective": "min_power",
      "background": "none"
    }

``luminaires`` is a layout file (:func:`hfrad.lighting.read_layout`; paths
relative to the spec) or a layout object. Each luminaire's unknown is its
dimming ``w_l`` in ``[0, max]`` (the layout's ``max``, default 1). A grid is a
work plane over a floor's outline (``floor``: its material; ``height`` above
the floor, ``spacing``, optional ``margin``), over a ``rectangle``
(``[[x0, x1], [z0, z1]]``, ``height`` absolute), over an IFC model's ``space``
(an ``IfcSpace`` name; ``height`` above its floor; the scene read from that
IFC file), or a ``sensors`` file; its
goals, in lux, are ``mean`` (EN 12464-1's maintained average, a lower bound),
``min``, ``max`` (every sensor) and ``uniformity`` (U0 = Emin / Eavg).
``background`` as for the patch spec: ``none`` (default here) or ``scene``
(the scene's emitting patches stay as a fixed part, daylight).

The illuminance of grid g is affine in the dimming, ``E_g(w) = R_g w + r_g``
(:class:`hfrad.lighting.LightingModel`: one batched solve for all L
luminaires, a stored gather operator per grid), so the goals are linear and
the same optimiser as the patch design (:mod:`hfrad.inverse.optimize`) finds
the least power ``sum_l w_l P_l`` (P_l: the luminaire's watts; a file without
watts counts its lumens at 100 lm/W).
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from ..lighting import LightingModel, SensorSet, floor_grid, grid_stats, parse_layout, read_layout, read_sensors
from ..lighting import rectangle_grid
from ..progress import ProgressCallback
from .design import _met
from .optimize import optimise
from .spec import GOALS, OBJECTIVES, DesignSpec, Emitter, SpecError, Target, read_spec
from .transfer import Response

__all__ = ["LightingSpec", "GridGoal", "LightingDesign", "parse_lighting_spec", "design_lighting",
           "is_lighting_spec"]

#: lm/W assumed for a luminaire whose file gives no input watts
DEFAULT_EFFICACY = 100.0

_TOP = {"luminaires", "grids", "objective", "background", "description"}
_GRID = {"name", "floor", "rectangle", "sensors", "space", "height", "spacing", "margin", "min", "max", "mean",
         "uniformity"}


@dataclass(frozen=True)
class GridGoal:
    """Sensors and their goals (lux; None = no such goal)."""

    sensors: SensorSet
    min: float | None = None
    max: float | None = None
    mean: float | None = None
    uniformity: float | None = None

    @property
    def name(self) -> str:
        return self.sensors.name

    def goals(self) -> dict:
        return {g: getattr(self, g) for g in GOALS if getattr(self, g) is not None}


@dataclass(frozen=True)
class LightingSpec:
    luminaires: tuple
    grids: tuple
    objective: str = "min_power"
    background: str = "none"


def is_lighting_spec(raw: Any) -> bool:
    """True for a spec that designs luminaires (it has ``luminaires``), not patch emitters."""
    return isinstance(raw, Mapping) and "luminaires" in raw


def _num(obj: Mapping, key: str, where: str, *, low=-math.inf, high=math.inf, positive=False) -> float | None:
    if key not in obj or obj[key] is None:
        return None
    v = obj[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < low or v > high \
            or (positive and v <= 0):
        rng = f"> {low:g}" if positive else f"in [{low:g}, {high:g}]"
        raise SpecError(f"{where}.{key}: expected a finite number {rng}, got {v!r}")
    return float(v)


def _grid(obj: Any, scene, base: Path, where: str) -> GridGoal:
    if not isinstance(obj, Mapping):
        raise SpecError(f"{where}: expected an object, got {obj!r}")
    bad = set(obj) - _GRID
    if bad:
        raise SpecError(f"{where}.{sorted(bad)[0]}: unknown key; expected one of {', '.join(sorted(_GRID))}")
    name = obj.get("name", where.rsplit(": ", 1)[-1])
    if not isinstance(name, str) or not name:
        raise SpecError(f"{where}.name: expected a non-empty string, got {name!r}")
    kinds = [k for k in ("floor", "rectangle", "sensors", "space") if k in obj]
    if len(kinds) != 1:
        raise SpecError(f"{where}: give exactly one of floor, rectangle, sensors or space (got {kinds or 'none'})")
    kind = kinds[0]
    lo, hi = _num(obj, "min", where, low=0.0), _num(obj, "max", where, low=0.0)
    mean, u = _num(obj, "mean", where, low=0.0), _num(obj, "uniformity", where, low=0.0, high=1.0)
    if lo is not None and hi is not None and lo > hi:
        raise SpecError(f"{where}.min: {lo:g} is above max {hi:g}")
    if lo is None and hi is None and mean is None and u is None:
        raise SpecError(f"{where}: no goal; give at least one of min, max, mean or uniformity (lux)")
    try:
        if kind == "sensors":
            sensors = read_sensors(base / str(obj["sensors"]), name=name)
        else:
            height = _num(obj, "height", where)
            spacing = _num(obj, "spacing", where, low=0.0, positive=True)
            margin = _num(obj, "margin", where, low=0.0) or 0.0
            if height is None or spacing is None:
                raise SpecError(f"{where}: a {kind} grid needs height and spacing (metres)")
            if kind == "floor":
                sensors = floor_grid(scene, height, spacing, material=str(obj["floor"]), name=name, margin=margin)
            elif kind == "space":
                sensors = _space_grid(scene, str(obj["space"]), height, spacing, margin, where)
            else:
                r = obj["rectangle"]
                ok = (isinstance(r, list) and len(r) == 2 and all(isinstance(p, list) and len(p) == 2 for p in r))
                if not ok:
                    raise SpecError(f"{where}.rectangle: expected [[x0, x1], [z0, z1]], got {r!r}")
                sensors = rectangle_grid(tuple(r[0]), tuple(r[1]), height, spacing, name=name, margin=margin)
    except SpecError:
        raise
    except (ValueError, FileNotFoundError) as exc:          # InputError, FileFormatError, missing file
        raise SpecError(f"{where}: {exc}") from None
    return GridGoal(sensors, lo, hi, mean, u)


def spec_input_files(raw: Any, base: "str | Path") -> dict:
    """The files a luminaire spec reads besides itself: its layout and sensor files, by field."""
    out: dict = {}
    if not isinstance(raw, Mapping):
        return out
    if isinstance(raw.get("luminaires"), str):
        out["the spec's luminaires"] = Path(base) / raw["luminaires"]
    for i, g in enumerate(raw.get("grids") or []):
        if isinstance(g, Mapping) and isinstance(g.get("sensors"), str):
            out[f"the spec's grids[{i}].sensors"] = Path(base) / g["sensors"]
    return out


def _space_grid(scene, space: str, height: float, spacing: float, margin: float, where: str) -> SensorSet:
    """The work plane of the IfcSpace named ``space`` of the IFC file the scene was read from."""
    from ..lighting.spaces import scene_ifc, space_grids

    path = scene_ifc(scene)
    if path is None:
        raise SpecError(f"{where}.space: the scene was not read from an IFC file that still exists "
                        f"({scene.name!r}); use floor, rectangle or sensors")
    grids = space_grids(path, height=height, spacing=spacing, margin=margin, scene=scene)
    for g in grids:
        if g.name == space:
            return g
    raise SpecError(f"{where}.space: no IfcSpace named {space!r} in {path}; its spaces: "
                    + ", ".join(g.name for g in grids))


def parse_lighting_spec(spec: "Mapping[str, Any] | str | Path", scene, *, base: "str | Path | None" = None,
                        source: str | None = None) -> LightingSpec:
    """Validate a luminaire design spec (module docstring) against ``scene``.

    Raises
    ------
    SpecError
        The first problem found, naming the field (``spec.json: grids[0].spacing: ...``).
    """
    if isinstance(spec, (str, Path)):
        base = Path(spec).parent if base is None else base
        source = source or str(spec)
        spec = read_spec(spec)
    base = Path(base or ".")
    where = source or "spec"
    if not isinstance(spec, Mapping):
        raise SpecError(f"{where}: expected an object with 'luminaires' and 'grids'")
    bad = set(spec) - _TOP
    if bad:
        raise SpecError(f"{where}: {sorted(bad)[0]}: unknown key in a luminaire spec; expected one of "
                        f"{', '.join(sorted(_TOP))} (patch emitters and luminaires are designed separately)")
    lum = spec.get("luminaires")
    try:
        if isinstance(lum, str):
            luminaires = read_layout(base / lum)
        elif isinstance(lum, Mapping):
            luminaires = parse_layout(lum, base=base, where=f"{where}: luminaires")
        else:
            raise SpecError(f"{where}: luminaires: expected a layout file name or a layout object, got {lum!r}")
    except SpecError:
        raise
    except (ValueError, FileNotFoundError) as exc:
        raise SpecError(f"{where}: luminaires: {exc}") from None
    grids = spec.get("grids")
    if not isinstance(grids, list) or not grids:
        raise SpecError(f"{where}: grids: expected a non-empty list of grids with goals, got {grids!r}")
    goals = tuple(_grid(g, scene, base, f"{where}: grids[{i}]") for i, g in enumerate(grids))
    names = [g.name for g in goals]
    dup = next((x for x in names if names.count(x) > 1), None)
    if dup is not None:
        raise SpecError(f"{where}: grids: the name {dup!r} is used twice")
    objective = spec.get("objective", "min_power")
    if objective not in OBJECTIVES:
        raise SpecError(f"{where}: objective: unknown objective {objective!r}; expected one of {', '.join(OBJECTIVES)}")
    if objective == "least_squares" and not any(g.mean is not None for g in goals):
        raise SpecError(f"{where}: objective: least_squares fits the grids' 'mean' goals, but no grid has one")
    background = spec.get("background", "none")
    if background not in ("none", "scene"):
        raise SpecError(f"{where}: background: expected none or scene, got {background!r}")
    return LightingSpec(tuple(luminaires), goals, objective, background)


@dataclass
class LightingDesign:
    """The outcome of :func:`design_lighting`: ``report`` (JSON-ready), the dimming, the model and responses."""

    report: dict
    spec: LightingSpec
    dimming: np.ndarray | None
    model: LightingModel = field(repr=False)
    responses: list = field(repr=False)

    @property
    def feasible(self) -> bool:
        return bool(self.report["feasible"])

    def illuminance(self) -> list:
        """Per grid (m_g,) lux of the design (None when infeasible)."""
        if self.dimming is None:
            return [None] * len(self.responses)
        return [r.illuminance(self.dimming) for r in self.responses]

    def to_json(self) -> str:
        return json.dumps(self.report, indent=2, allow_nan=False)


def luminaire_power(lum) -> float:
    """W at full output: the file's input watts, else its lumens at DEFAULT_EFFICACY."""
    return lum.watts if lum.watts > 0 else lum.photometry.flux() / DEFAULT_EFFICACY


def _design_spec(spec: LightingSpec) -> DesignSpec:
    """The patch-design structures the optimiser reads: one emitter per luminaire, one target per grid."""
    none = np.zeros(0, np.int64)
    emitters = tuple(Emitter(l.name, none, np.ones(3), l.max) for l in spec.luminaires)
    targets = tuple(Target(g.name, none, "irradiance_lux", g.min, g.max, g.mean, g.uniformity) for g in spec.grids)
    return DesignSpec(emitters, targets, spec.objective, spec.background)


def design_lighting(fac, spec: "LightingSpec | Mapping | str | Path", *, model: LightingModel | None = None,
                    responses: list | None = None, verify: bool = True,
                    progress: ProgressCallback = None) -> LightingDesign:
    """Dimming of every luminaire that meets the grids' goals at least power.

    Parameters
    ----------
    fac : HFactorization
        With its scene.
    spec : LightingSpec, dict, or path of a .json / .toml spec (module docstring)
    model, responses : optional
        A :class:`LightingModel` of these luminaires and its
        :class:`SensorResponse` per grid, to skip the precompute (timing
        repeated designs).
    verify : bool
        Recompute the designed lighting from scratch: one ``fac.solve`` of
        its first-bounce emission, the direct light at the sensors ray cast
        again; ``report['verified']`` compares it with the optimiser's
        superposition.
    progress : callable (done, total), optional
        Luminaires of the precompute.

    Returns
    -------
    LightingDesign
        ``report``: ``feasible``, ``status``, ``message``, ``objective``,
        ``total_power_W``, ``luminaires`` (name, catalogue name, watts, max,
        dimming, power_W), ``grids`` (name, sensors, goals, achieved average /
        minimum / maximum / U0 / Ud, met per goal), ``conflicts``,
        ``timings`` (precompute parts, ``design_s``: the optimisation and
        report after the precompute, ``relight_s``: one relighting of every
        grid), ``verified``.
    """
    t0 = time.perf_counter()
    if not isinstance(spec, LightingSpec):
        spec = parse_lighting_spec(spec, fac.scene)
    if model is None:
        model = LightingModel(fac, spec.luminaires, background=spec.background, progress=progress)
    if responses is None:
        responses = [model.sensors(g.sensors) for g in spec.grids]
    cost = np.array([luminaire_power(l) for l in spec.luminaires])
    lumens = [l.photometry.flux() for l in spec.luminaires]      # integrated once per file (cached)
    t_pre = time.perf_counter() - t0
    t1 = time.perf_counter()
    dspec = _design_spec(spec)
    L = len(spec.luminaires)
    resp = Response([r.matrix for r in responses], [r.offset for r in responses],
                    [np.full(len(r.sensors), 1.0 / len(r.sensors)) for r in responses],
                    L + int(spec.background == "scene"), t_pre, None)
    sol = optimise(dspec, resp, cost)
    w = sol.intensity
    grids_out, all_met = [], w is not None
    radiosity_error = None if w is None else model.radiosity_error(w)   # the design's figure, once
    for g, r in zip(spec.grids, responses):
        entry = {"name": g.name, "sensors": len(g.sensors), "spacing_m": g.sensors.spacing, "goals": g.goals(),
                 "achieved": None, "met": None}
        if w is not None:
            st = grid_stats(r.illuminance(w))
            entry["achieved"] = st
            lux_error = model.illuminance_error(r, radiosity_error)   # the interreflected light's figure
            entry["error_lux"] = {"maximum": float(lux_error.max()), "average": float(lux_error.mean())}
            entry["met"] = _met(dspec.targets[spec.grids.index(g)],
                                {"min": st["minimum"], "mean": st["average"], "max": st["maximum"],
                                 "uniformity": st["U0"]}, spec.objective)
            all_met &= all(entry["met"].values())
        grids_out.append(entry)
    lums_out = [{"name": l.name, "catalogue": l.photometry.name, "watts": luminaire_power(l),
                 "lumens": lumens[i], "max": l.max,
                 "dimming": None if w is None else float(w[i]),
                 "power_W": None if w is None else float(w[i] * cost[i])} for i, l in enumerate(spec.luminaires)]
    status, message = sol.status, sol.message
    if w is not None and not all_met:
        unmet = [f"{g['name']}.{k}" for g in grids_out for k, ok in g["met"].items() if not ok]
        status, message = "goals_not_met", f"best fit leaves these goals unmet: {', '.join(unmet)}"
    t_design = time.perf_counter() - t1
    relight = None
    if w is not None:
        reps, t2 = 200, time.perf_counter()
        for _ in range(reps):
            for r in responses:
                r.illuminance(w)
        relight = (time.perf_counter() - t2) / reps
    report = {
        "feasible": bool(all_met), "status": status, "message": message,
        "objective": {"name": spec.objective, "value": sol.objective,
                      "unit": "W" if spec.objective == "min_power" else "sum of squared relative residuals"},
        "total_power_W": None if w is None else float(cost @ w),
        "full_power_W": float(cost.sum()),
        "luminaires": lums_out, "grids": grids_out, "conflicts": sol.conflicts, "background": spec.background,
        **({} if w is None else {"radiosity_error": radiosity_error.as_dict()}),
        "lp_solves": int(sol.lp_solves),
        "timings": {**{k: v for k, v in model.timings.items()},
                    "gather_s": float(sum(r.seconds["gather_s"] for r in responses)),
                    "direct_sensors_s": float(sum(r.seconds["direct_s"] for r in responses)),
                    "precompute_s": t_pre, "design_s": t_design, "relight_s": relight},
        "factorization": {"n_patches": int(fac.n_patches), "rank": int(fac.rank), "eps": float(fac.eps)},
        "verified": None,
    }
    if w is not None and verify:
        report["verified"] = _verify(model, spec, responses, w)
    return LightingDesign(report, spec, w, model, responses)


def _verify(model: LightingModel, spec: LightingSpec, responses: list, w: np.ndarray) -> dict:
    """The design from scratch: one solve of its first-bounce emission, direct light ray cast again."""
    from ..lighting import direct_illuminance
    from ..render.falsecolor import LUMINOUS_EFFICACY, photometric

    t0 = time.perf_counter()
    fac, scene = model.fac, model.scene
    colours = np.array([l.color for l in spec.luminaires])
    H = model.patch_direct * w                                           # (n, L) lux
    E = np.asarray(fac.reflectance) * ((H / LUMINOUS_EFFICACY) @ colours)
    if spec.background == "scene":
        E = E + np.asarray(scene.emission)
    B = np.asarray(fac.solve(E), np.float64)
    lums = [l.replace(dimming=1.0) for l in spec.luminaires]
    deviation, out, met = 0.0, [], True
    for g, r in zip(spec.grids, responses):
        D = direct_illuminance(lums, g.sensors.points, g.sensors.normals, caster=model.caster,
                               spacing=model.spacing, near_ratio=model.near_ratio) @ w
        lux = D + photometric(r.gather.apply(B), "lux")
        pred = r.illuminance(w)
        deviation = max(deviation, float(np.abs(lux - pred).max() / max(np.abs(pred).max(), 1e-300)))
        st = grid_stats(lux)
        target = Target(g.name, np.zeros(0, np.int64), "irradiance_lux", g.min, g.max, g.mean, g.uniformity)
        ok = _met(target, {"min": st["minimum"], "mean": st["average"], "max": st["maximum"],
                           "uniformity": st["U0"]}, spec.objective)
        met &= all(ok.values())
        out.append({"name": g.name, **st, "met": ok})
    return {"method": "one fac.solve of the designed first-bounce emission; direct light at the sensors ray cast "
                      "again", "time_s": time.perf_counter() - t0, "goals_met": bool(met),
            "max_relative_deviation": deviation, "grids": out}
