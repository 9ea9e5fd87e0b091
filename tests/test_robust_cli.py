"""Issue 26, items 3, 4, 5 and 8: bad options, memory before work, writing, the headline figure.

Every case here failed on the code before (a traceback, an out-of-memory run,
a hidden temporary name in the message, "guaranteed bound 2.05"); each now
gives one line and exit code 2 before any work, or the figure a user can
rely on first. The cases tried and their outcomes before and after are
listed in the issue's note (cli-writing.md).
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import stat
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

import hfrad
from conftest import run_cli as run
from hfrad.errors import MemoryLimitError

GB = 1 << 30


def one_clear_line(result, *needles):
    """Exit code 2, an 'error:' line with each needle, no traceback and no hidden temporary name."""
    out = result.output
    assert result.exit_code == 2, out
    assert "Traceback" not in out and "internal error" not in out, out
    assert ".tmp" not in out, out
    errors = [line for line in out.splitlines() if line.startswith("error:")]
    assert len(errors) == 1, out
    for needle in needles:
        assert needle in errors[0], out
    return errors[0]


@pytest.fixture(scope="module")
def coarse_hfr(tmp_path_factory):
    """A 62-patch Cornell box at eps 0.02: its a-priori bound is above 100% (284%, 181%, 134%)."""
    path = tmp_path_factory.mktemp("robust") / "coarse.hfr"
    fac = hfrad.factorize(hfrad.load_scene("cornell", patches=60), eps=0.02)
    hfrad.save(fac, path)
    return path


@pytest.fixture
def no_meshing(monkeypatch):
    """Cutting faces into patches fails the test: a refusal must come before it."""
    import hfrad.scene.load as load

    def forbidden(*args, **kwargs):
        raise AssertionError("the scene was cut into patches before the refusal")

    monkeypatch.setattr(load, "subdivide", forbidden)
    monkeypatch.setattr(load, "cluster", forbidden)


@pytest.fixture
def memory_8gb(monkeypatch):
    """8 GB available, whatever the machine has (the refusals below name it)."""
    import hfrad.memory

    monkeypatch.setattr(hfrad.memory, "available_bytes", lambda: 8 * GB)


# -- 3. options ------------------------------------------------------------------------------------

@pytest.mark.parametrize("option, value, needle", [
    ("--emission", "light=1,2", "--emission"),
    ("--emission", "light", "--emission"),
    ("--emission", "light=a,b,c", "--emission"),
    ("--area-light", "1,2", "--area-light"),
    ("--area-light", "1,2,3,4", "--area-light"),
])
def test_malformed_light_options(option, value, needle):
    """Were typer's BadParameter from its own copy of click: 'internal error' and exit 1."""
    line = one_clear_line(run("info", "cornell", option, value), needle, repr(value))
    assert "R,G,B" in line


def test_values_are_printed_as_numbers():
    line = one_clear_line(run("info", "cornell", "--emission", "light=nan"))
    assert "np.float64" not in line and "nan" in line


def test_quoted_values_are_cut_to_about_200_characters():
    line = one_clear_line(run("info", "cornell", "--emission", "light=" + "1," * 5000))
    assert len(line) < 400 and "characters)" in line


@pytest.mark.parametrize("args, needle", [
    (["--processes", "0"], "--processes"),
    (["--processes", "-3"], "--processes"),
    (["--processes", "100000"], "--processes"),
    (["--workers", "100000"], "--workers"),
    (["--scheduler", "nonsense"], "--scheduler"),
    (["--samples", "4000000"], "--samples"),
    (["--refine", "inf"], "--refine"),
    (["--refine", "1.5"], "--refine"),       # a relative jump never exceeds 1: refined nothing, silently
])
def test_precompute_options_refused_before_work(tmp_path, no_meshing, args, needle):
    one_clear_line(run("precompute", "cornell", "--patches", "300", "-q", "-o", tmp_path / "x.hfr", *args), needle)
    assert list(tmp_path.iterdir()) == []


