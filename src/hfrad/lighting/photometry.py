"""Photometric files: IES LM-63 (1986/1991/1995/2002/2019) and EULUMDAT (.ldt) -> a candela table.

A :class:`Photometry` holds luminous intensities ``I(h, v)`` in candela over a
grid of horizontal angles ``h`` and vertical angles ``v`` (degrees), with the
file's symmetry kept (only the stored part of the web is held; a query angle is
folded into it), and answers ``intensity(directions)`` by bilinear
interpolation.

Coordinates (the luminaire's own frame; :mod:`hfrad.lighting.luminaire` places
it in a scene):

- **Type C** (IES type 1, every EULUMDAT file): ``z`` up, the nadir is ``-z``.
  The vertical angle gamma is measured from the nadir (0 = straight down, 90 =
  horizontal, 180 = straight up); the horizontal angle C from ``+x`` (C0, the
  luminaire's length axis) towards ``+y`` (C90). Direction
  ``(sin g cos C, sin g sin C, -cos g)``.
- **Type B** (IES type 2): the B-planes turn about the luminaire's ``y`` axis.
  Horizontal angle H (-90..90) turns the plane from the nadir towards ``+x``;
  vertical angle V (-90..90) leaves the plane towards ``+y``. Direction
  ``(cos V sin H, sin V, -cos V cos H)``. Directions behind (|H| > 90) get 0.

Symmetry of the stored horizontal angles (LM-63 type C): a single angle 0 is
rotationally symmetric; 0..90 is symmetric about both the C0-C180 and
C90-C270 planes; 0..180 about the C0-C180 plane; 90..270 (older files) about
the C90-C270 plane; anything ending above 180 is a full web, wrapping at 360.
Type B: 0..90 horizontal angles are symmetric in H (I(-H) = I(H)); 0..90
vertical angles symmetric in V. EULUMDAT's Isym indicator 0-4 maps onto the
same foldings (1: rotational, 2: C0-C180 plane, 3: C90-C270 plane, 4: both).

Scale: an IES file's candela values are multiplied by its multiplier and its
ballast factor (and, in 1986-1995 files, by the ballast-lamp photometric
factor; LM-63-2002 calls that field "future use" and LM-63-2019 the file
generation type, so it is not applied there). EULUMDAT values are cd per 1000
lamp lumens: multiplied by the lamps' total flux / 1000 and the file's
conversion factor. Only ``TILT=NONE`` is read (a tilt table is an error).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import FileFormatError, InputError

__all__ = ["Photometry", "read_photometry", "parse_ies", "parse_ldt"]

_FEET = 0.3048
#: most angles along one axis of a table (0.1 degree steps over 360 degrees)
_MAX_ANGLES = 3601
#: largest photometric file read, bytes (catalogue files are kilobytes)
_MAX_FILE_BYTES = 64 << 20


@dataclass(frozen=True, eq=False)
class Photometry:
    """A luminous intensity distribution (candela table) with its symmetry.

    Attributes
    ----------
    kind : {"C", "B"}
        Photometric type (see the module docstring for the angles).
    horizontal : (h,) float, degrees, increasing
        The stored horizontal angles (C or H).
    vertical : (v,) float, degrees, increasing
        The stored vertical angles (gamma or V).
    candela : (h, v) float >= 0, cd
        Intensities, every scale factor of the file applied.
    lumens : float
        Lamp lumens (all lamps; -1 for absolute photometry), as the file says.
    watts : float
        Input watts (0 when the file does not say).
    size : (3,) float, metres
        Luminous opening: length (along C0 / x), width (along C90 / y), height.
        A negative length means a circular opening of that diameter (IES
        convention); zeros a point.
    name : str
        Luminaire name or catalogue number from the file.
    source : str
        Format read: ``IES:LM-63-2019``, ``IESNA:LM-63-2002``, ``IESNA:LM-63-1995``,
        ``IESNA91``, ``LM-63-1986`` or ``EULUMDAT``.
    """

    kind: str
    horizontal: np.ndarray
    vertical: np.ndarray
    candela: np.ndarray
    lumens: float = -1.0
    watts: float = 0.0
    size: tuple = (0.0, 0.0, 0.0)
    name: str = ""
    source: str = ""
    keywords: dict = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        h = np.asarray(self.horizontal, np.float64).reshape(-1)
        v = np.asarray(self.vertical, np.float64).reshape(-1)
        cd = np.asarray(self.candela, np.float64)
        if self.kind not in ("C", "B"):
            raise InputError(f"photometric type must be 'C' or 'B', got {self.kind!r}")
        if cd.shape != (len(h), len(v)):
            raise InputError(f"candela must have shape (horizontal, vertical) = ({len(h)}, {len(v)}), "
                             f"got {cd.shape}")
        if len(v) < 1 or len(h) < 1 or np.any(np.diff(h) <= 0) or np.any(np.diff(v) <= 0):
            raise InputError("photometric angles must be strictly increasing and non-empty")
        if not np.isfinite(cd).all() or (cd < 0).any():
            raise InputError("candela values must be finite and >= 0")
        for name, a in (("horizontal", h), ("vertical", v), ("candela", cd)):
            a = a.copy()
            a.flags.writeable = False
            object.__setattr__(self, name, a)
        object.__setattr__(self, "size", tuple(float(x) for x in self.size))
        object.__setattr__(self, "_flux", {})                 # resolution -> lumens (the table is read-only)

    # -- symmetry --------------------------------------------------------------------------------
    @property
    def symmetry(self) -> str:
        """``rotational``, ``quadrant``, ``bilateral`` (C0-C180), ``bilateral90`` (C90-C270) or ``none``
        (type B: ``quadrant``, ``bilateral_h``, ``bilateral_v`` or ``none``)."""
        h, v = self.horizontal, self.vertical
        if self.kind == "B":
            sym_h, sym_v = h[0] >= 0, v[0] >= 0
            return {(True, True): "quadrant", (True, False): "bilateral_h",
                    (False, True): "bilateral_v", (False, False): "none"}[(bool(sym_h), bool(sym_v))]
        if len(h) == 1:
            return "rotational"
        if h[0] == 0 and h[-1] == 90:
            return "quadrant"
        if h[0] == 0 and h[-1] == 180:
            return "bilateral"
        if h[0] == 90 and h[-1] == 270:
            return "bilateral90"
        return "none"

    def _fold(self, hq: np.ndarray, vq: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Query angles (degrees) folded into the stored ranges by the symmetry."""
        sym = self.symmetry
        if self.kind == "B":
            if sym in ("quadrant", "bilateral_h"):
                hq = np.abs(hq)
            if sym in ("quadrant", "bilateral_v"):
                vq = np.abs(vq)
            return hq, vq
        c = np.mod(hq, 360.0)
        if sym == "rotational":
            c = np.zeros_like(c)
        elif sym == "quadrant":
            c = np.where(c > 180.0, 360.0 - c, c)
            c = np.where(c > 90.0, 180.0 - c, c)
        elif sym == "bilateral":
            c = np.where(c > 180.0, 360.0 - c, c)
        elif sym == "bilateral90":
            c = np.where(c < 90.0, 180.0 - c, np.where(c > 270.0, 540.0 - c, c))
        return c, vq

    def _table(self) -> tuple[np.ndarray, np.ndarray]:
        """Horizontal angles and candela with a wrap-around column for a full type C web."""
        h, cd = self.horizontal, self.candela
        if self.kind == "C" and self.symmetry == "none":
            if h[-1] < 360.0 + h[0]:                     # close the circle: the first plane again at +360
                h = np.append(h, h[0] + 360.0)
                cd = np.vstack([cd, cd[:1]])
        return h, cd

    # -- evaluation ------------------------------------------------------------------------------
    def angles(self, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(horizontal, vertical) angles in degrees of unit ``directions`` (..., 3) in the luminaire frame."""
        d = np.asarray(directions, np.float64)
        x, y, z = d[..., 0], d[..., 1], d[..., 2]
        if self.kind == "C":
            gamma = np.degrees(np.arctan2(np.hypot(x, y), -z))
            c = np.degrees(np.arctan2(y, x))
            return np.mod(c, 360.0), gamma
        hb = np.degrees(np.arctan2(x, -z))
        vb = np.degrees(np.arcsin(np.clip(y, -1.0, 1.0)))
        return hb, vb

    def intensity(self, directions: np.ndarray) -> np.ndarray:
        """(...,) float, cd: intensity towards unit ``directions`` (..., 3), luminaire frame.

        Bilinear in (horizontal, vertical) angle on the stored web after
        folding by the symmetry; 0 outside the web's vertical range (e.g. the
        upper hemisphere of a 0-90 degree file) and behind a type B web.
        """
        hq, vq = self.angles(directions)
        return self.intensity_at(hq, vq)

    def intensity_at(self, horizontal: np.ndarray, vertical: np.ndarray) -> np.ndarray:
        """(...,) float, cd at angles in degrees (type C: C, gamma; type B: H, V)."""
        hq, vq = self._fold(np.asarray(horizontal, np.float64), np.asarray(vertical, np.float64))
        h, cd = self._table()
        v = self.vertical
        tol = 1e-9
        outside = (vq < v[0] - tol) | (vq > v[-1] + tol)
        if self.kind == "B":
            outside |= (hq < h[0] - tol) | (hq > h[-1] + tol)
        vi, vf = _bracket(v, vq)
        if len(h) == 1:
            col = cd[0]
            out = (1 - vf) * col[vi] + vf * col[np.minimum(vi + 1, len(v) - 1)]
        else:
            hi, hf = _bracket(h, hq)
            vj = np.minimum(vi + 1, len(v) - 1)
            hj = np.minimum(hi + 1, len(h) - 1)
            out = ((1 - hf) * ((1 - vf) * cd[hi, vi] + vf * cd[hi, vj])
                   + hf * ((1 - vf) * cd[hj, vi] + vf * cd[hj, vj]))
        return np.where(outside, 0.0, out)

    def flux(self, resolution: float = 0.5) -> float:
        """Luminous flux of the distribution, lumens: the integral of I over the sphere.

        Midpoint rule on a (gamma, C) grid of ``resolution`` degrees; the
        bilinear interpolant is integrated, so a finer grid changes the result
        only by its own quadrature error (about 1e-5 at 0.5 degrees).
        """
        if resolution in self._flux:
            return self._flux[resolution]
        ng, nc = int(round(180 / resolution)), int(round(360 / resolution))
        g = np.radians((np.arange(ng) + 0.5) * resolution)
        c = np.radians((np.arange(nc) + 0.5) * resolution)
        G, C = np.meshgrid(g, c, indexing="ij")
        d = np.stack([np.sin(G) * np.cos(C), np.sin(G) * np.sin(C), -np.cos(G)], axis=-1)
        dw = math.radians(resolution) ** 2 * np.sin(G)
        self._flux[resolution] = float((self.intensity(d) * dw).sum())
        return self._flux[resolution]

    def scaled(self, factor: float) -> "Photometry":
        """The same distribution with every intensity times ``factor``."""
        return Photometry(self.kind, self.horizontal, self.vertical, self.candela * float(factor),
                          self.lumens, self.watts, self.size, self.name, self.source, dict(self.keywords))


def _bracket(grid: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index i and fraction f with q = (1 - f) grid[i] + f grid[i + 1], clamped to the grid."""
    q = np.clip(q, grid[0], grid[-1])
    if len(grid) == 1:
        return np.zeros(np.shape(q), np.int64), np.zeros(np.shape(q))
    i = np.clip(np.searchsorted(grid, q, side="right") - 1, 0, len(grid) - 2)
    f = (q - grid[i]) / (grid[i + 1] - grid[i])
    return i, np.clip(f, 0.0, 1.0)


