"""The ``hfrad`` command line, end to end on small scenes."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import run_cli as run


@pytest.fixture(scope="module")
def cornell_hfr(tmp_path_factory):
    path = tmp_path_factory.mktemp("cli") / "cornell.hfr"
    result = run("precompute", "cornell", "--patches", "400", "--eps", "0.05", "-o", path, "--quiet")
    assert result.exit_code == 0, result.output
    assert "eq. 5 bound" in result.output
    return path


def test_solve_outputs(cornell_hfr, tmp_path):
    for suffix in (".npz", ".csv", ".ply", ".glb"):
        out = tmp_path / f"b{suffix}"
        result = run("solve", cornell_hfr, "-o", out)
        assert result.exit_code == 0, result.output
        assert out.exists() and out.stat().st_size > 0
    data = np.load(tmp_path / "b.npz")
    assert data["B"].shape == (data["area"].shape[0], 3)
    assert (data["B"] >= data["E"] - 1e-6).all()  # radiosity = emission + reflected light


def test_solve_with_new_emission(cornell_hfr, tmp_path):
    out = tmp_path / "red.npz"
    result = run("solve", cornell_hfr, "-o", out, "--emission", "light=0", "--emission", "red=1,0,0")
    assert result.exit_code == 0, result.output
    data = np.load(out)
    names = list(data["material_names"])
    red = data["material"] == names.index("red")
    assert np.allclose(data["E"][red], [1, 0, 0]) and not data["E"][~red].any()
    assert data["B"][:, 1:].max() < 1e-3 * data["B"][:, 0].max() + 1e-9  # only red light, red walls


@pytest.mark.parametrize("args, message", [
    (["--emission", "nope=1,1,1"], "no material or group named 'nope'"),
    (["--emission", "light=0"], "no emitter"),
    (["--emission", "light=1,nan,1"], "R,G,B"),
    (["--emission-scale", "-1"], "emission-scale"),
])
def test_solve_bad_emission(cornell_hfr, tmp_path, args, message):
    result = run("solve", cornell_hfr, "-o", tmp_path / "x.npz", *args)
    assert result.exit_code != 0
    assert message in result.output
    assert not (tmp_path / "x.npz").exists()


def test_render_png(cornell_hfr, tmp_path):
    out = tmp_path / "c.png"
    result = run("render", cornell_hfr, "-o", out, "--camera", "front", "--width", "96", "--height", "96")
    assert result.exit_code == 0, result.output
    from PIL import Image

    image = np.asarray(Image.open(out))
    assert image.shape == (96, 96, 3)
    left, right = image[:, :48].astype(float), image[:, 48:].astype(float)
    assert left[..., 0].mean() > right[..., 0].mean() and right[..., 1].mean() > left[..., 1].mean()


def test_bad_files(tmp_path):
    result = run("solve", tmp_path / "missing.hfr", "-o", tmp_path / "x.npz")
    assert result.exit_code != 0 and "missing.hfr" in result.output
    junk = tmp_path / "junk.hfr"
    junk.write_bytes(b"not an hdf5 file at all")
    result = run("solve", junk, "-o", tmp_path / "x.npz")
    assert result.exit_code != 0 and "junk.hfr" in result.output
    result = run("precompute", "cornell", "-o", tmp_path / "x.hfr", "--eps", "1.5", "--quiet")
    assert result.exit_code != 0 and "eps must be in (0, 1)" in result.output
    result = run("precompute", "cornell", "-o", tmp_path / "x.hfr", "--block", "100000", "--quiet")
    assert result.exit_code != 0 and "block size" in result.output
    assert not (tmp_path / "x.hfr").exists()


def test_demo(tmp_path):
    result = run("demo", "-o", tmp_path, "--patches", "300", "--quiet")
    assert result.exit_code == 0, result.output
    for name in ("cornell.png", "cornell-blue.png", "cornell.glb", "cornell.hfr"):
        assert (tmp_path / name).exists()
    assert "eq. 5 bound" in result.output


def test_info_and_version():
    result = run("info", "cornell", "--json")
    assert result.exit_code == 0 and '"patches": 54' in result.output  # floor and ceiling: constrained Delaunay around the holes
    result = run("--version")
    assert result.exit_code == 0 and result.output.startswith("hfrad ")


def test_solve_residual(cornell_hfr, tmp_path):
    result = run("solve", cornell_hfr, "-o", tmp_path / "r.npz", "--residual", "--quiet")
    assert result.exit_code == 0, result.output
    line = next(l for l in result.output.splitlines() if "residual" in l)
    values = [float(x) for x in line.split(":")[-1].split(",")]
    assert len(values) == 3 and all(0 < v < 0.05 for v in values)  # eps = 0.05 factorization
