"""Radiance scene description (``.rad``) reader.

A Radiance file is a list of primitives ``modifier type identifier``
followed by three argument lists (strings, integers, reals), each opened by
its count. hfrad reads what a Lambertian radiosity can represent and says
what it did with the rest:

========================  ==========================================================================
``polygon``               triangles (concave outlines and seamed holes by ear clipping)
``plastic``, ``metal``    reflectance = colour x (1 - specularity), the diffuse part; a specular
                          part is listed in the warnings as dropped (absorbed)
``trans``                 reflectance = colour x (1 - spec) x (1 - trans), transmittance =
                          colour x (1 - spec) x trans (a window; the specular part reported)
``glass``                 a window: transmittance and reflectance of a pane at normal incidence
                          (refractive index 1.52 unless given), from the transmissivity as
                          Radiance defines it
``light``, ``glow``       emitted exitance = pi x radiance x 179 / 683 (W/m^2), reflectance 0
                          (Radiance's light sources do not reflect); ``glow``'s radius is not used
``alias``                the same material under another name
patterns, textures        ignored (the material's own colour is used), listed in the warnings
``mirror`` and other      refused with the line: a specular or data-driven material has no
specular materials        Lambertian equivalent
``sphere``, ``ring``, ..  refused with the line (hfrad reads polygons)
``source``                skipped, listed (a distant source: sky and sun are the daylight work)
``!genbox``, ``!xform``   run by Radiance's own tools without a shell (:mod:`hfrad.scene.radcmd`)
========================  ==========================================================================

Modifiers are resolved in file order as Radiance does (a name means its
latest definition); ``void`` ends a chain. Counts are checked before their
arguments are read (:data:`MAX_ARGUMENTS`, :data:`MAX_PRIMITIVES`). Every error
names the file and line, and, for text an inline command produced, that command's line.
The model is Z-up; it is turned to y-up (:func:`hfrad.scene.polygons.z_up_to_y_up`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from ..errors import SceneError
from ..validation import clip_token
from .obj import _lines
from .polygons import Z_UP_NOTE, triangulate_polygon, z_up_to_y_up
from .radcmd import run_command

__all__ = ["read_rad", "MAX_ARGUMENTS", "MAX_PRIMITIVES"]

#: Most arguments in one list of one primitive (a polygon of 100,000 corners).
MAX_ARGUMENTS = 300_000

#: Most primitives in one model, inline commands' output included.
MAX_PRIMITIVES = 5_000_000

#: Deepest nesting of ``!xform`` files.
MAX_DEPTH = 8

#: Radiance's luminous efficacy of its white "watt" (lm/W) against hfrad's 683 lm/W (lux = 683 x Rec. 709
#: luminance of the irradiance): a Radiance radiance L is hfrad's L x 179 / 683, so both give the same lux.
RADIANCE_EFFICACY = 179.0
HFRAD_EFFICACY = 683.0

#: Refractive index of Radiance's ``glass`` when not given.
GLASS_INDEX = 1.52

SURFACES = {"polygon"}
REFUSED_SURFACES = {"sphere", "bubble", "cone", "cup", "cylinder", "tube", "ring", "mesh", "instance"}
MATERIALS = {"plastic", "metal", "trans", "glass", "light", "glow"}
REFUSED_MATERIALS = {
    "mirror": "a perfect mirror", "mist": "a participating medium", "dielectric": "a refracting dielectric",
    "interface": "a refracting interface", "prism1": "a prism", "prism2": "a prism",
    "plasfunc": "a BRDF function", "metfunc": "a BRDF function", "transfunc": "a BRDF function",
    "BRTDfunc": "a BRDF function", "plasdata": "measured BRDF data", "metdata": "measured BRDF data",
    "transdata": "measured BRDF data", "ashik2": "an anisotropic specular model", "WGMDfunc": "a BRDF function",
    "BSDF": "a BSDF file", "aBSDF": "a BSDF file", "antimatter": "antimatter (constructive solid geometry)",
    "spotlight": "a directional source (use light, or luminaires with hfrad lux)",
    "illum": "a secondary source (mkillum's output)", "mixfunc": "a mixture of materials",
    "mixdata": "a mixture of materials", "mixpict": "a mixture of materials", "mixtext": "a mixture of materials",
}
PATTERNS = {"texfunc", "texdata", "colorfunc", "brightfunc", "colordata", "brightdata", "colorpict",
            "colortext", "brighttext", "specfunc", "specdata", "specpict"}
REAL_COUNTS = {"plastic": (5,), "metal": (5,), "trans": (7,), "glass": (3, 4), "light": (3,), "glow": (4,)}


@dataclass
class Primitive:
    modifier: str
    kind: str
    name: str
    strings: list[str]
    reals: list[float]
    where: str

    def text(self) -> str:
        """The primitive as Radiance text (full float precision)."""
        if self.kind == "alias":
            return f"{self.modifier} alias {self.name} {self.strings[0]}\n"
        return (f"{self.modifier} {self.kind} {self.name}\n{len(self.strings)} {' '.join(self.strings)}\n0\n"
                f"{len(self.reals)} {' '.join(repr(x) for x in self.reals)}\n")


def _words(lines, where_of) -> Iterator[tuple[str, str]]:
    """(word, where) of Radiance text given as (number, line) pairs, ``#`` comments dropped; an inline
    command line is one word starting with ``!``. ``where_of(number)`` is the place for messages."""
    pending = ""
    for number, raw in lines:
        line = pending + raw.rstrip("\r\n")
        if line.strip().startswith("!") and line.endswith("\\"):
            pending = line[:-1] + " "  # a command continued on the next line
            continue
        pending = ""
        where = where_of(number)
        stripped = line.strip()
        if stripped.startswith("!"):
            yield stripped, where
            continue
        for word in line.split():
            if word.startswith("#"):
                break
            yield word, where


class _Reader:
    """Primitives of a Radiance file, inline commands expanded in place."""

    def __init__(self, root: Path) -> None:
        self.folder = root.parent
        self.count = 0

    def file(self, path: Path, depth: int = 0, suffix: str = "") -> list[Primitive]:
        return self._parse(_words(_lines(path), lambda n: f"{path}:{n}{suffix}"), path, depth)

    def _nested(self, depth: int):
        def read(path: Path, where: str) -> str:
            if depth + 1 > MAX_DEPTH:
                raise SceneError(f"{where.split(' (read by')[0]}: xform files nested more than {MAX_DEPTH} deep "
                                 f"(does {path.name} include itself?)")
            return "".join(p.text() for p in self.file(path, depth + 1, f" (read by {where})"))
        return read

    def _parse(self, words: Iterator[tuple[str, str]], path: Path, depth: int) -> list[Primitive]:
        out: list[Primitive] = []
        for word, where in words:
            if word.startswith("!"):
                text = run_command(word[1:].strip(), self.folder, where, self._nested(depth))
                command = clip_token(word, 60)
                out += self._parse(_words(enumerate(text.splitlines(), 1),
                                          lambda n: f"{where} (line {n} of the output of {command})"), path, depth)
                continue
            out.append(self._primitive(word, words, where))
            self.count += 1
            if self.count > MAX_PRIMITIVES:
                raise SceneError(f"{where}: more than {MAX_PRIMITIVES:,} primitives; hfrad reads at most that many")
        return out

    def _primitive(self, modifier: str, words, where: str) -> Primitive:
        head = [next(words, (None, where)) for _ in range(2)]
        if head[1][0] is None:
            raise SceneError(f"{where}: incomplete primitive after {clip_token(modifier)}")
        kind, name = head[0][0], head[1][0]
        _check_kind(kind, head[0][1])
        if kind == "alias":  # 'mod alias new old': no argument lists
            old = next(words, (None, where))[0]
            if old is None:
                raise SceneError(f"{where}: alias {clip_token(name)} names no material")
            return Primitive(modifier, kind, name, [old], [], where)
        strings = self._list(words, where, kind, "string")
        ints = self._list(words, where, kind, "integer")
        if ints:
            raise SceneError(f"{where}: {kind} {clip_token(name)}: integer arguments are not used by Radiance's "
                             f"primitives, got {len(ints)}")
        reals = [self._real(w, where, kind) for w in self._list(words, where, kind, "real")]
        return Primitive(modifier, kind, name, strings, reals, where)

    @staticmethod
    def _list(words, where: str, kind: str, what: str) -> list[str]:
        word, at = next(words, (None, where))
        try:
            count = int(word)
        except (TypeError, ValueError):
            raise SceneError(f"{at}: {kind}: expected the number of {what} arguments, got "
                             f"{clip_token(str(word)) if word is not None else 'the end of the file'}") from None
        if not 0 <= count <= MAX_ARGUMENTS:
            raise SceneError(f"{at}: {kind}: {count:,} {what} arguments; hfrad reads 0 to {MAX_ARGUMENTS:,}")
        values = []
        for _ in range(count):
            value, at = next(words, (None, at))
            if value is None:
                raise SceneError(f"{at}: {kind}: the file ends inside its {count} {what} arguments")
            values.append(value)
        return values

    @staticmethod
    def _real(word: str, where: str, kind: str) -> float:
        try:
            value = float(word)
        except ValueError:
            raise SceneError(f"{where}: {kind}: expected a number, got {clip_token(word)}") from None
        if not math.isfinite(value):
            raise SceneError(f"{where}: {kind}: non-finite number {clip_token(word)}")
        return value


def _check_kind(kind: str, where: str) -> None:
    """Refuse a primitive type hfrad cannot represent, at its own line, before reading its arguments."""
    if kind in REFUSED_MATERIALS:
        raise SceneError(f"{where}: material type {kind} ({REFUSED_MATERIALS[kind]}) is not supported: "
                         "hfrad's radiosity is Lambertian. Replace it by plastic with the diffuse reflectance wanted")
    if kind in REFUSED_SURFACES:
        raise SceneError(f"{where}: surface type {kind} is not supported (hfrad reads polygons): convert it to "
                         "polygons (e.g. genrev/gensurf, or export the model as polygons)")
    if not (kind in SURFACES or kind in MATERIALS or kind in PATTERNS or kind in ("alias", "source")):
        raise SceneError(f"{where}: unknown primitive type {clip_token(kind)}")


def _glass(tn: np.ndarray, index: float) -> tuple[np.ndarray, np.ndarray]:
    """(reflectance, transmittance) of a pane at normal incidence from Radiance's transmissivity ``tn``.

    One surface reflects ``r = ((n - 1) / (n + 1))^2``; with the light bouncing
    between the two surfaces, ``T = tn (1 - r)^2 / (1 - r^2 tn^2)`` and
    ``R = r + r (1 - r)^2 tn^2 / (1 - r^2 tn^2)`` (clear glass, tn = 0.96: T = 0.88).
    """
    r = ((index - 1.0) / (index + 1.0)) ** 2
    d = 1.0 - r * r * tn * tn
    return r + r * (1 - r) ** 2 * tn * tn / d, tn * (1 - r) ** 2 / d


def _material(p: Primitive, notes: list[str]) -> dict:
    """hfrad material properties of a Radiance material primitive (see the module's table)."""
    props = _material_values(p, notes)
    return {k: (v if k == "where" else tuple(float(x) for x in v)) for k, v in props.items()}


def _material_values(p: Primitive, notes: list[str]) -> dict:
    counts = REAL_COUNTS[p.kind]
    if len(p.reals) not in counts:
        raise SceneError(f"{p.where}: {p.kind} {clip_token(p.name)} needs {' or '.join(map(str, counts))} real "
                         f"arguments, got {len(p.reals)}")
    rgb = np.array(p.reals[:3], dtype=np.float64)
    if (rgb < 0).any():
        raise SceneError(f"{p.where}: {p.kind} {clip_token(p.name)}: negative colour {tuple(rgb.tolist())}")
    props = {"where": p.where, "reflectance": (0.0, 0.0, 0.0)}
    if p.kind in ("light", "glow"):
        props["emission"] = tuple(math.pi * rgb * (RADIANCE_EFFICACY / HFRAD_EFFICACY))
        return props
    if p.kind == "glass":
        rho, tau = _glass(np.minimum(rgb, 1.0), p.reals[3] if len(p.reals) == 4 else GLASS_INDEX)
        props.update(reflectance=tuple(rho), transmittance=tuple(tau))
        return props
    spec = p.reals[3]
    if not 0 <= spec <= 1:
        raise SceneError(f"{p.where}: {p.kind} {clip_token(p.name)}: specularity {spec:g} outside [0, 1]")
    diffuse = rgb * (1.0 - spec)
    if p.kind == "trans":
        share = p.reals[5]
        if not 0 <= share <= 1:
            raise SceneError(f"{p.where}: trans {clip_token(p.name)}: transmitted share {share:g} outside [0, 1]")
        props["transmittance"] = tuple(diffuse * share)
        diffuse = diffuse * (1.0 - share)
    if spec > 0:
        lost = rgb * spec if p.kind == "metal" else np.full(3, spec)
        notes.append(f"{p.where}: {p.kind} {p.name}: the specular part ({', '.join(f'{x:.3g}' for x in lost)}) is "
                     "dropped (absorbed); the diffuse part is the reflectance")
    props["reflectance"] = tuple(diffuse)
    return props


class _Modifiers:
    """Radiance's modifier table in file order: materials, aliases, patterns."""

    def __init__(self, notes: list[str]) -> None:
        self.table: dict[str, Primitive] = {}
        self.notes = notes
        self.materials: dict[str, dict] = {}   # hfrad name -> properties
        self.hfrad_name: dict[int, str] = {}   # id(primitive) -> hfrad material name

    def define(self, p: Primitive) -> None:
        if p.modifier != "void" and p.modifier not in self.table:
            raise SceneError(f"{p.where}: {p.kind} {clip_token(p.name)} is modified by {clip_token(p.modifier)}, "
                             "which is not defined above it")
        if p.kind == "alias" and p.strings[0] not in self.table:
            raise SceneError(f"{p.where}: alias {clip_token(p.name)} of {clip_token(p.strings[0])}, which is not "
                             "defined above it")
        self.table[p.name] = p

    def material(self, modifier: str, where: str) -> str:
        """The hfrad material name for a surface's modifier, resolving aliases and patterns."""
        seen = 0
        p = self.table.get(modifier)
        while p is not None and p.kind == "alias" and seen < 100:
            p, seen = self.table.get(p.strings[0]), seen + 1
        if p is None:
            raise SceneError(f"{where}: modifier {clip_token(modifier)} is not defined above this surface")
        if p.kind not in MATERIALS:
            raise SceneError(f"{where}: modifier {clip_token(modifier)} is a {p.kind} (defined at {p.where}), "
                             "not a material")
        key = id(p)
        if key not in self.hfrad_name:
            self.hfrad_name[key] = self._add(p)
        return self.hfrad_name[key]

    def _add(self, p: Primitive) -> str:
        """The hfrad name of a newly used material: its own, or ``name~k`` when redefined differently
        (Radiance's latest definition wins for the surfaces after it; hfrad keeps both)."""
        props = _material(p, self.notes)
        same = {k: v for k, v in props.items() if k != "where"}
        for k in range(len(self.materials) + 1):
            name = p.name if k == 0 else f"{p.name}~{k}"
            if name not in self.materials:
                break
            if {a: b for a, b in self.materials[name].items() if a != "where"} == same:
                return name  # the same material defined again (an xform'd file read twice)
        if name != p.name:
            self.notes.append(f"{p.where}: material {p.name} redefined with other values; its surfaces from "
                              f"here on use the material '{name}'")
        self.materials[name] = props
        self._patterns(p)
        return name

    def _patterns(self, p: Primitive) -> None:
        chain, mod = [], p.modifier
        while mod != "void" and len(chain) < 100:
            q = self.table[mod]
            chain.append(f"{q.kind} {q.name}")
            mod = q.modifier
        if chain:
            self.notes.append(f"{p.where}: material {p.name}: modifier(s) {', '.join(chain)} ignored (patterns and "
                              "textures are not evaluated; the material's own colour is used)")


def read_rad(path: Path) -> dict:
    """Parse a Radiance scene file into the loader's plain dict (as :func:`hfrad.scene.obj.read_obj`).

    Returns
    -------
    dict
        ``vertices`` (v, 3) y-up metres-as-given, ``faces`` (n, 3), ``face_material``,
        ``material_names``, ``materials`` (name -> reflectance, emission,
        transmittance, where), ``face_group`` / ``group_names`` (a polygon's
        identifier up to its first ``.``: genbox's sides share their box's
        name), ``warnings`` (what was dropped or assumed).

    Raises
    ------
    SceneError
        Unsupported or malformed primitives, undefined modifiers, refused
        inline commands (file and line in each message).
    """
    path = Path(path)
    notes: list[str] = []
    prims = _Reader(path).file(path)
    mods = _Modifiers(notes)
    vertices, faces, face_material, face_group = [], [], [], []
    names: list[str] = []
    groups: dict[str, int] = {}
    skipped: dict[str, int] = {}
    nv = 0
    for p in prims:
        if p.kind in SURFACES:
            if len(p.reals) < 9 or len(p.reals) % 3:
                raise SceneError(f"{p.where}: polygon {clip_token(p.name)} needs 3 numbers per corner and at least "
                                 f"3 corners, got {len(p.reals)} numbers")
            mat = mods.material(p.modifier, p.where)
            if mat not in names:
                names.append(mat)
            corners = np.array(p.reals).reshape(-1, 3)
            tri = triangulate_polygon(corners)
            vertices.append(corners)
            faces.append(tri + nv)
            nv += len(corners)
            face_material += [names.index(mat)] * len(tri)
            face_group += [groups.setdefault(p.name.split(".")[0] or "default", len(groups))] * len(tri)
        elif p.kind == "source":
            skipped["source"] = skipped.get("source", 0) + 1
        else:  # materials, patterns, aliases (the reader refused every other type)
            mods.define(p)
    if not faces:
        raise SceneError(f"{path}: no polygons found (is this a Radiance scene file?)")
    if skipped:
        notes.append(f"{skipped['source']} distant source(s) (sky, sun) skipped: hfrad has no sky yet")
    notes.append(Z_UP_NOTE)
    return {
        "vertices": z_up_to_y_up(np.vstack(vertices)),
        "faces": np.vstack(faces).astype(np.int64),
        "face_material": np.array(face_material, dtype=np.int64),
        "material_names": names,
        "materials": mods.materials,
        "face_group": np.array(face_group, dtype=np.int64),
        "group_names": list(groups),
        "missing_mtl": [],
        "missing_materials": [],
        "warnings": notes,
    }
