"""``hfrad precompute --scheduler/--workers``: a cluster started by hand, an unreachable one, Ctrl-C."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from conftest import default_sigint
from hfrad import DaskBackend, PrecomputeOptions
import hfrad
from hfrad.cli import app
from hfrad.solve.hfr import load_hfr, read_hfr_metadata
from hfrad.pipeline import factorize
from hfrad.scene.load import load_scene

SRC = str(Path(hfrad.__file__).resolve().parents[1])
ENV = {**os.environ, "PYTHONPATH": SRC + os.pathsep + os.environ.get("PYTHONPATH", "")}
runner = CliRunner()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait_for(path: Path, text: str, proc: subprocess.Popen, seconds: float) -> None:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        if path.exists() and text in path.read_text(errors="replace"):
            return
        if proc.poll() is not None:
            raise AssertionError(f"{proc.args} exited early:\n{path.read_text(errors='replace')}")
        time.sleep(0.2)
    raise AssertionError(f"{text!r} did not appear in {path} within {seconds} s:\n{path.read_text(errors='replace')}")


@pytest.fixture
def hand_made_cluster(tmp_path):
    """`dask scheduler` and two `dask worker` processes started from the command line, as in docs/cluster.md."""
    address = f"tcp://127.0.0.1:{_free_port()}"
    procs = []
    try:
        log = tmp_path / "scheduler.log"
        procs.append(subprocess.Popen(["dask", "scheduler", "--host", "127.0.0.1", "--port", address.rsplit(":", 1)[1],
                                       "--no-dashboard"], stdout=subprocess.DEVNULL, stderr=log.open("w"), env=ENV))
        _wait_for(log, "Scheduler at", procs[0], 30)
        for i in range(2):
            wlog = tmp_path / f"worker{i}.log"
            procs.append(subprocess.Popen(["dask", "worker", address, "--nthreads", "1", "--no-dashboard",
                                           "--name", f"w{i}"], stdout=subprocess.DEVNULL, stderr=wlog.open("w"),
                                          env=ENV))
        for i in range(2):
            _wait_for(tmp_path / f"worker{i}.log", "Registered to", procs[1 + i], 30)
        yield address
    finally:
        for p in reversed(procs):  # test processes: no graceful shutdown needed
            p.kill()
            p.wait(10)


def test_precompute_on_a_scheduler_started_by_hand(hand_made_cluster, tmp_path):
    out = tmp_path / "cornell.hfr"
    result = runner.invoke(app, ["precompute", "cornell", "--patches", "600", "--block", "64", "-o", str(out),
                                 "--scheduler", hand_made_cluster])
    assert result.exit_code == 0, result.output
    assert f"the Dask scheduler at {hand_made_cluster} (2 workers)" in result.output
    meta = read_hfr_metadata(out)
    assert meta["parameters"]["backend"] == "dask" and meta["parameters"]["workers"] == 2
    assert meta["timings"]["time_formfactors"] > 0 and meta["achieved_error"] <= 0.02 * meta["norm"]
    fac = load_hfr(out)
    scene = load_scene("cornell", patches=600)
    local = factorize(scene, eps=0.02, options=PrecomputeOptions(block_size=64))
    B, B_local = fac.solve(scene.emission), local.solve(scene.emission)
    assert fac.rank == local.rank
    assert np.allclose(B, B_local, rtol=1e-4, atol=1e-6 * np.abs(B_local).max())


def test_hierarchical_precompute_on_a_scheduler(hand_made_cluster, tmp_path):
    """--far-field hierarchical on Dask: the workers build the H-matrix, the client factors it; the
    checkpoint folder beside the output is gone once the .hfr is written."""
    out = tmp_path / "cornell.hfr"
    result = runner.invoke(app, ["precompute", "cornell", "--patches", "600", "--eps", "0.05", "--far-field",
                                 "hierarchical", "-o", str(out), "--scheduler", hand_made_cluster])
    assert result.exit_code == 0, result.output
    assert "far field hierarchical:" in result.output
    meta = read_hfr_metadata(out)
    assert meta["parameters"]["backend"] == "dask" and meta["parameters"]["workers"] == 2
    assert meta["parameters"]["far_field"] == "hierarchical"
    assert not out.with_name(out.name + ".partial.d").exists()


def test_unreachable_scheduler_exits_2(tmp_path):
    import dask

    address = f"tcp://127.0.0.1:{_free_port()}"
    out = tmp_path / "x.hfr"
    with dask.config.set({"distributed.comm.timeouts.connect": "1s"}):
        result = runner.invoke(app, ["precompute", "furnace", "-o", str(out), "--scheduler", address])
    assert result.exit_code == 2
    assert f"cannot reach the Dask scheduler at {address}" in result.output
    assert "Traceback" not in result.output and not out.exists()


@pytest.mark.parametrize("args, message", [
    (["--scheduler", "tcp://127.0.0.1:1", "--workers", "2"], "not both"),
    (["--workers", "2", "--processes", "2"], "--processes is for the in-process path"),
])
def test_conflicting_options_are_refused(tmp_path, args, message):
    result = runner.invoke(app, ["precompute", "furnace", "-o", str(tmp_path / "x.hfr"), *args])
    assert result.exit_code == 2 and message in result.output
    assert not (tmp_path / "x.hfr").exists()


@pytest.fixture(scope="module")
def dask_hfr(tmp_path_factory):
    """A Dask-made .hfr with the near field (forced on at 400 patches).

    Made on an in-process LocalCluster and saved as the CLI saves it: worker processes
    start in seconds but compile the form-factor kernel again (~100 s under this machine's
    load), which the slow test below and the scheduler test above pay for the CLI path.
    """
    from hfrad.distributed import connect
    from hfrad.solve.hfr import save_hfr

    out = tmp_path_factory.mktemp("dask") / "d.hfr"
    scene = load_scene("cornell", patches=400)
    with connect(workers=1, processes=False) as cluster:
        fac = factorize(scene, eps=0.02, near_field=32, backend=DaskBackend(scheduler=cluster),
                        options=PrecomputeOptions(block_size=64))
    save_hfr(fac, out)
    return out


def test_solve_render_view_design_work_on_a_dask_hfr(dask_hfr, tmp_path):
    """The reported bug: `hfrad solve` of a Dask-made file died in the error figures (exit 1)."""
    import json

    from hfrad.viewer import ViewerApp

    meta = read_hfr_metadata(dask_hfr)
    assert meta["parameters"]["backend"] == "dask" and meta["solver"] == "woodbury+neumann(I - D_c N)"
    solved = runner.invoke(app, ["solve", str(dask_hfr), "-o", str(tmp_path / "B.npz"), "--json"])
    assert solved.exit_code == 0, solved.output
    report = json.loads(solved.output.strip().splitlines()[-1])
    assert report["a_priori_kind"] == "probes" and report["a_priori_norm"] == "area"
    assert report["a_priori_failure_probability"] == pytest.approx(1e-6)
    # the per-solve figure from the rows of F the Dask pass kept
    assert report["error_bound_kind"] in ("sampled", "exact-rows") and report["error_norm"] == "reflected"
    assert all(b is not None and 0 < b < 1 for b in report["error_bound"])
    words = runner.invoke(app, ["solve", str(dask_hfr), "-o", str(tmp_path / "B2.npz")])
    assert words.exit_code == 0 and "Traceback" not in words.output and "wrote" in words.output, words.output
    fac = load_hfr(dask_hfr)
    B = np.load(tmp_path / "B.npz")["B"]
    assert np.allclose(B, fac.solve(fac.scene.emission), rtol=1e-5, atol=1e-6 * np.abs(B).max())

    png = tmp_path / "r.png"
    rendered = runner.invoke(app, ["render", str(dask_hfr), "-o", str(png), "--width", "48", "--height", "32"])
    assert rendered.exit_code == 0 and png.stat().st_size > 0, rendered.output

    spec = tmp_path / "spec.json"
    spec.write_text(json.dumps({"emitters": [{"name": "light", "material": "light", "max": 1000.0}],
                                "targets": [{"name": "floor", "group": "floor", "quantity": "irradiance_lux",
                                             "min": 100.0}]}))
    designed = runner.invoke(app, ["design", str(spec), str(dask_hfr), "-o", str(tmp_path / "d.json"), "--quiet"])
    assert designed.exit_code == 0, designed.output
    assert json.loads((tmp_path / "d.json").read_text())["feasible"]

    port = _free_port()
    viewer = ViewerApp(fac, port=port, save_dir=tmp_path)   # what `hfrad view` serves, without a browser
    try:
        assert viewer.wait_idle(30)
        assert np.allclose(viewer._shown[0], B, rtol=1e-4, atol=1e-6 * np.abs(B).max())
    finally:
        viewer.close()


@pytest.mark.slow
def test_the_reported_commands(tmp_path):
    """`hfrad precompute cornell --patches 3000 --workers 2 -o d.hfr` then `hfrad solve d.hfr -o B.npz` (issue 27)."""
    out = tmp_path / "d.hfr"
    made = runner.invoke(app, ["precompute", "cornell", "--patches", "3000", "--workers", "2", "-o", str(out)])
    assert made.exit_code == 0, made.output
    solved = runner.invoke(app, ["solve", str(out), "-o", str(tmp_path / "B.npz")])
    assert solved.exit_code == 0, solved.output
    assert "Traceback" not in solved.output and "wrote" in solved.output


@pytest.mark.slow
def test_ctrl_c_leaves_no_output(tmp_path):
    """SIGINT while the LocalCluster works: the command stops and no .hfr (nor a temporary file) is left."""
    out = tmp_path / "big.hfr"
    log = tmp_path / "stderr.log"
    proc = subprocess.Popen([sys.executable, "-m", "hfrad", "precompute", "cornell", "--patches", "3000",
                             "--block", "32", "--workers", "1", "-o", str(out)],
                            stdout=subprocess.DEVNULL, stderr=log.open("w"), env={**ENV, "COLUMNS": "200"},
                            preexec_fn=default_sigint)
    try:
        _wait_for(log, "running on 1 local worker", proc, 60)
        time.sleep(4.0)  # the cluster is up and the blocks are being computed
        proc.send_signal(signal.SIGINT)
        rc = proc.wait(30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert rc != 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["stderr.log"], list(tmp_path.iterdir())