def test_unknown_design_method(coarse_hfr, tmp_path):
    spec = tmp_path / "spec.json"
    spec.write_text(json.dumps({"emitters": [{"name": "light", "material": "light", "max": 1000}],
                                "targets": [{"name": "floor", "group": "floor", "min": 100}]}))
    one_clear_line(run("design", spec, coarse_hfr, "-o", tmp_path / "d.json", "--method", "bogus"),
                   "--method", "auto, forward, adjoint")


def test_design_picture_size_refused_before_the_solves(coarse_hfr, tmp_path, monkeypatch):
    """`hfrad design --render --width 1000000` ran the design's solves first, then refused the picture."""
    import hfrad.inverse

    spec = tmp_path / "spec.json"
    spec.write_text(json.dumps({"emitters": [{"name": "light", "material": "light", "max": 1000}],
                                "targets": [{"name": "floor", "group": "floor", "min": 100}]}))

    def forbidden(*args, **kwargs):
        raise AssertionError("the design solved before the picture size was checked")

    monkeypatch.setattr(hfrad.inverse, "design", forbidden)        # what `hfrad design` calls
    one_clear_line(run("design", spec, coarse_hfr, "-o", tmp_path / "d.json", "--render", tmp_path / "d.png",
                       "--width", "1000000"), "width", "16,384")
    assert list(tmp_path.iterdir()) == [spec]


def test_picture_of_100000_pixels_a_side_is_refused(coarse_hfr, tmp_path):
    t0 = time.perf_counter()
    one_clear_line(run("render", coarse_hfr, "-o", tmp_path / "r.png", "--width", "100000", "--height", "100000"),
                   "width", "16,384")
    assert time.perf_counter() - t0 < 10


def test_picture_larger_than_memory_is_refused(coarse_hfr, tmp_path, memory_8gb):
    """16,000^2 pixels at ~256 B each: 61 GB, refused by memory, not by the side limit."""
    one_clear_line(run("render", coarse_hfr, "-o", tmp_path / "r.png", "--width", "16000", "--height", "16000"),
                   "rendering 16,000 x 16,000 pixels needs about", "available")


@pytest.mark.parametrize("args, needle", [
    (["--exposure", "1e308"], "exposure"),
    (["--falsecolor", "--width", "8", "--height", "8"], "16 x 24"),
    (["--falsecolor", "--width", "100", "--height", "8"], "16 x 24"),
])
def test_render_values_that_broke_the_picture(coarse_hfr, tmp_path, args, needle):
    one_clear_line(run("render", coarse_hfr, "-o", tmp_path / "r.png", *args), needle)


def test_smallest_false_colour_picture_is_drawn(coarse_hfr, tmp_path):
    result = run("render", coarse_hfr, "-o", tmp_path / "r.png", "--falsecolor", "--width", "16", "--height", "24")
    assert result.exit_code == 0, result.output
    from PIL import Image
    assert Image.open(tmp_path / "r.png").size == (16, 24)


def test_json_nested_100000_deep(coarse_hfr, tmp_path):
    """Was RecursionError: 'internal error'."""
    deep = tmp_path / "deep.json"
    deep.write_text("[" * 100_000 + "]" * 100_000)
    one_clear_line(run("solve", coarse_hfr, "-o", tmp_path / "b.npz", "--emission-file", deep),
                   "nested too deeply", str(deep))


def test_deep_spec_files(tmp_path):
    from hfrad.inverse.spec import SpecError, read_spec

    for suffix, text in ((".json", '{"emitters": ' + "[" * 100_000 + "]" * 100_000 + "}"),
                         (".toml", "a = " + "[" * 100_000 + "]" * 100_000)):
        path = tmp_path / f"deep{suffix}"
        path.write_text(text)
        with pytest.raises(SpecError, match="nested too deeply"):
            read_spec(path)


def test_loads_json_points_at_the_depth():
    from hfrad.jsonfile import loads_json

    text = '{"a": "[[[[", "b": ' + "[" * 5000 + "]" * 5000 + "}"
    with pytest.raises(json.JSONDecodeError) as info:
        loads_json(text)
    limit = sys.getrecursionlimit() // 2
    # the outer brace is level 1, the brackets inside the string are not counted
    assert info.value.pos == text.index("[[[[[") + limit - 1
    assert loads_json('{"a": [[1]]}') == {"a": [[1]]}


