"""Luminaires placed in a scene: a photometric distribution, a position, an aim and a rotation.

A :class:`Luminaire` puts a :class:`~hfrad.lighting.photometry.Photometry` in
the scene's frame. Its local frame (see :mod:`hfrad.lighting.photometry`) has
``-z`` (the nadir, gamma = 0) along ``aim`` and ``+x`` (C0) along the
projection of the world's ``+x`` onto the plane normal to the aim (world
``+z`` when the aim is along x), turned by ``rotation`` degrees: a
right-handed turn about the local ``+z`` (``-aim``), so 90 puts C0 where C90
was.

A layout file (JSON, or TOML by the ``.toml`` extension) places many::

    {
      "defaults": {"photometry": "downlight.ies", "aim": [0, -1, 0], "max": 1.0},
      "luminaires": [
        {"name": "L1", "position": [1.0, 2.79, 1.25]},
        {"name": "L2", "position": [3.0, 2.79, 1.25], "rotation": 90, "dimming": 0.8,
         "color": [1.0, 0.95, 0.85], "photometry": "panel.ldt"}
      ]
    }

Photometric paths are relative to the layout file. ``dimming`` (default 1)
scales the intensities; ``max`` (default 1) is the largest dimming ``hfrad
design`` may choose; ``color`` is the relative RGB of the light, normalised to
luminance 1 so that dimming and photometry alone set the lux.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from ..errors import InputError
from ..jsonfile import read_document
from .limits import check_area_points
from .photometry import Photometry, read_photometry

__all__ = ["Luminaire", "read_layout", "parse_layout", "LayoutError"]

#: Rec. 709 luminance weights (as render/tonemap's LUMINANCE_WEIGHTS; repeated here to keep the
#: luminaire free of the renderer: checked equal in tests/test_lighting.py)
_Y = np.array([0.2126, 0.7152, 0.0722])


class LayoutError(InputError):
    """A layout file or entry is malformed; the message names the field (``luminaires[2].aim``)."""


def _show(v) -> str:
    r = repr(v)
    return r if len(r) <= 80 else r[:77] + "..."


def _three(v, what: str) -> np.ndarray:
    """(3,) float from three real numbers (not strings, booleans or objects); LayoutError naming ``what``."""
    items = list(v) if isinstance(v, (list, tuple, np.ndarray)) else None
    if items is None or len(items) != 3 or not all(
            isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, (bool, np.bool_))
            for x in items):
        raise LayoutError(f"{what}: expected three finite numbers, got {_show(v)}")
    a = np.array([float(x) for x in items])
    if not np.isfinite(a).all():
        raise LayoutError(f"{what}: expected three finite numbers, got {_show(v)}")
    return a


def _unit(v, what: str) -> np.ndarray:
    a = _three(v, what)
    if np.linalg.norm(a) == 0:
        raise LayoutError(f"{what}: expected three finite numbers, not all zero, got {v!r}")
    return a / np.linalg.norm(a)


@dataclass(frozen=True, eq=False)
class Luminaire:
    """One luminaire in the scene.

    Parameters
    ----------
    photometry : Photometry
    position : (3,) float, metres
        Centre of the luminous opening.
    aim : (3,) float
        Direction of the nadir (gamma = 0) in the scene; default straight down
        along ``-y`` (hfrad's scenes are y-up).
    rotation : float, degrees
        Turn of C0 about the aim.
    dimming : float >= 0
        Factor on every intensity.
    color : (3,) float >= 0
        Relative RGB; stored normalised to luminance 1.
    name : str
    max : float >= 0
        Largest dimming a design may choose.
    """

    photometry: Photometry
    position: np.ndarray
    aim: np.ndarray = field(default_factory=lambda: np.array([0.0, -1.0, 0.0]))
    rotation: float = 0.0
    dimming: float = 1.0
    color: np.ndarray = field(default_factory=lambda: np.ones(3))
    name: str = "luminaire"
    max: float = 1.0

    def __post_init__(self) -> None:
        pos = _three(self.position, f"luminaire {self.name!r}: position")
        object.__setattr__(self, "position", pos)
        object.__setattr__(self, "aim", _unit(self.aim, f"luminaire {self.name!r}: aim"))
        for key in ("rotation", "dimming", "max"):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) \
                    or (key != "rotation" and v < 0):
                raise LayoutError(f"luminaire {self.name!r}: {key} must be a finite number"
                                  + (" >= 0" if key != "rotation" else "") + f", got {v!r}")
            object.__setattr__(self, key, float(v))
        c = _three(self.color, f"luminaire {self.name!r}: color")
        if (c < 0).any() or not float(c @ _Y) > 0:
            raise LayoutError(f"luminaire {self.name!r}: color must be three numbers >= 0 with a non-zero "
                              f"luminance, got {self.color!r}")
        object.__setattr__(self, "color", c / float(c @ _Y))

    @property
    def frame(self) -> np.ndarray:
        """(3, 3) columns: the luminaire's local x (C0), y (C90) and z (up, -aim) in scene coordinates."""
        z = -self.aim
        ref = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 0.0, 1.0])
        x = ref - (ref @ z) * z
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        a = math.radians(self.rotation)
        x, y = math.cos(a) * x + math.sin(a) * y, -math.sin(a) * x + math.cos(a) * y
        return np.stack([x, y, z], axis=1)

    def intensity(self, directions: np.ndarray) -> np.ndarray:
        """(...,) cd towards unit scene ``directions`` (..., 3) at dimming 1."""
        return self.photometry.intensity(np.asarray(directions, np.float64) @ self.frame)

    @property
    def size(self) -> float:
        """Largest dimension of the luminous opening, metres (0 for a point source)."""
        length, width, height = (abs(x) for x in self.photometry.size)
        return float(max(length, width, height))

    def emission_points(self, spacing: float) -> tuple[np.ndarray, np.ndarray]:
        """Points spread over the luminous opening, about ``spacing`` apart, and their shares of the intensity.

        A rectangle length x width (C0 x C90): the centres of an even grid of
        cells. A disk (a negative length or width, as LM-63 marks round
        openings; or a length with zero width, as EULUMDAT does) of diameter
        the larger of |length| and |width|: equal-width rings, each cut into
        cells about ``spacing`` long, a point at each cell's centre of area,
        weighted by the cell's area. A point source: its centre.

        Returns
        -------
        points : (k, 3) float, scene coordinates
        weights : (k,) float, summing to 1
        """
        length, width, _ = self.photometry.size
        check_area_points(self.name, length, width, spacing)
        frame = self.frame
        if length < 0 or width < 0 or (width == 0 and length > 0):
            r = 0.5 * max(abs(length), abs(width))
            rings = max(1, int(math.ceil(r / spacing)))
            local, weights = [], []
            for j in range(rings):
                r0, r1 = r * j / rings, r * (j + 1) / rings
                mid = math.sqrt(0.5 * (r0 * r0 + r1 * r1))
                count = 1 if j == 0 and rings == 1 else max(3, int(round(2 * math.pi * mid / spacing)))
                a = (np.arange(count) + 0.5) * 2 * math.pi / count
                local.append(np.column_stack([mid * np.cos(a), mid * np.sin(a)]) if count > 1 else np.zeros((1, 2)))
                weights.append(np.full(count, (r1 * r1 - r0 * r0) / (r * r) / count))
            local, weights = np.vstack(local), np.concatenate(weights)
        elif length > 0 or width > 0:
            nx = max(1, int(math.ceil(length / spacing)))
            ny = max(1, int(math.ceil(width / spacing)))
            ux = ((np.arange(nx) + 0.5) / nx - 0.5) * length
            uy = ((np.arange(ny) + 0.5) / ny - 0.5) * width
            X, Y = np.meshgrid(ux, uy, indexing="ij")
            local = np.stack([X.ravel(), Y.ravel()], axis=1)
            weights = np.full(len(local), 1.0 / len(local))
        else:
            local, weights = np.zeros((1, 2)), np.ones(1)
        return self.position + local @ frame[:, :2].T, weights

    @property
    def watts(self) -> float:
        """Input watts at full output (from the photometric file; 0 when it does not say)."""
        return float(self.photometry.watts)

    def replace(self, **changes) -> "Luminaire":
        values = {k: getattr(self, k) for k in ("photometry", "position", "aim", "rotation", "dimming",
                                                 "color", "name", "max")}
        values.update(changes)
        return Luminaire(**values)


