"""The viewer's pieces without a browser: lighting by superposition, colours, coalescing, the server's robustness."""

from __future__ import annotations

import socket
import threading
import time
import warnings

import numpy as np
import pytest
from typer.testing import CliRunner

import hfrad
from hfrad.cli import app as cli_app
from hfrad.errors import FileFormatError, InputError, SceneError
from hfrad.render.tonemap import srgb_encode, tonemap
from hfrad.viewer.coalesce import LatestWins
from hfrad.viewer.display import MeshColors, MeshGLB, aces_filmic, precompensate_aces
from hfrad.viewer.lighting import Emitter, Lighting, scene_emitters

viser = pytest.importorskip("viser", reason="hfrad view needs viser (pip install viser)")


@pytest.fixture(scope="module")
def fac():
    scene = hfrad.load_scene("cornell", patches=400)
    return hfrad.factorize(scene, eps=0.05)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def recv_mesh(ws, timeout: float = 10.0) -> None:
    """Read messages until one that carries a mesh (viser compresses it; other messages are < 1 KB)."""
    end = time.monotonic() + timeout
    while len(ws.recv(timeout=max(0.1, end - time.monotonic()))) <= 2048:
        pass


def test_superposition_equals_direct_solves(fac):
    """Radiosity is linear in the exitance: sums of batched unit solves = one solve of the summed exitance."""
    lighting = Lighting(fac)
    emitters, warnings = scene_emitters(fac.scene)
    assert [e.name for e in emitters] == ["light"] and not warnings
    assert np.allclose(lighting.exitance(emitters), fac.scene.emission)
    emitters = [Emitter("light", 20.0, (1.0, 0.5, 0.25)), Emitter("red", 3.0, (1.0, 0.0, 0.2)),
                Emitter("floor", 7.0, on=False), Emitter("tall_block", 2.0)]   # a group over a material
    E = lighting.exitance(emitters)
    B = lighting.radiosity(emitters)
    ref = fac.solve(E)
    assert np.abs(B - ref).max() <= 1e-5 * np.abs(ref).max()   # float32 factors: rounding only
    assert np.array_equal(lighting.radiosity(emitters, direct=True), ref)
    # the group named later wins on patches it shares with 'white' (as repeated --emission does)
    scene = fac.scene
    tall = scene.group == scene.groups.index("tall_block")
    assert np.allclose(E[tall], 2.0) and not E[scene.material == scene.material_names.index("green")].any()
    with pytest.raises(SceneError, match="no material or group named 'lamp'"):
        lighting.radiosity([Emitter("lamp", 1.0)])


def test_vertex_colors_match_render_tonemap(fac):
    scene = fac.scene
    colors = MeshColors(scene)
    assert colors.faces.shape == (scene.n_triangles, 3)
    B = np.full((scene.n_patches, 3), 3.0)     # constant radiosity: smoothing leaves it unchanged
    display, ev = colors.shaded(B, np.zeros_like(B), exposure=-1.0)
    expected = tonemap(np.full(3, 3.0 / np.pi), exposure=-1.0)
    assert ev == -1.0
    assert np.array_equal(np.rint(srgb_encode(display) * 255).astype(np.uint8),
                          np.broadcast_to(expected, display.shape))
    # what three.js draws (ACES filmic, then sRGB) is the render's 8-bit value again
    shown = np.rint(srgb_encode(aces_filmic(precompensate_aces(display))) * 255)
    assert np.abs(shown - expected).max() <= 1
    fc, top = colors.falsecolor(fac.solve(scene.emission), scene.emission, "lux")
    assert top > 0 and fc.shape == display.shape and (fc >= 0).all() and (fc <= 1).all()


def test_vertex_radiosity_is_the_renderers_smoothing(fac):
    # smooth (vertex-interpolated) shading, the one helper the renderer uses: every corner of every
    # triangle gets the renderer's corner value, and a radiosity linear in height comes back exactly
    # at the vertices inside the back wall (the area-weighted mean left patch-sized blotches there)
    from hfrad.render import smooth_corners

    scene = fac.scene
    colors = MeshColors(scene)
    B = fac.solve(scene.emission)
    at_vertex = colors.radiosity(B)                                    # (v, 3)
    np.testing.assert_allclose(at_vertex[colors.faces], smooth_corners(scene, B), rtol=1e-12, atol=0)
    assert len(np.unique(np.round(at_vertex[:, 0], 9))) > 0.5 * len(at_vertex)   # not one value a patch
    linear = np.repeat((0.2 + 0.4 * scene.vertices[scene.faces].mean(axis=1)[:, 1])[:, None], 3, axis=1)
    v = colors.vertices
    inner = (np.abs(v[:, 2] + 1) < 1e-9) & (np.abs(v[:, 0]) < 0.999) & (v[:, 1] > 0.001) & (v[:, 1] < 1.999)
    assert inner.sum() > 20
    np.testing.assert_allclose(colors.radiosity(linear)[inner, 0], 0.2 + 0.4 * v[inner, 1], rtol=1e-9)