# -- IES LM-63 ---------------------------------------------------------------------------------------
_IES_HEADERS = {"IESNA:LM-63-1995": "IESNA:LM-63-1995", "IESNA:LM-63-2002": "IESNA:LM-63-2002",
                "IES:LM-63-2019": "IES:LM-63-2019", "IESNA91": "IESNA91", "IESNA:LM-63-1991": "IESNA91"}


def parse_ies(text: str, *, where: str = "IES file") -> Photometry:
    """A :class:`Photometry` from the text of an IES LM-63 file (1986 to 2019).

    Raises
    ------
    FileFormatError
        Naming ``where`` and the line: no ``TILT=`` line, a tilt table
        (only ``TILT=NONE`` is read), too few numbers, an unknown photometric
        type, angles out of order or outside the ranges LM-63 allows.
    """
    lines = text.replace("\r\n", "\n").replace("\r", "\n").split("\n")
    first = lines[0].strip().lstrip("\ufeff") if lines else ""
    source = next((v for k, v in _IES_HEADERS.items() if first.upper().startswith(k)), "LM-63-1986")
    keywords: dict[str, str] = {}
    tilt_line = None
    for i, line in enumerate(lines):
        s = line.strip()
        if s.upper().startswith("TILT"):
            tilt_line = i
            value = s.split("=", 1)[1].strip() if "=" in s else ""
            if value.upper() != "NONE":
                raise FileFormatError(f"{where}:{i + 1}: TILT={value}: only TILT=NONE is supported "
                                      "(a tilt table varies the lamp output with the luminaire's tilt)")
            break
        m = re.match(r"\[([^\]]+)\]\s*(.*)", s)
        if m:
            key = m.group(1).strip().upper()
            keywords[key] = (keywords[key] + " " + m.group(2)).strip() if key in keywords else m.group(2).strip()
    if tilt_line is None:
        raise FileFormatError(f"{where}: no TILT= line; not an IES LM-63 photometric file")
    tokens: list[tuple[str, int]] = []
    for i in range(tilt_line + 1, len(lines)):
        tokens += [(t, i + 1) for t in lines[i].replace(",", " ").split()]
    pos = 0

    def take(count: int, what: str) -> np.ndarray:
        nonlocal pos
        if pos + count > len(tokens):
            raise FileFormatError(f"{where}: the file ends while reading {what} (expected {count} more "
                                  f"numbers after line {tokens[-1][1] if tokens else tilt_line + 1})")
        out = []
        for t, ln in tokens[pos:pos + count]:
            try:
                out.append(float(t))
            except ValueError:
                raise FileFormatError(f"{where}:{ln}: {what}: {t!r} is not a number") from None
            if not math.isfinite(out[-1]):
                raise FileFormatError(f"{where}:{ln}: {what}: {t!r} is not a finite number")
        pos += count
        return np.array(out)

    head = take(10, "the luminaire line (lamps, lumens, multiplier, angles, type, units, size)")
    n_lamps, lumens, multiplier, nv, nh, ptype, units, width, length, height = head
    line_of_head = tokens[pos - 1][1]
    ballast, factor2, watts = take(3, "the ballast line (ballast factor, photometric factor, watts)")
    if nv < 1 or nh < 1 or nv != int(nv) or nh != int(nh) or nv * nh > _MAX_ANGLES ** 2:
        raise FileFormatError(f"{where}:{line_of_head}: numbers of angles must be positive integers, "
                              f"got {nv:g} vertical and {nh:g} horizontal")
    nv, nh = int(nv), int(nh)
    kinds = {1: "C", 2: "B"}
    if int(ptype) not in kinds:
        raise FileFormatError(f"{where}:{line_of_head}: photometric type {ptype:g}: only types 1 (C) and "
                              "2 (B) are supported (type 3, A, is not)")
    kind = kinds[int(ptype)]
    v = take(nv, "the vertical angles")
    h = take(nh, "the horizontal angles")
    cd = take(nv * nh, "the candela values").reshape(nh, nv)
    if np.any(np.diff(v) <= 0) or np.any(np.diff(h) <= 0):
        raise FileFormatError(f"{where}: angles must be strictly increasing; vertical {v.tolist()[:6]}..., "
                              f"horizontal {h.tolist()[:6]}...")
    if kind == "C":
        if v[0] < 0 or v[-1] > 180:
            raise FileFormatError(f"{where}: type C vertical angles must lie in 0..180, got {v[0]:g}..{v[-1]:g}")
        ok = (nh == 1 and h[0] == 0) or (h[0] == 0 and h[-1] in (90, 180)) or (h[0] == 90 and h[-1] == 270) \
            or (h[0] >= 0 and 180 < h[-1] <= 360)
        if not ok:
            raise FileFormatError(f"{where}: type C horizontal angles {h[0]:g}..{h[-1]:g}: expected 0 "
                                  "(rotational), 0..90, 0..180, 90..270 or a full 0..360")
    else:
        if not (-90 <= v[0] and v[-1] <= 90 and -90 <= h[0] and h[-1] <= 90):
            raise FileFormatError(f"{where}: type B angles must lie in -90..90")
    scale = multiplier * ballast * (factor2 if source in ("LM-63-1986", "IESNA91", "IESNA:LM-63-1995") else 1.0)
    if (cd < 0).any():
        raise FileFormatError(f"{where}: negative candela value {cd.min():g}")
    to_m = _FEET if int(units) == 1 else 1.0
    name = keywords.get("LUMCAT") or keywords.get("LUMINAIRE") or keywords.get("TEST") or ""
    lamp_lumens = lumens * n_lamps if lumens > 0 else -1.0
    return Photometry(kind, h, v, cd * scale, lamp_lumens, float(watts),
                      (length * to_m, width * to_m, height * to_m), name, source, keywords)