# -- 4. memory before work -------------------------------------------------------------------------

def test_max_edge_far_too_small_is_refused_before_meshing(tmp_path, no_meshing, memory_8gb):
    """`hfrad precompute cornell --max-edge 1e-4` ran into the OOM killer after 142 s."""
    t0 = time.perf_counter()
    line = one_clear_line(run("precompute", "cornell", "--max-edge", "1e-4", "-q", "-o", tmp_path / "x.hfr"),
                          "at least 6,540,223,849 patches", "needs about", "available")
    assert time.perf_counter() - t0 < 5
    assert "8.0 GB" in line or "6.4 GB" in line        # 80% of the 8 GB


def test_two_million_patches_refused_in_under_a_second(tmp_path, no_meshing, memory_8gb):
    """`--patches 2000000` took 44 s of meshing before the memory check."""
    run("info", "cornell", "--json")                    # imports and the built-in scene, not timed
    t0 = time.perf_counter()
    one_clear_line(run("precompute", "cornell", "--patches", "2000000", "-q", "-o", tmp_path / "x.hfr"),
                   "precomputing about 2,000,000 patches with 120 near-field entries a row needs about")
    assert time.perf_counter() - t0 < 1.0


def test_dense_form_factors_refused_before_meshing(tmp_path, no_meshing):
    one_clear_line(run("formfactors", "cornell", "--patches", "200000", "-q", "-o", tmp_path / "f.npz"),
                   "dense")


def test_demo_refused_before_meshing(tmp_path, no_meshing, memory_8gb):
    one_clear_line(run("demo", "--patches", "2000000", "-q", "-o", tmp_path / "demo"), "2,000,000 patches")


def test_api_load_scene_refuses_with_both_numbers(no_meshing, memory_8gb):
    with pytest.raises(MemoryLimitError, match=r"cutting into at least 6,540,223,849 patches needs about "
                                               r"6\.\d TB but only 6\.4 GB is available"):
        hfrad.load_scene("cornell", max_edge=1e-4)


def test_patch_estimate_is_a_lower_bound_of_the_mesh():
    """area / (sqrt(3)/4 h^2) never exceeds what meshing makes (Cornell box: 1.8 times it at h = 0.3 m, 1.4 at
    0.1 m, 1.14 at 0.01 m: the boundary's share shrinks as patches get smaller)."""
    from hfrad.scene.load import cut_patches, estimate_patch_count

    scene = hfrad.load_scene("cornell")
    for h in (0.3, 0.1):
        estimate = estimate_patch_count(scene, max_edge=h)
        made = cut_patches(scene, max_edge=h).n_patches
        assert estimate <= made <= 2 * estimate, (h, estimate, made)
        assert made == hfrad.load_scene("cornell", max_edge=h).n_patches
    assert estimate_patch_count(scene, patches=1234) == 1234
    assert estimate_patch_count(scene) == scene.n_patches


def test_max_edge_help_states_the_formula():
    result = run("precompute", "--help")
    assert "0.433" in result.output and "max_edge^2" in result.output


# -- 5. writing ------------------------------------------------------------------------------------

@pytest.fixture
def no_factorize(monkeypatch):
    import hfrad.pipeline

    def forbidden(*args, **kwargs):
        raise AssertionError("the precompute ran before the output was checked")

    monkeypatch.setattr(hfrad.pipeline, "factorize", forbidden)


def test_damaged_checkpoint_is_refused_without_resuming(tmp_path):
    """'resuming from checkpoint' was printed before the damaged checkpoint was refused."""
    out = tmp_path / "x.hfr"
    (tmp_path / "x.hfr.partial").write_bytes(b"not an HDF5 file")
    result = run("precompute", "cornell", "--patches", "60", "-q", "-o", out)
    one_clear_line(result, "x.hfr.partial")
    assert "resum" not in result.output
    assert not out.exists()