def test_emitter_values_are_checked():
    with pytest.raises(InputError, match=r"emitter 'lamp': intensity must be a finite number >= 0 W/m\^2, got -1"):
        Emitter("lamp", -1.0)
    with pytest.raises(InputError, match=r"emitter 'lamp': intensity .* got nan"):
        Emitter("lamp", float("nan"))
    with pytest.raises(InputError, match=r"emitter 'lamp': color must be three numbers in \[0, 1\]"):
        Emitter("lamp", 1.0, color=(2.0, 0.0, 0.0))
    with pytest.raises(InputError, match="color must be three numbers"):
        Emitter("lamp", 1.0, color=(1.0, 1.0))
    assert Emitter("lamp", 2, color=[0, 0.5, 1]).color == (0.0, 0.5, 1.0)


def test_glb_is_valid_gltf(fac):
    import trimesh

    colors = MeshColors(fac.scene)
    glb = MeshGLB(colors.vertices, colors.faces)
    c = np.random.default_rng(0).random((len(colors.vertices), 3))
    data = glb.encode(c)
    mesh = trimesh.load(trimesh.util.wrap_as_stream(data), file_type="glb", force="mesh", process=False)
    assert len(mesh.faces) == fac.scene.n_triangles
    with pytest.raises(ValueError, match="shape"):
        glb.encode(c[:-1])


def test_latest_wins_coalesces():
    seen = []
    gate = threading.Event()

    def handle(x):
        gate.wait(5)
        seen.append(x)

    worker = LatestWins(handle)
    worker.submit(0)
    time.sleep(0.05)             # 0 is running, blocked on the gate
    for i in range(1, 100):
        worker.submit(i)         # never blocks; each replaces the one waiting
    gate.set()
    assert worker.wait_idle(5)
    worker.close()
    assert seen == [0, 99] and worker.replaced == 98 and worker.handled == 2


def test_latest_wins_survives_errors():
    errors, seen = [], []

    def handle(x):
        if x == "bad":
            raise RuntimeError("boom")
        seen.append(x)

    worker = LatestWins(handle, lambda req, exc: errors.append((req, str(exc))))
    worker.submit("bad")
    assert worker.wait_idle(5)
    worker.submit("good")
    assert worker.wait_idle(5)
    worker.close()
    assert errors == [("bad", "boom")] and seen == ["good"]


def test_server_survives_bad_clients(fac, tmp_path):
    """Garbage messages and clients that vanish mid-stream leave the server updating and serving."""
    from websockets.sync.client import connect

    from hfrad.viewer import ViewerApp

    app = ViewerApp(fac, port=free_port(), save_dir=tmp_path)
    try:
        assert app.host == "127.0.0.1"
        ws_url = app.url.replace("http", "ws")
        proto = f"viser-v{viser.__version__}"
        for payload in (b"\x00\xff garbage", "not msgpack", b"\x81\xa4type\xa7Nothing", b""):
            ws = connect(ws_url, subprotocols=[proto], open_timeout=10)
            ws.send(payload)
            ws.close()
        ws = connect(ws_url, subprotocols=[proto], open_timeout=10)
        ws.recv(timeout=10)                     # mid-stream: drop the connection without a close frame
        ws.socket.close()
        done = threading.Event()
        app.add_listener(lambda stats: done.set())
        app.set_emitter("light", intensity=30.0)
        assert done.wait(10) and app.wait_idle(10)
        assert app.last.sent < 5.0
        # several tabs at once: two new clients both get the scene, then both get the next change
        tabs = [connect(ws_url, subprotocols=[proto], open_timeout=10, max_size=None) for _ in range(2)]
        for ws in tabs:
            recv_mesh(ws)                                    # the initial scene, mesh included
        app.set_emitter("light", color=(0.2, 0.4, 1.0))    # (auto exposure: an intensity alone changes nothing)
        assert app.wait_idle(10)
        for ws in tabs:
            recv_mesh(ws)                                    # the new colours
            ws.close()
        # a bad emission upload is refused with a message, the state unchanged
        with pytest.raises(FileFormatError, match="emitters\\[0\\].exitance"):
            app.load_emission('{"format": "hfrad-emission", "version": 1, '
                              '"emitters": [{"name": "light", "exitance": [1, 2]}]}')
        with pytest.raises(SceneError, match="no material or group named 'lamp'"):
            app.load_emission('{"format": "hfrad-emission", "version": 1, '
                              '"emitters": [{"name": "lamp", "exitance": [1, 2, 3]}]}')
        assert [e.name for e in app.state.emitters] == ["light"]
    finally:
        app.close()


