"""Lighting inputs validated at the boundary, and outputs all-or-nothing (issue 47, items 2 and 4).

Photometric files, layouts, sensor files, grids and design specs: one error
naming the file and the field (exit 2) before any work; sizes refused with
the number. Outputs: one naming an input is refused; a command whose last
step fails leaves none of its outputs; a version-1 .hfr file is refused.
"""

from __future__ import annotations

import json
import math

import h5py
import numpy as np
import pytest

import hfrad
from hfrad.errors import FileFormatError, InputError, MemoryLimitError
from hfrad.lighting import Luminaire, Photometry, read_layout, read_sensors, rectangle_grid
from hfrad.lighting.photometry import read_photometry
from tests.conftest import run_cli

_IES = """IESNA:LM-63-2002
TILT=NONE
1 1000 1.0 {nv} 1 1 2 {w} -0.15 0.0
1.0 1.0 16
0 30 60 90
0
500 400 200 {cd}
"""


def _ies(tmp_path, name="a.ies", nv="4", w="-0.15", cd="0"):
    p = tmp_path / name
    p.write_text(_IES.format(nv=nv, w=w, cd=cd))
    return p


def _ldt(conversion="1", lamps="1", gammas=("0", "45", "90", "135", "180")):
    L = (["Co", "1", "1", "1", "0", "5", "45", "r", "lum", "n", "f", "d", "600", "600", "80", "0", "0",
          "0", "0", "0", "0", "100", "80", conversion, "0", "1", lamps, "LED", "3000", "3000", "80", "30"]
         + ["0.5"] * 10 + ["0"] + list(gammas) + ["300", "280", "200", "100", "0"])
    return "\n".join(L) + "\n"


@pytest.mark.parametrize("field, value", [("nv", "nan"), ("nv", "inf"), ("cd", "nan"), ("w", "inf")])
def test_non_finite_ies_numbers_name_the_file_and_line(tmp_path, field, value):
    """Main: NaN counts raised 'cannot convert float NaN to integer' (a traceback at the CLI)."""
    p = _ies(tmp_path, **{field: value})
    with pytest.raises(FileFormatError, match=r"a\.ies:\d+: .*not a finite number"):
        read_photometry(p)


@pytest.mark.parametrize("kw, what", [({"conversion": "nan"}, "conversion factor"),
                                      ({"lamps": "nan"}, "number of lamps"),
                                      ({"gammas": ("0", "90", "180", "270", "360")}, "gamma angles in 0..180")])
def test_bad_eulumdat_numbers_are_refused_naming_the_file(tmp_path, kw, what):
    assert read_photometry(_write(tmp_path / "ok.ldt", _ldt())).kind == "C"
    with pytest.raises(FileFormatError, match=rf"b\.ldt.*{what}"):
        read_photometry(_write(tmp_path / "b.ldt", _ldt(**kw)))


def _write(p, text):
    p.write_text(text)
    return p


def test_the_distributions_own_checks_name_the_file(tmp_path):
    """Angles not increasing are caught by Photometry, which does not know the file: the reader adds it."""
    p = tmp_path / "dup.ies"
    p.write_text(_IES.format(nv=4, w=0, cd=0).replace("0 30 60 90", "0 30 30 90"))
    with pytest.raises(FileFormatError, match="dup.ies"):
        read_photometry(p)
    (tmp_path / "bin.ies").write_bytes(b"TILT=NONE\0\1\2" * 10)
    with pytest.raises(FileFormatError, match="bin.ies: a binary file"):
        read_photometry(tmp_path / "bin.ies")


@pytest.mark.parametrize("key, value", [("position", "abc"), ("position", {"x": 1}), ("position", ["1", "2", "3"]),
                                        ("aim", "down"), ("aim", {"a": 1}), ("color", "white"),
                                        ("color", [True, 1, 1])])
def test_layout_vectors_must_be_three_numbers(tmp_path, key, value):
    """Main: a string or an object raised ValueError/TypeError from numpy (a traceback at the CLI)."""
    _ies(tmp_path)
    entry = {"position": [0, 2, 0], key: value}
    (tmp_path / "lay.json").write_text(json.dumps({"defaults": {"photometry": "a.ies"}, "luminaires": [entry]}))
    with pytest.raises(InputError, match=rf"lay\.json: luminaires\[0\]: .*{key}: expected three finite numbers"):
        read_layout(tmp_path / "lay.json")


def test_binary_sensor_file_is_one_clear_error(tmp_path):
    (tmp_path / "s.txt").write_bytes(bytes(range(256)))
    with pytest.raises(FileFormatError, match="s.txt: not a text sensor file"):
        read_sensors(tmp_path / "s.txt")


def test_sizes_are_refused_with_the_number_before_any_work(tmp_path):
    with pytest.raises(MemoryLimitError, match=r"sensor grid of [\d,]+ points"):
        rectangle_grid((0, 1000), (0, 1000), 0.8, 1e-4)                 # 1e14 points
    with pytest.raises(InputError, match="margin"):
        rectangle_grid((0, 5), (0, 5), 0.8, 0.5, margin=-1)
    big = Photometry("C", [0.0], [0.0, 90.0], [[100.0, 0.0]], size=(304800.0, 304800.0, 0.0))   # a 1e6 ft opening
    with pytest.raises(InputError, match=r"needs [\d,]+ area-source points"):
        Luminaire(big, [0, 1, 0]).emission_points(0.1)
    fac = hfrad.factorize(hfrad.load_scene("furnace", patches=50), eps=1e-2)
    from hfrad.lighting import LightingModel
    with pytest.raises(InputError, match="area-source points"):
        LightingModel(fac, [Luminaire(big, [0.5, 0.5, 0.5])])
    from hfrad.lighting.limits import check_lighting_size
    with pytest.raises(MemoryLimitError, match="10,000,000 sensors"):
        check_lighting_size(100_000, 12, [10_000_000])
    with pytest.raises(InputError, match=r"1,000,000 sensors on 722 patches: .* 2.9e\+09 rays"):
        check_lighting_size(722, 12, [1_000_000])                       # fits in memory, but a quarter hour
    check_lighting_size(722, 12, [480, 20])                             # the office example's grid


