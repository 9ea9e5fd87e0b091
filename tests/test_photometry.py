"""Photometric files (IES LM-63 1986-2019, EULUMDAT): parsing, symmetry, scale, interpolation.

Every file here is written by the test in the shape real catalogue files have
(keyword headers, values broken over lines, CRLF line ends, comma decimals in
EULUMDAT), and the parsed table is checked against the numbers written.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from hfrad.errors import FileFormatError
from hfrad.lighting import parse_ies, parse_ldt, read_photometry

V = [0, 10, 20, 30, 40, 50, 60, 70, 80, 90]


def _ies(header: str, h, v, cd, *, multiplier=1.0, ballast=1.0, factor2=1.0, watts=36.0, units=2,
         size=(0.0, 0.0, 0.0), ptype=1, lamps=1, lumens=3000.0, per_line=7, keywords=True) -> str:
    lines = [header] if header else []
    if keywords:
        lines += ["[TEST] 12345", "[TESTLAB] hfrad photometric lab", "[MANUFAC] Example Lighting",
                  "[LUMCAT] EX-600", "[LUMINAIRE] recessed panel 600 x 600", "[MORE] prismatic diffuser",
                  "[LAMP] LED module"]
    lines += ["TILT=NONE",
              f"{lamps} {lumens:g} {multiplier:g} {len(v)} {len(h)} {ptype} {units} {size[1]:g} {size[0]:g} {size[2]:g}",
              f"{ballast:g} {factor2:g} {watts:g}"]

    def block(values):
        values = [f"{x:.10g}" for x in values]
        return [" ".join(values[i:i + per_line]) for i in range(0, len(values), per_line)]
    lines += block(v) + block(h)
    for row in np.asarray(cd).reshape(len(h), len(v)):
        lines += block(row)
    return "\r\n".join(lines) + "\r\n"


def _f_quadrant(c, g):
    return 1000 * np.cos(np.radians(g)) ** 1.5 * (1 + 0.3 * np.cos(np.radians(2 * c)))


@pytest.mark.parametrize("header", ["IES:LM-63-2019", "IESNA:LM-63-2002", "IESNA:LM-63-1995", "IESNA91", ""])
def test_ies_quadrant_symmetry_every_version(header):
    h = [0, 22.5, 45, 67.5, 90]
    cd = _f_quadrant(np.array(h)[:, None], np.array(V)[None, :])
    ph = parse_ies(_ies(header, h, V, cd, multiplier=2.0, ballast=0.9, factor2=0.5))
    assert ph.symmetry == "quadrant" and ph.kind == "C"
    # 1986/1991/1995 apply the ballast-lamp photometric factor; 2002 and 2019 do not
    scale = 2.0 * 0.9 * (0.5 if header in ("", "IESNA91", "IESNA:LM-63-1995") else 1.0)
    np.testing.assert_allclose(ph.candela, cd * scale, rtol=1e-9)
    assert ph.name == "EX-600" and ph.lumens == 3000 and ph.watts == 36
    # the four quadrants mirror the stored one, at stored grid angles exactly
    for c in (0, 22.5, 67.5, 90):
        for c2 in (180 - c, 180 + c, 360 - c):
            np.testing.assert_allclose(ph.intensity_at(np.array([c2]), np.array([30.0])),
                                       scale * _f_quadrant(c, 30), rtol=1e-9)
    # upper hemisphere is dark for a 0-90 web
    assert ph.intensity_at(np.array([10.0]), np.array([120.0]))[0] == 0.0


def test_ies_bilateral_and_c90_c270_symmetry():
    h = list(range(0, 181, 30))
    cd = 100 + np.array(h)[:, None] + np.array(V)[None, :]          # not symmetric within 0..180
    ph = parse_ies(_ies("IESNA:LM-63-2002", h, V, cd))
    assert ph.symmetry == "bilateral"
    for c in (30, 60, 150):
        np.testing.assert_allclose(ph.intensity_at(np.array([360 - c]), np.array([V])),
                                   ph.intensity_at(np.array([c]), np.array([V])), rtol=1e-12)
    np.testing.assert_allclose(ph.intensity_at(np.array([300.0]), np.array([20.0])), 100 + 60 + 20)
    # older files: 90..270, symmetric about the C90-C270 plane, I(C) = I(180 - C)
    h2 = list(range(90, 271, 30))
    cd2 = 100 + np.array(h2)[:, None] + np.array(V)[None, :]
    ph2 = parse_ies(_ies("IESNA:LM-63-1995", h2, V, cd2))
    assert ph2.symmetry == "bilateral90"
    np.testing.assert_allclose(ph2.intensity_at(np.array([30.0, 330.0]), np.array([40.0, 40.0])),
                               [100 + 150 + 40, 100 + 210 + 40], rtol=1e-12)


def test_ies_full_web_wraps_at_360_and_interpolates_bilinearly():
    h = list(range(0, 360, 45))                                   # 0..315: the file stops short of 360
    cd = np.array([[10.0 * (k + 1) + g for g in V] for k in range(len(h))])
    ph = parse_ies(_ies("IES:LM-63-2019", h, V, cd, per_line=4))
    assert ph.symmetry == "none"
    # halfway between C315 (80 + g) and C360 = C0 (10 + g), at gamma halfway between 20 and 30
    np.testing.assert_allclose(ph.intensity_at(np.array([337.5]), np.array([25.0])), 0.5 * (80 + 10) + 25)
    np.testing.assert_allclose(ph.intensity_at(np.array([-22.5]), np.array([25.0])), 0.5 * (80 + 10) + 25)
    # directions: gamma from the nadir (-z), C from +x towards +y
    d = np.array([[math.sin(math.radians(20)) * math.cos(math.radians(90)),
                   math.sin(math.radians(20)) * math.sin(math.radians(90)), -math.cos(math.radians(20))]])
    np.testing.assert_allclose(ph.intensity(d), 30 + 20, rtol=1e-9)


def test_ies_rotational_downlight_flux_feet_and_full_sphere():
    """A single horizontal angle: I(gamma) everywhere; a Lambertian I0 cos(g) gives pi I0 lumens."""
    v = np.arange(0, 181, 2.5)
    i0 = 1000.0
    cd = np.where(v <= 90, i0 * np.cos(np.radians(v)), 0.0)
    ph = parse_ies(_ies("IESNA:LM-63-2002", [0], v, cd, units=1, size=(-0.5, 0, 0.1), per_line=10))
    assert ph.symmetry == "rotational"
    assert ph.flux() == pytest.approx(math.pi * i0, rel=1e-3)     # piecewise-linear cos: 2e-4 below pi I0
    np.testing.assert_allclose(ph.size, [-0.5 * 0.3048, 0.0, 0.1 * 0.3048])
    np.testing.assert_allclose(ph.intensity_at(np.array([0.0, 123.0]), np.array([60.0, 60.0])), 500.0, rtol=1e-12)


def test_ies_type_b_symmetric_in_h():
    h = [0, 15, 30, 45, 60, 75, 90]
    v = [-90, -60, -30, 0, 30, 60, 90]
    cd = np.array([[1000 - 5 * hh - 2 * vv - abs(vv) for vv in v] for hh in h], float)
    ph = parse_ies(_ies("IESNA:LM-63-2002", h, v, cd, ptype=2))
    assert ph.kind == "B" and ph.symmetry == "bilateral_h"
    np.testing.assert_allclose(ph.intensity_at(np.array([-30.0, 30.0]), np.array([30.0, 30.0])),
                               1000 - 150 - 60 - 30, rtol=1e-12)
    # direction (cos V sin H, sin V, -cos V cos H); behind the web (|H| > 90) is dark
    Hr, Vr = math.radians(-30), math.radians(30)
    d = np.array([[math.cos(Vr) * math.sin(Hr), math.sin(Vr), -math.cos(Vr) * math.cos(Hr)], [0, 0, 1.0]])
    np.testing.assert_allclose(ph.intensity(d), [1000 - 150 - 60 - 30, 0.0], rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("text, match", [
    ("IESNA:LM-63-2002\n[TEST] x\nTILT=INCLUDE\n1\n", "only TILT=NONE"),
    ("IESNA:LM-63-2002\n[TEST] x\n", "no TILT"),
    ("IESNA:LM-63-2002\nTILT=NONE\n1 1000 1 3 1 1 2 0 0 0\n1 1 10\n0 45 90\n0\n100 50\n", "ends while reading"),
    ("IESNA:LM-63-2002\nTILT=NONE\n1 1000 1 3 1 3 2 0 0 0\n1 1 10\n0 45 90\n0\n100 50 0\n", "type 3"),
    ("IESNA:LM-63-2002\nTILT=NONE\n1 1000 1 3 1 1 2 0 0 0\n1 1 10\n0 45 4x\n0\n100 50 0\n", "not a number"),
    ("IESNA:LM-63-2002\nTILT=NONE\n1 1000 1 3 2 1 2 0 0 0\n1 1 10\n0 45 90\n0 120\n100 50 0 1 1 1\n",
     "horizontal angles"),
])
def test_ies_errors_name_the_problem(text, match):
    with pytest.raises(FileFormatError, match=match):
        parse_ies(text, where="bad.ies")


# -- EULUMDAT -----------------------------------------------------------------------------------------
def _ldt(isym: int, f, *, mc=24, dg=5.0, flux=2000.0, conversion=1.0, lamps=2, width=600) -> str:
    """A EULUMDAT file of f(C, gamma) (cd/klm), stored as the symmetry indicator says."""
    c_all = np.arange(mc) * 360.0 / mc
    g = np.arange(0, 180 + dg / 2, dg)
    stored = {0: range(mc), 1: [0], 2: range(mc // 2 + 1), 4: range(mc // 4 + 1),
              3: [(3 * mc // 4 + k) % mc for k in range(mc // 2 + 1)]}[isym]
    L = ["Example Lighting GmbH", "1", str(isym), str(mc), f"{360 / mc:g}", str(len(g)), f"{dg:g}",
         "report 42", "Panel 600", "EX-600-LDT", "ex600.ldt", "2026-12-02 hfrad", "620", str(width), "80",
         "600", str(width), "0", "0", "0", "0", "100", "85", f"{conversion:g}".replace(".", ","), "0", "1",
         str(lamps), "LED", f"{flux / lamps:g}", "4000", "80", "36"]
    L += ["0.5"] * 10
    L += [f"{c:g}" for c in c_all] + [f"{x:g}" for x in g]
    for k in stored:
        L += [f"{v:.6f}".replace(".", ",") for v in f(c_all[k], g)]
    return "\r\n".join(L) + "\r\n"


_LDT_CASES = {
    0: lambda c, g: 200 + 80 * np.cos(np.radians(g)) + 30 * np.sin(np.radians(c)) + 10 * np.cos(np.radians(c)),
    1: lambda c, g: 200 + 80 * np.cos(np.radians(g)) + 0 * c,
    2: lambda c, g: 200 + 80 * np.cos(np.radians(g)) + 30 * np.cos(np.radians(c)),         # f(-C) = f(C)
    3: lambda c, g: 200 + 80 * np.cos(np.radians(g)) + 30 * np.sin(np.radians(c)),         # f(180 - C) = f(C)
    4: lambda c, g: 200 + 80 * np.cos(np.radians(g)) + 30 * np.cos(np.radians(2 * c)),     # both planes
}


@pytest.mark.parametrize("isym", [0, 1, 2, 3, 4])
def test_ldt_every_symmetry_reproduces_the_distribution(isym):
    f = _LDT_CASES[isym]
    ph = parse_ldt(_ldt(isym, f, conversion=1.5))
    assert ph.source == "EULUMDAT" and ph.kind == "C"
    assert ph.symmetry == {0: "none", 1: "rotational", 2: "bilateral", 3: "bilateral90", 4: "quadrant"}[isym]
    scale = 2000 / 1000 * 1.5                           # cd/klm x lamp flux / 1000 x conversion factor
    # every C plane of the full circle at every stored gamma, within the file's 6 decimals
    C = np.repeat(np.arange(24) * 15.0, 37)
    G = np.tile(np.arange(0, 181, 5.0), 24)
    np.testing.assert_allclose(ph.intensity_at(C, G), scale * f(C, G), rtol=1e-8)
    assert ph.lumens == 2000 and ph.size == (0.6, 0.6, 0.0)


def test_ldt_round_disk_and_errors():
    ph = parse_ldt(_ldt(1, _LDT_CASES[1], width=0))
    assert ph.size[0] == -0.6                            # b1 = 0: circular opening of diameter 600 mm
    bad = _ldt(2, _LDT_CASES[2]).split("\r\n")
    bad[2] = "7"
    with pytest.raises(FileFormatError, match="Isym 7"):
        parse_ldt("\r\n".join(bad), where="bad.ldt")
    with pytest.raises(FileFormatError, match="bad.ldt: the file ends"):
        parse_ldt("\r\n".join(_ldt(0, _LDT_CASES[0]).split("\r\n")[:100]), where="bad.ldt")


def test_read_photometry_by_extension(tmp_path):
    (tmp_path / "a.ies").write_bytes(_ies("IESNA:LM-63-2002", [0], V, 100 * np.ones(len(V))).encode("latin-1"))
    (tmp_path / "b.ldt").write_bytes(_ldt(1, _LDT_CASES[1]).encode("latin-1"))
    assert read_photometry(tmp_path / "a.ies").intensity_at(np.array([0.0]), np.array([45.0]))[0] == 100
    assert read_photometry(tmp_path / "b.ldt").source == "EULUMDAT"
    with pytest.raises(FileNotFoundError):
        read_photometry(tmp_path / "missing.ies")