def test_emission_round_trip_and_png(fac, tmp_path):
    """The page's saved emission reproduces its radiosity through `hfrad solve --emission-file`."""
    from hfrad.io.emission import read_emission
    from hfrad.render.camera import Camera
    from hfrad.viewer import ViewerApp

    hfr = tmp_path / "c.hfr"
    hfrad.save(fac, hfr)
    app = ViewerApp(hfrad.load(hfr), port=free_port(), save_dir=tmp_path)
    try:
        app.add_emitter("green", intensity=4.0)
        with pytest.raises(InputError, match="'green' is already an emitter"):
            app.add_emitter("green")
        with pytest.raises(InputError, match="no emitter named 'blue'; the emitters are 'light', 'green'"):
            app.set_emitter("blue", on=False)
        app.set_emitter("light", color=(1.0, 0.5, 0.5))
        app.set_emitter("green", on=False)
        app.set_emitter("green", on=True)
        assert app.wait_idle(10)
        path = tmp_path / "e.json"
        path.write_text(app.emission_text())
        assert [s.name for s in read_emission(path)] == ["light", "green"]
        out = tmp_path / "b.npz"
        result = CliRunner().invoke(cli_app, ["solve", str(hfr), "-o", str(out), "--emission-file", str(path)])
        assert result.exit_code == 0, result.output
        B_page, E_page = app._shown[0], app._shown[1]
        data = np.load(out)
        assert np.array_equal(data["E"], E_page)
        assert np.abs(data["B"] - B_page).max() <= 1e-5 * np.abs(B_page).max()
        from PIL import Image
        png = app.save_png(Camera.auto(fac.scene.bounds), tmp_path / "v.png", height=48)
        img = np.asarray(Image.open(png))
        assert img.shape == (48, 64, 3) and img.max() > 0
        # false colour in lux: the scale tops the brightest non-emitting vertex, as in pictures
        app.state.falsecolor, app.state.unit = True, "lux"
        app.submit()
        assert app.wait_idle(10)
        unit, top = app._colorbar_key
        lux = 683.0 * app.colors.radiosity(B_page) @ [0.2126, 0.7152, 0.0722]
        lit = E_page.max(axis=1)[app.colors._vertex_patch] <= 0
        assert unit == "lux" and app._colorbar.visible
        assert lux[lit].max() <= top <= 1.4 * lux[lit].max()     # rounded up to a tick (step <= 2/5 of max)
        png = app.save_png(Camera.auto(fac.scene.bounds), tmp_path / "f.png", height=96)
        assert np.asarray(Image.open(png)).shape == (96, 128, 3)
    finally:
        app.close()


def test_cli_refuses_non_factorization(tmp_path):
    bad = tmp_path / "scene.obj"
    bad.write_text("v 0 0 0\n")
    result = CliRunner().invoke(cli_app, ["view", str(bad)])
    assert result.exit_code == 2 and "not a factorization file (.hfr)" in result.output
    fake = tmp_path / "fake.hfr"
    fake.write_bytes(b"not hdf5 at all")
    result = CliRunner().invoke(cli_app, ["view", str(fake)])
    assert result.exit_code == 2 and "fake.hfr" in result.output, result.output


def test_page_error_figure_is_the_factorizations_bound(fac):
    from hfrad.viewer.app import _error_estimate
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        expected = np.asarray(fac.error_estimate().bound, dtype=np.float64)
    got = _error_estimate(fac)
    assert got.shape == (3,)
    np.testing.assert_array_equal(got, expected)