def test_accepted_checkpoint_is_announced(tmp_path):
    """A checkpoint written by the same command is resumed, and said so once it is accepted."""
    out = tmp_path / "x.hfr"
    partial = tmp_path / "x.hfr.partial"
    scene = hfrad.load_scene("cornell", patches=60)
    # the state after every block but the last (none is written after the last), kept on completion
    hfrad.factorize(scene, eps=0.02, checkpoint=hfrad.Checkpoint(partial, interval=0, keep=True),
                    options=hfrad.PrecomputeOptions(block_size=16))
    assert partial.exists()
    result = run("precompute", "cornell", "--patches", "60", "--block", "16", "-q", "-o", out)
    assert result.exit_code == 0, result.output
    said = [line for line in result.output.splitlines() if line.startswith("resumed from checkpoint")]
    assert said == [f"resumed from checkpoint {partial} (3 column blocks were done)"], result.output
    assert out.exists() and not partial.exists()


def test_missing_folder_refused_before_work(tmp_path, no_factorize):
    target = tmp_path / "nosuch" / "x.hfr"
    one_clear_line(run("precompute", "cornell", "--patches", "60", "-q", "-o", target), str(target), "does not exist")


def test_output_that_is_a_directory(tmp_path, no_factorize, coarse_hfr):
    (tmp_path / "out.hfr").mkdir()
    one_clear_line(run("precompute", "cornell", "--patches", "60", "-q", "-o", tmp_path / "out.hfr"),
                   str(tmp_path / "out.hfr"), "is a directory")
    (tmp_path / "b.npz").mkdir()
    one_clear_line(run("solve", coarse_hfr, "-o", tmp_path / "b.npz"), "is a directory")


def test_read_only_folder(tmp_path, monkeypatch, coarse_hfr):
    """Simulated (root may write anywhere): creating any file there fails with EROFS."""
    import hfrad.atomic

    def read_only(path):
        raise OSError(errno.EROFS, "Read-only file system", str(path))

    monkeypatch.setattr(hfrad.atomic, "new_file", read_only)
    one_clear_line(run("solve", coarse_hfr, "-o", tmp_path / "b.npz"), str(tmp_path / "b.npz"), "read-only")
    one_clear_line(run("demo", "--patches", "60", "-q", "-o", tmp_path / "demo"), "read-only")


def test_demo_output_that_is_a_file(tmp_path):
    (tmp_path / "f").write_text("x")
    one_clear_line(run("demo", "--patches", "60", "-q", "-o", tmp_path / "f"), "not a folder")


def test_no_space_while_writing_is_one_line(tmp_path, monkeypatch, coarse_hfr):
    """ENOSPC from the rename (simulated): 'no space left on device writing X', exit 2, nothing left."""
    import hfrad.atomic

    def full(tmp, path):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(hfrad.atomic, "publish", full)
    target = tmp_path / "b.npz"
    one_clear_line(run("solve", coarse_hfr, "-o", target), f"no space left on device writing {target}")
    assert list(tmp_path.iterdir()) == []


def test_atomic_write_error_names_the_target(tmp_path):
    from hfrad.errors import WriteError

    target = tmp_path / "a.bin"
    with pytest.raises(WriteError, match=f"no space left on device writing {target}$") as info:
        with hfrad.atomic.atomic_path(target) as tmp:
            tmp.write_bytes(b"half")
            raise OSError(errno.ENOSPC, "No space left on device", str(tmp))
    assert info.value.errno == errno.ENOSPC and isinstance(info.value, OSError)
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(WriteError, match="needs about 1.0 TB"):   # the HDF5 writers' check before writing
        with hfrad.atomic.atomic_path(target, size=1 << 40):
            pass


def test_stale_temporaries_of_the_target_are_removed(tmp_path):
    from hfrad.atomic import _RUN_START, atomic_path

    target = tmp_path / "out.png"
    stale = tmp_path / ".out.png.deadbeef.tmp"      # a killed earlier run's
    fresh = tmp_path / ".out.png.0123abcd.tmp"      # a concurrent writer's, newer than this run
    other = tmp_path / ".other.png.deadbeef.tmp"    # another target's
    mine = tmp_path / ".out.png.notmine.tmp"        # not a name the writer makes
    for p in (stale, fresh, other, mine):
        p.write_bytes(b"x")
    old = _RUN_START - 3600
    for p in (stale, other, mine):
        os.utime(p, (old, old))
    os.utime(fresh, (_RUN_START + 1, _RUN_START + 1))
    with atomic_path(target) as tmp:
        tmp.write_bytes(b"png")
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([target.name, fresh.name, other.name, mine.name])