_KEYS = {"name", "photometry", "position", "aim", "rotation", "dimming", "color", "max"}


def parse_layout(layout: Mapping[str, Any], *, base: "str | Path" = ".", where: str = "layout") -> list[Luminaire]:
    """Luminaires of a layout (the structure of the module docstring), photometry read from ``base``.

    Raises
    ------
    LayoutError
        Names the field: unknown key, missing photometry or position, bad
        vector or number, duplicate name.
    FileNotFoundError, FileFormatError
        A photometric file is missing or unreadable.
    """
    if not isinstance(layout, Mapping):
        raise LayoutError(f"{where}: expected an object with 'luminaires', got {type(layout).__name__}")
    unknown = set(layout) - {"luminaires", "defaults", "description"}
    if unknown:
        raise LayoutError(f"{where}: {sorted(unknown)[0]}: unknown key; expected luminaires, defaults, description")
    defaults = layout.get("defaults", {})
    if not isinstance(defaults, Mapping) or set(defaults) - _KEYS:
        raise LayoutError(f"{where}: defaults: expected an object with keys among {', '.join(sorted(_KEYS))}")
    items = layout.get("luminaires")
    if not isinstance(items, list) or not items:
        raise LayoutError(f"{where}: luminaires: expected a non-empty list, got {items!r}")
    cache: dict[Path, Photometry] = {}
    out, names = [], set()
    for i, item in enumerate(items):
        field_ = f"{where}: luminaires[{i}]"
        if not isinstance(item, Mapping):
            raise LayoutError(f"{field_}: expected an object, got {item!r}")
        bad = set(item) - _KEYS
        if bad:
            raise LayoutError(f"{field_}.{sorted(bad)[0]}: unknown key; expected one of {', '.join(sorted(_KEYS))}")
        entry = {**defaults, **item}
        for key in ("photometry", "position"):
            if key not in entry:
                raise LayoutError(f"{field_}: no {key} (give it here or in defaults)")
        ph = entry["photometry"]
        if isinstance(ph, Photometry):
            photometry = ph
        else:
            path = Path(base) / str(ph)
            if path not in cache:
                cache[path] = read_photometry(path)
            photometry = cache[path]
        name = str(entry.get("name", f"L{i + 1}"))
        if name in names:
            raise LayoutError(f"{field_}.name: {name!r} is used twice; names must be unique")
        names.add(name)
        kw = {k: entry[k] for k in ("aim", "rotation", "dimming", "color", "max") if k in entry}
        try:
            out.append(Luminaire(photometry, entry["position"], name=name, **kw))
        except LayoutError as exc:
            raise LayoutError(f"{field_}: {exc}") from None
    return out


def read_layout(path: "str | Path") -> list[Luminaire]:
    """Luminaires of a layout file (.json or .toml); photometric paths relative to the file.

    Raises
    ------
    FileNotFoundError
    LayoutError
        Not valid JSON/TOML, or a malformed entry (names the field).
    """
    path = Path(path)
    data = read_document(path, what="layout", error=LayoutError)
    return parse_layout(data, base=path.parent, where=str(path))