def test_a_design_grid_without_a_goal_is_refused(tmp_path):
    from hfrad.inverse.luminaires import SpecError, parse_lighting_spec
    _ies(tmp_path)
    lay = {"defaults": {"photometry": "a.ies"}, "luminaires": [{"position": [0.5, 0.9, 0.5]}]}
    spec = {"luminaires": lay, "grids": [{"rectangle": [[0.1, 0.9], [0.1, 0.9]], "height": 0.5, "spacing": 0.2}]}
    with pytest.raises(SpecError, match=r"grids\[0\]: no goal"):
        parse_lighting_spec(spec, hfrad.load_scene("furnace", patches=50), base=tmp_path)


# -- outputs (item 4) ----------------------------------------------------------------------------

@pytest.fixture(scope="module")
def box(tmp_path_factory):
    d = tmp_path_factory.mktemp("box")
    fac = hfrad.factorize(hfrad.load_scene("cornell", patches=150), eps=1e-2)
    hfr = fac.save(d / "box.hfr")
    _ies(d)
    (d / "lay.json").write_text(json.dumps({"defaults": {"photometry": "a.ies"},
                                            "luminaires": [{"name": "L1", "position": [0, 1.9, 0]}]}))
    (d / "pts.txt").write_text("0 0.5 0 0 1 0\n")
    (d / "spec.json").write_text(json.dumps({"luminaires": "lay.json", "grids": [
        {"name": "g", "floor": "white", "height": 0.5, "spacing": 0.5, "mean": 5}]}))
    return d, hfr


@pytest.mark.parametrize("cmd", ["lux-layout", "lux-hfr", "design-spec", "design-layout", "design-render-spec"])
def test_an_output_naming_an_input_is_refused(box, cmd):
    """Main overwrote the layout or the spec with the result."""
    d, hfr = box
    args = {"lux-layout": ["lux", hfr, "--layout", d / "lay.json", "--floor", "white", "-o", d / "lay.json"],
            "lux-hfr": ["lux", hfr, "--layout", d / "lay.json", "--floor", "white", "-o", d / "lay.json",
                        "--csv", d / "x.csv"],
            "design-spec": ["design", d / "spec.json", hfr, "-o", d / "spec.json"],
            "design-layout": ["design", d / "spec.json", hfr, "-o", d / "lay.json"],
            "design-render-spec": ["design", d / "spec.json", hfr, "-o", d / "x.json", "--plan", d / "p.png",
                                   "--render", d / "spec.json"]}[cmd]
    before = {p: p.read_bytes() for p in (d / "lay.json", d / "spec.json")}
    res = run_cli(*args, "--quiet")
    assert res.exit_code == 2 and "is also the" in res.output, res.output
    assert all(p.read_bytes() == b for p, b in before.items())


def test_a_failing_last_step_leaves_no_output(box, tmp_path):
    """Main wrote the JSON, then refused --plan without a grid (or failed on --csv): the JSON stayed."""
    d, hfr = box
    out = tmp_path / "r.json"
    res = run_cli("lux", hfr, "--layout", d / "lay.json", "--sensors", d / "pts.txt", "-o", out,
                  "--plan", tmp_path / "p.png", "--quiet")
    assert res.exit_code == 2 and "--plan needs" in res.output and not out.exists()
    res = run_cli("lux", hfr, "--layout", d / "lay.json", "--floor", "white", "-o", out,
                  "--csv", tmp_path / "none" / "x.csv", "--quiet")
    assert res.exit_code == 2 and not out.exists()
    (tmp_path / "ro").mkdir()
    (tmp_path / "p.png").mkdir()                                    # the plan cannot be written: a folder is there
    res = run_cli("lux", hfr, "--layout", d / "lay.json", "--floor", "white", "-o", out,
                  "--plan", tmp_path / "p.png", "--quiet")
    assert res.exit_code == 2 and not out.exists(), res.output
    res = run_cli("design", d / "spec.json", hfr, "-o", out, "--plan", tmp_path / "p.png", "--quiet")
    assert res.exit_code == 2 and not out.exists(), res.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.png", "ro"]          # no temporaries either


def test_a_version_1_hfr_file_is_refused(box, tmp_path):
    """Main loaded a crafted version-1 file (no checksums, digest removed) and solved from its data."""
    d, hfr = box
    old = tmp_path / "v1.hfr"
    old.write_bytes(hfr.read_bytes())
    with h5py.File(old, "a") as f:
        f.attrs["format_version"] = 1
        for key in [k for k in f.attrs if "sha" in k or k == "datasets"]:
            del f.attrs[key]
    with pytest.raises(FileFormatError, match="carries no checksums"):
        hfrad.load(old)