# -- EULUMDAT ----------------------------------------------------------------------------------------
def parse_ldt(text: str, *, where: str = "LDT file") -> Photometry:
    """A :class:`Photometry` from the text of a EULUMDAT (.ldt) file.

    The intensities of the stored C-planes follow the symmetry indicator
    Isym: 0 all Mc planes; 1 one plane (rotational); 2 C0..C180 (Mc/2 + 1
    planes); 3 C270..C360..C90 (Mc/2 + 1 planes, from index 3 Mc/4); 4 C0..C90
    (Mc/4 + 1 planes). Values in cd/klm are scaled by the lamps' flux / 1000
    and the conversion factor.

    Raises
    ------
    FileFormatError
        Naming ``where`` and the line: too few lines, a field that is not a
        number, an unknown Isym, a number of C-planes that the symmetry cannot
        divide.
    """
    lines = text.replace("\r\n", "\n").replace("\r", "\n").split("\n")
    idx = 0

    def line(what: str) -> str:
        nonlocal idx
        if idx >= len(lines):
            raise FileFormatError(f"{where}: the file ends at line {idx} while reading {what}")
        idx += 1
        return lines[idx - 1].strip()

    def num(what: str) -> float:
        s = line(what)
        try:
            x = float(s.replace(",", ".")) if s else 0.0
        except ValueError:
            raise FileFormatError(f"{where}:{idx}: {what}: {s!r} is not a number") from None
        if not math.isfinite(x):
            raise FileFormatError(f"{where}:{idx}: {what}: {s!r} is not a finite number")
        return x

    def count(what: str, high: int) -> int:
        x = num(what)
        if x != int(x) or not 0 <= x <= high:
            raise FileFormatError(f"{where}:{idx}: {what}: expected a whole number 0..{high}, got {x:g}")
        return int(x)

    company = line("the company")
    num("Ityp")
    isym = count("Isym (symmetry indicator)", 99)   # 5..99: refused below, by name
    mc = count("Mc (number of C-planes)", _MAX_ANGLES)
    num("Dc")
    ng = count("Ng (intensities per C-plane)", _MAX_ANGLES)
    num("Dg")
    line("the report number")
    name = line("the luminaire name")
    number = line("the luminaire number")
    line("the file name")
    line("the date")
    num("the luminaire length")
    num("the luminaire width")
    num("the luminaire height")
    lum_length = num("the luminous area's length")
    lum_width = num("the luminous area's width")
    heights = [num(f"the luminous area's height at C{c}") for c in (0, 90, 180, 270)]
    num("DFF")
    num("LORL")
    conversion = num("the conversion factor")
    num("the tilt")
    n_sets = count("the number of lamp sets", 20)
    if n_sets < 1:
        raise FileFormatError(f"{where}:{idx}: number of lamp sets must be at least 1, got {n_sets}")
    lamps, flux, watts = [], [], []
    for _ in range(n_sets):
        lamps.append(num("the number of lamps"))
        line("the lamp type")
        flux.append(num("the lamps' flux"))
        line("the colour temperature")
        line("the colour rendering")
        watts.append(num("the wattage"))
    for k in range(10):
        num(f"direct ratio {k + 1}")
    if isym not in (0, 1, 2, 3, 4):
        raise FileFormatError(f"{where}: Isym {isym}: expected 0 (none), 1 (rotational), 2 (C0-C180), "
                              "3 (C90-C270) or 4 (both planes)")
    if mc < 1 or ng < 1 or (isym in (2, 3) and mc % 2) or (isym == 4 and mc % 4):
        raise FileFormatError(f"{where}: Mc = {mc} C-planes and Ng = {ng} angles do not fit symmetry Isym {isym}")
    c_all = np.array([num(f"C angle {k + 1}") for k in range(mc)])
    g = np.array([num(f"gamma angle {k + 1}") for k in range(ng)])
    if (c_all < 0).any() or (c_all >= 360).any() or (g < 0).any() or (g > 180).any():
        raise FileFormatError(f"{where}: C angles must lie in 0..360 (got {c_all.min():g}..{c_all.max():g}) and "
                              f"gamma angles in 0..180 (got {g.min():g}..{g.max():g})")
    stored = {0: mc, 1: 1, 2: mc // 2 + 1, 3: mc // 2 + 1, 4: mc // 4 + 1}[isym]
    values = np.array([num(f"intensity {k + 1}") for k in range(stored * ng)]).reshape(stored, ng)
    total_flux = abs(lamps[0]) * flux[0] if lamps[0] > 0 else flux[0]
    cd = values * (total_flux / 1000.0) * (conversion if conversion > 0 else 1.0)
    if isym == 1:
        h = np.array([0.0])
    elif isym == 2:
        h = c_all[: mc // 2 + 1]
    elif isym == 4:
        h = c_all[: mc // 4 + 1]
    elif isym == 3:
        # stored C270 .. C360 .. C90; keep them as 90..270 (I(C) = I(180 - C)), angles increasing
        first = 3 * mc // 4
        cs = np.array([c_all[(first + k) % mc] % 360.0 for k in range(stored)])
        h = np.mod(180.0 - cs, 360.0)                     # C270 -> 270, C0 -> 180, C90 -> 90
        order = np.argsort(h)
        h, cd = h[order], cd[order]
    else:
        h, order = np.unique(np.mod(c_all, 360.0), return_index=True)
        cd = cd[order]
    size = (-lum_length / 1000.0 if lum_width == 0 else lum_length / 1000.0, lum_width / 1000.0,
            max(heights) / 1000.0)
    return Photometry("C", h, g, cd, float(total_flux), float(sum(watts)), size,
                      f"{name} {number}".strip() or company, "EULUMDAT",
                      {"COMPANY": company, "ISYM": str(isym)})


def read_photometry(path: "str | Path") -> Photometry:
    """A :class:`Photometry` from an ``.ies`` or ``.ldt`` file (by extension; else by content).

    Raises
    ------
    FileNotFoundError
        No such file.
    FileFormatError
        The file is not a readable IES LM-63 or EULUMDAT file (names the line).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such photometric file")
    if path.stat().st_size > _MAX_FILE_BYTES:
        raise FileFormatError(f"{path}: {path.stat().st_size:,} bytes; a photometric file is at most "
                              f"{_MAX_FILE_BYTES:,}")
    text = path.read_bytes().decode("latin-1")
    if "\0" in text:
        raise FileFormatError(f"{path}: a binary file, not an IES (.ies) or EULUMDAT (.ldt) text file")
    try:
        if path.suffix.lower() == ".ldt":
            return parse_ldt(text, where=str(path))
        if path.suffix.lower() == ".ies" or "TILT" in text.upper():
            return parse_ies(text, where=str(path))
    except FileFormatError:
        raise
    except InputError as exc:                   # the distribution's own checks do not know the file
        raise FileFormatError(f"{path}: {exc}") from None
    raise FileFormatError(f"{path}: not an IES (.ies) or EULUMDAT (.ldt) file")
