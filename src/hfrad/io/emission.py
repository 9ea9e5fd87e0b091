"""Emission files: the exitance of named materials or groups, as JSON.

Written by ``hfrad view`` (button "save emission") and read by
``hfrad solve --emission-file`` and ``hfrad render --emission-file``::

    {
      "format": "hfrad-emission",
      "version": 1,
      "emitters": [
        {"name": "light", "exitance": [17.0, 12.0, 4.0]},
        {"name": "lamp",  "exitance": [5.0, 5.0, 5.0], "on": false}
      ]
    }

Fields of an emitter:

- ``name`` (string, required): a material, else a group, of the scene (the
  names ``hfrad info`` lists and ``--emission NAME=R,G,B`` takes).
- ``exitance`` (three numbers >= 0, required): emitted exitance in W/m^2 per
  RGB channel, the same on every patch of that material or group.
- ``on`` (true/false, optional, default true): false emits nothing but keeps
  the exitance, so a viewer can switch the light back on.

Emitters are applied in order, like repeated ``--emission`` options: a later
entry wins on patches two names share; materials and groups not listed keep
the scene's own emission. Unknown fields are refused, so a misspelt field
does not silently do nothing.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from pathlib import Path
from typing import Sequence

from ..jsonfile import loads_json
from ..errors import FileFormatError
from ..validation import MAX_EXITANCE, clip_token

#: Longest emitter name accepted (material and group names are short; a longer one is a broken file).
MAX_NAME = 1000

#: The ``format`` field of an emission file.
FORMAT = "hfrad-emission"
#: The ``version`` field written; files of a higher version are refused.
VERSION = 1
_TOP_FIELDS = ("format", "version", "emitters")
_EMITTER_FIELDS = ("name", "exitance", "on")


@dataclasses.dataclass(frozen=True)
class EmitterSetting:
    """One light of an emission file.

    Attributes
    ----------
    name : str
        Material (looked up first) or group of the scene.
    exitance : (3,) float >= 0, W/m^2
    on : bool
        When False the emitter emits nothing (its exitance is kept).
    """

    name: str
    exitance: tuple[float, float, float]
    on: bool = True

    @property
    def emitted(self) -> tuple[float, float, float]:
        """(3,) float, W/m^2: ``exitance`` when on, else zeros."""
        return self.exitance if self.on else (0.0, 0.0, 0.0)


def _fail(path, where: str, message: str) -> FileFormatError:
    return FileFormatError(f"{path}: {where}: {message}")


def _exitance(path, where: str, value) -> tuple[float, float, float]:
    ok = (isinstance(value, list) and len(value) == 3
          and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in value)
          and all(_finite(x) and x >= 0 for x in value))
    if not ok:
        raise _fail(path, where, f"expected three finite numbers >= 0 (R, G, B in W/m^2), got {_quote(value)}")
    out = tuple(float(x) for x in value)
    if max(out) > MAX_EXITANCE:
        raise _fail(path, where, f"{max(out):g} W/m^2 is above the largest exitance hfrad computes with, "
                                 f"{MAX_EXITANCE:g} W/m^2 (radiosity is stored in float32 and would overflow)")
    return out


def _field(name: str) -> str:
    """A field name for an error line, cut to about 200 characters."""
    return name if len(name) <= 200 else f"{name[:200]}... ({len(name):,} characters)"


def _finite(x) -> bool:
    """A JSON number that is a finite float (an integer of 400 digits is not: float() overflows)."""
    try:
        return math.isfinite(float(x))
    except OverflowError:
        return False


def _quote(value) -> str:
    """A JSON value for an error line, at most about 200 characters of it."""
    try:
        text = json.dumps(value)
    except (TypeError, ValueError, RecursionError):
        text = type(value).__name__
    return clip_token(text)


def parse_emission(data, path: "str | os.PathLike" = "<emission>") -> list[EmitterSetting]:
    """Validate the decoded JSON of an emission file.

    Parameters
    ----------
    data : object
        What ``json.load`` returned.
    path : str or PathLike
        Named in error messages.

    Returns
    -------
    list of EmitterSetting, in file order

    Raises
    ------
    FileFormatError
        Naming the file and the bad field, e.g.
        ``light.json: emitters[1].exitance: expected three finite numbers >= 0 ...``.
    """
    if not isinstance(data, dict):
        raise _fail(path, "top level", f"expected a JSON object with 'format', 'version' and 'emitters', "
                                       f"got {type(data).__name__}")
    unknown = sorted(set(data) - set(_TOP_FIELDS))
    if unknown:
        raise _fail(path, _field(unknown[0]), f"unknown field; allowed: {', '.join(_TOP_FIELDS)}")
    if data.get("format") != FORMAT:
        raise _fail(path, "format", f"expected {FORMAT!r}, got {_quote(data.get('format'))}")
    version = data.get("version")
    if version != VERSION:
        raise _fail(path, "version", f"expected {VERSION} (this hfrad reads version {VERSION}), got {_quote(version)}")
    emitters = data.get("emitters")
    if not isinstance(emitters, list):
        raise _fail(path, "emitters", f"expected a list of {{\"name\": ..., \"exitance\": [R, G, B]}}, "
                                      f"got {_quote(emitters)}")
    out = []
    for i, item in enumerate(emitters):
        where = f"emitters[{i}]"
        if not isinstance(item, dict):
            raise _fail(path, where, f"expected an object with 'name' and 'exitance', got {_quote(item)}")
        unknown = sorted(set(item) - set(_EMITTER_FIELDS))
        if unknown:
            raise _fail(path, f"{where}.{_field(unknown[0])}",
                        f"unknown field; allowed: {', '.join(_EMITTER_FIELDS)}")
        name = item.get("name")
        if not isinstance(name, str) or not name or len(name) > MAX_NAME:
            raise _fail(path, f"{where}.name", f"expected a material or group name (at most {MAX_NAME} "
                                               f"characters), got {_quote(name)}")
        if "exitance" not in item:
            raise _fail(path, f"{where}.exitance", "missing (three numbers, W/m^2)")
        on = item.get("on", True)
        if not isinstance(on, bool):
            raise _fail(path, f"{where}.on", f"expected true or false, got {_quote(on)}")
        out.append(EmitterSetting(name, _exitance(path, f"{where}.exitance", item["exitance"]), on))
    return out


def read_emission(path: "str | os.PathLike") -> list[EmitterSetting]:
    """Read an emission file (see the module docstring for the format).

    Raises
    ------
    FileNotFoundError
        No such file.
    FileFormatError
        Not JSON (with line and column) or a bad field (named).
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: no such emission file") from None
    except UnicodeDecodeError:
        raise FileFormatError(f"{path}: not a UTF-8 JSON emission file") from None
    return loads_emission(text, path)