def test_overwritten_file_takes_the_umask_mode(tmp_path, coarse_hfr):
    target = tmp_path / "b.npz"
    target.write_bytes(b"old")
    os.chmod(target, 0o600)
    old = os.umask(0o022)
    try:
        result = run("solve", coarse_hfr, "-o", target)
    finally:
        os.umask(old)
    assert result.exit_code == 0, result.output
    assert stat.S_IMODE(os.stat(target).st_mode) == 0o644
    assert np.load(target)["B"].shape[1] == 3


def _mount_tiny_tmpfs(where: Path) -> bool:
    if os.geteuid() != 0 or shutil.which("mount") is None:
        return False
    where.mkdir()
    return subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(where)],
                          capture_output=True).returncode == 0


def test_full_disk_precompute_is_one_line_and_leaves_nothing(tmp_path):
    """A real 64 KB tmpfs (root only): the .hfr does not fit. h5py crashed the process on closing a file after
    ENOSPC (segmentation fault, exit 139); now one line, exit 2, no temporary left."""
    full = tmp_path / "full"
    if not _mount_tiny_tmpfs(full):
        pytest.skip("needs root and `mount -t tmpfs` to make a small file system")
    try:
        target = full / "x.hfr"
        done = subprocess.run([sys.executable, "-m", "hfrad", "precompute", "cornell", "--patches", "60", "-q",
                               "-o", str(target)], capture_output=True, text=True, timeout=300)
        assert done.returncode == 2, (done.returncode, done.stdout, done.stderr)
        assert f"no space left on device writing {target}" in done.stderr, done.stderr
        assert "Traceback" not in done.stderr
        assert list(full.iterdir()) == []
    finally:
        subprocess.run(["umount", str(full)], capture_output=True)


def test_full_disk_api_save_and_checkpoint_refused_cleanly(tmp_path):
    """The API's hfrad.save and the stream's checkpoint on a real 64 KB tmpfs: a WriteError naming the file,
    nothing left (hfrad.save ran h5py into ENOSPC, which crashes the process on closing the file)."""
    full = tmp_path / "full"
    if not _mount_tiny_tmpfs(full):
        pytest.skip("needs root and `mount -t tmpfs` to make a small file system")
    script = textwrap.dedent(f"""
        import warnings
        import numpy as np
        import hfrad
        from hfrad.errors import WriteError
        from hfrad.lowrank.hf import HFStream
        from hfrad.lowrank.streaming import save_checkpoint
        warnings.simplefilter("ignore")
        fac = hfrad.factorize(hfrad.load_scene("cornell", patches=300), eps=0.05)
        stream = HFStream(4096, 16, eps=0.05)
        for j in range(3):
            stream.push(np.random.default_rng(j).random((4096, 256)))
        for write in (lambda: hfrad.save(fac, {str(full / "x.hfr")!r}),
                      lambda: save_checkpoint(stream, {str(full / "x.partial")!r})):
            try:
                write()
            except WriteError as exc:
                print("refused:", exc)
        """)
    try:
        done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, (done.returncode, done.stderr)
        assert done.stdout.count("refused: no space left on device writing") == 2, done.stdout
        assert list(full.iterdir()) == []
    finally:
        subprocess.run(["umount", str(full)], capture_output=True)


# -- 8. the headline figure ------------------------------------------------------------------------

def test_solve_prints_its_own_figure_first_then_no_useful_bound(coarse_hfr, tmp_path):
    """Was 'bound on the relative radiosity error ...: 2.84, 1.81, 1.34 (guaranteed ...)' after the 'wrote' line;
    then 'no useful a-priori bound' first (issue 10); now this solve's own figure first (issue 42)."""
    result = run("solve", coarse_hfr, "-o", tmp_path / "b.npz")
    assert result.exit_code == 0, result.output
    lines = result.output.splitlines()
    assert lines[0].startswith("error of this solution: at most "), result.output
    assert "of the reflected light" in lines[0] and "row" in lines[0] and "of F" in lines[0]
    priori = next(line for line in lines if "a-priori" in line)
    assert priori.startswith("no useful a-priori bound on the relative radiosity error"), result.output
    assert "--residual" in priori and "--eps" in priori
    assert "2.84" not in result.output


