"""Emission JSON files: the reader's errors, and `solve`/`render --emission-file` agreeing with `--emission`."""

from __future__ import annotations

import json

import numpy as np
import pytest

from conftest import run_cli as run
from hfrad.errors import FileFormatError
from hfrad.io.emission import EmitterSetting, emission_overrides, read_emission, write_emission


@pytest.fixture(scope="module")
def hfr(tmp_path_factory):
    path = tmp_path_factory.mktemp("emission") / "cornell.hfr"
    result = run("precompute", "cornell", "--patches", "300", "--eps", "0.05", "-o", path, "--quiet")
    assert result.exit_code == 0, result.output
    return path


def test_round_trip(tmp_path):
    settings = [EmitterSetting("light", (17.0, 12.0, 4.0)), EmitterSetting("red", (1.0, 0.5, 0.0), on=False)]
    path = write_emission(tmp_path / "e.json", settings)
    assert read_emission(path) == settings
    assert emission_overrides(settings) == {"light": (17.0, 12.0, 4.0), "red": (0.0, 0.0, 0.0)}
    assert [p.name for p in tmp_path.iterdir()] == ["e.json"]  # no temporary left behind


@pytest.mark.parametrize("doc, message", [
    ("[1, 2]", "top level: expected a JSON object"),
    ('{"format": "hfrad-emission", "version": 1, "emitters": [], "extra": 1}', "extra: unknown field"),
    ('{"format": "other", "version": 1, "emitters": []}', "format: expected 'hfrad-emission'"),
    ('{"format": "hfrad-emission", "version": 2, "emitters": []}', "version: expected 1"),
    ('{"format": "hfrad-emission", "version": 1, "emitters": {}}', "emitters: expected a list"),
    ('{"format": "hfrad-emission", "version": 1, "emitters": [{"name": "a", "exitance": [1, 2]}]}',
     "emitters[0].exitance: expected three finite numbers >= 0"),
    ('{"format": "hfrad-emission", "version": 1, "emitters": [{"name": "a", "exitance": [1, 1, 1]},'
     ' {"name": "b", "exitance": [1, -2, 3]}]}', "emitters[1].exitance"),
    ('{"format": "hfrad-emission", "version": 1, "emitters": [{"name": "a", "exitance": [1, 1, "x"]}]}',
     "emitters[0].exitance"),
    ('{"format": "hfrad-emission", "version": 1, "emitters": [{"name": "", "exitance": [1, 1, 1]}]}',
     "emitters[0].name"),
    ('{"format": "hfrad-emission", "version": 1, "emitters": [{"name": "a"}]}', "emitters[0].exitance: missing"),
    ('{"format": "hfrad-emission", "version": 1, "emitters": [{"name": "a", "exitance": [1, 1, 1], "on": 1}]}',
     "emitters[0].on: expected true or false"),
    ('{"format": "hfrad-emission", "version": 1, "emitters": [{"name": "a", "exitanse": [1, 1, 1]}]}',
     "emitters[0].exitanse: unknown field"),
    ('{"format": "hfrad-emission",\n "version": 1,,}', "not valid JSON"),
])
def test_bad_files_name_the_field(tmp_path, doc, message):
    path = tmp_path / "bad.json"
    path.write_text(doc)
    with pytest.raises(FileFormatError) as err:
        read_emission(path)
    assert message in str(err.value) and str(path) in str(err.value)


def test_solve_with_emission_file_matches_emission_option(hfr, tmp_path):
    path = write_emission(tmp_path / "e.json", [EmitterSetting("light", (0.0, 0.0, 0.0), on=True),
                                                EmitterSetting("red", (1.0, 0.0, 0.0)),
                                                EmitterSetting("green", (3.0, 3.0, 3.0), on=False)])
    a, b = tmp_path / "a.npz", tmp_path / "b.npz"
    result = run("solve", hfr, "-o", a, "--emission-file", path)
    assert result.exit_code == 0, result.output
    result = run("solve", hfr, "-o", b, "--emission", "light=0", "--emission", "red=1,0,0")
    assert result.exit_code == 0, result.output
    A, B = np.load(a), np.load(b)
    assert A["E"].any() and np.array_equal(A["E"], B["E"]) and np.array_equal(A["B"], B["B"])
    # --emission overrides the file
    result = run("solve", hfr, "-o", a, "--emission-file", path, "--emission", "red=0,2,0")
    assert result.exit_code == 0, result.output
    red = np.load(a)["material"] == list(np.load(a)["material_names"]).index("red")
    assert np.allclose(np.load(a)["E"][red], [0, 2, 0])


def test_cli_errors(hfr, tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"format": "hfrad-emission", "version": 1,
                               "emitters": [{"name": "lamp", "exitance": [1, 1, 1]}]}))
    for cmd, out in (("solve", tmp_path / "x.npz"), ("render", tmp_path / "x.png")):
        result = run(cmd, hfr, "-o", out, "--emission-file", bad)
        assert result.exit_code == 2 and "no material or group named 'lamp'" in result.output, result.output
        result = run(cmd, hfr, "-o", out, "--emission-file", tmp_path / "missing.json")
        assert result.exit_code == 2 and "missing.json" in result.output, result.output
        assert not out.exists()
    good = write_emission(tmp_path / "g.json", [EmitterSetting("light", (5.0, 5.0, 5.0))])
    result = run("render", hfr, "-o", tmp_path / "r.png", "--emission-file", good, "--width", "32",
                 "--height", "32")
    assert result.exit_code == 0, result.output