def loads_emission(text: str, source: "str | os.PathLike" = "<emission>") -> list[EmitterSetting]:
    """Parse the text of an emission file; ``source`` is named in errors (see :func:`read_emission`)."""
    try:
        data = loads_json(text)   # RecursionError of a deeply nested file -> JSONDecodeError
    except json.JSONDecodeError as exc:
        raise FileFormatError(f"{source}: not valid JSON: {exc.msg} at line {exc.lineno}, "
                              f"column {exc.colno}") from None
    return parse_emission(data, source)


def emission_overrides(settings: Sequence[EmitterSetting]) -> dict[str, tuple[float, float, float]]:
    """``{name: emitted exitance}`` in file order, for :func:`hfrad.scene.load.set_emission`."""
    out: dict[str, tuple[float, float, float]] = {}
    for s in settings:
        out.pop(s.name, None)  # a repeated name moves to its last position, where it wins
        out[s.name] = s.emitted
    return out


def emission_json(settings: Sequence[EmitterSetting]) -> str:
    """The JSON text of an emission file (pretty-printed, newline-terminated)."""
    emitters = []
    for s in settings:
        item = {"name": s.name, "exitance": [float(x) for x in s.exitance]}
        if not s.on:
            item["on"] = False
        emitters.append(item)
    return json.dumps({"format": FORMAT, "version": VERSION, "emitters": emitters}, indent=2) + "\n"


def write_emission(path: "str | os.PathLike", settings: Sequence[EmitterSetting]) -> Path:
    """Write an emission file atomically (temporary name, then rename)."""
    from ..atomic import atomic_path

    text = emission_json(settings)
    with atomic_path(path) as tmp:
        Path(tmp).write_text(text, encoding="utf-8")
    return Path(path)