def test_solve_with_residual_prints_both_figures_of_the_solution_first(coarse_hfr, tmp_path):
    result = run("solve", coarse_hfr, "-o", tmp_path / "b.npz", "--residual", "-q")
    assert result.exit_code == 0, result.output
    lines = result.output.splitlines()
    first = lines[0]
    assert first.startswith("error of this solution: at most "), result.output
    second = next(line for line in lines if line.startswith("guaranteed bound of this solution (--residual): "))
    for line in (first, second):
        text = line.split("at most ")[1].split("(")[0].replace("of the reflected light", "")
        figures = [float(x.strip().rstrip("%")) / 100 for x in text.split(",")]
        assert len(figures) == 3 and all(0 < f < 1 for f in figures)


def test_accuracy_lines_never_call_a_bound_above_100_percent_guaranteed():
    from hfrad.solve.bounds import accuracy_lines, estimate_errors

    est = estimate_errors(0.02, [0.9, 0.9, 0.9], operator_error=[0.2, 0.2, 0.2], contraction=[0.85, 0.85, 0.85],
                          norm="area", failure_probability=1e-6)
    assert est.bound[0] > 1                                    # 0.2 / 0.15 = 1.33 -> inf-free but useless
    lines = accuracy_lines(est, achieved_error=0.02)
    assert lines[0].startswith("no useful a-priori bound")
    # delta = 0.1 / 1.1 = 0.0909 needs operator error 0.0909 * 0.15 = 0.0136: eps 0.02 * 0.0136 / 0.2
    assert "--eps 0.0014" in lines[0]
    good = estimate_errors(0.02, [0.5] * 3, operator_error=[0.01] * 3, contraction=[0.5] * 3, norm="area",
                           failure_probability=1e-6)
    assert accuracy_lines(good)[0].startswith("a-priori bound on the relative radiosity error of any solve: "
                                              "at most 2.04%")
    hopeless = estimate_errors(0.02, [0.9] * 3, operator_error=[0.1] * 3, contraction=[1.2] * 3, norm="area",
                               failure_probability=1e-6)
    assert "no eps gives an a-priori bound" in accuracy_lines(hopeless, achieved_error=0.02)[0]


def test_demo_prints_each_solutions_figure_without_a_second_pass(tmp_path, monkeypatch):
    """The demo computed the solution's residual (the form factors again, doubling its time); then it
    printed the command that gives the guaranteed figure; now each solution's figure comes first, from the
    rows of F kept during the pass (issue 42), and the form factors are still never recomputed."""
    from hfrad.solve.woodbury import HFactorization

    def forbidden(*args, **kwargs):
        raise AssertionError("the demo recomputed the form factors for a residual")

    monkeypatch.setattr(HFactorization, "residual", forbidden)
    result = run("demo", "--patches", "60", "-q", "-o", tmp_path)
    assert result.exit_code == 0, result.output
    lines = result.output.splitlines()
    assert lines[0].startswith("Cornell box:")
    # 60 patches: every row of F is kept, so the figure is a bound
    assert lines[1].startswith("error of this solution: at most ") and "every row of F is stored" in lines[1], lines
    assert "a-priori bound on the relative radiosity error" in lines[2], result.output
    assert any(line.startswith("relit blue: error of this solution: at most ") for line in lines), result.output


def test_bad_near_field_refused_before_meshing(tmp_path, no_meshing):
    """`--near-field none` was refused only after the scene was read, cleaned and clustered."""
    one_clear_line(run("precompute", "cornell", "--patches", "300", "--near-field", "none", "-o", tmp_path / "x.hfr"),
                   "--near-field", "'none'")
    assert not (tmp_path / "x.hfr").exists()
