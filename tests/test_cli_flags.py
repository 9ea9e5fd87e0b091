"""The command line speaks one language: same flags, same meanings, clear exits."""

from __future__ import annotations

import json

import click
import pytest
import typer
from conftest import run_cli as run

from hfrad.cli import app

SCENE_COMMANDS = ("info", "formfactors", "precompute")
SCENE_FLAGS = {"--max-edge", "--patches", "--unit-scale", "--emission", "--area-light", "--default-reflectance",
               "--allow-missing-materials"}



def _flags(command: str) -> dict[str, click.Parameter]:
    group = typer.main.get_command(app)
    out = {}
    for p in group.commands[command].params:
        for name in getattr(p, "opts", []):
            out[name] = p
    return out


def test_scene_loading_commands_share_their_options():
    for command in SCENE_COMMANDS:
        missing = SCENE_FLAGS - set(_flags(command))
        assert not missing, f"hfrad {command} lacks {sorted(missing)}"
    helps = {c: _flags(c)["--emission"].help for c in (*SCENE_COMMANDS, "solve", "render")}
    assert len(set(helps.values())) == 1, helps          # one declaration, one meaning
    assert "--emit" in _flags("precompute") and "--emit" in _flags("solve")   # the old spelling still works


def test_dtype_is_spelled_the_same_everywhere():
    for command in ("formfactors", "precompute"):
        flags = _flags(command)
        assert "--dtype" in flags and "--float32" not in flags


def test_user_errors_exit_2_with_one_line(tmp_path):
    result = run("formfactors", "cornell", "-o", tmp_path / "f.npz", "--dtype", "float16", "--quiet")
    assert result.exit_code == 2
    assert "--dtype must be float32 or float64" in result.output
    assert "Traceback" not in result.output and len(result.output.strip().splitlines()) == 1


def test_internal_errors_keep_their_traceback(monkeypatch, tmp_path):
    import hfrad.scene.load

    def broken(*args, **kwargs):
        raise KeyError("a bug")

    monkeypatch.setattr(hfrad.scene.load, "load_scene", broken)
    result = run("info", "cornell")
    assert result.exit_code == 1
    assert "internal error" in result.output and "report" in result.output
    assert "KeyError" in result.output and "Traceback" in result.output


def test_an_import_error_of_a_broken_install_is_internal(monkeypatch):
    import hfrad.scene.load

    def broken(*args, **kwargs):
        from hfrad.scene import no_such_module  # noqa: F401

    monkeypatch.setattr(hfrad.scene.load, "load_scene", broken)
    result = run("info", "cornell")
    assert result.exit_code == 1 and "internal error" in result.output


def test_allow_missing_materials_on_precompute(tmp_path):
    obj = tmp_path / "tri.obj"
    obj.write_text("mtllib missing.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nusemtl wall\n"
                   "f 1 2 3\nf 1 3 4\nf 1 4 2\nf 2 4 3\n")
    refused = run("precompute", obj, "-o", tmp_path / "t.hfr", "--area-light", "1", "--quiet")
    assert refused.exit_code == 2 and "--allow-missing-materials" in refused.output
    ok = run("precompute", obj, "-o", tmp_path / "t.hfr", "--allow-missing-materials", "--emission", "wall=1",
             "--eps", "0.1", "--quiet")
    assert ok.exit_code == 0, ok.output


def test_solve_json(tmp_path):
    hfr = tmp_path / "c.hfr"
    assert run("precompute", "cornell", "--patches", "200", "--eps", "0.05", "-o", hfr, "--quiet").exit_code == 0
    result = run("solve", hfr, "-o", tmp_path / "b.npz", "--json", "--emit", "light=5")
    assert result.exit_code == 0, result.output
    line = next(l for l in result.output.splitlines() if l.startswith("{"))
    report = json.loads(line)
    for key in ("error_bound", "error_norm", "eq5_bound", "rank", "solve_ms"):
        assert key in report, key
    assert len(report["error_bound"]) == 3 and report["rank"] > 0 and report["solve_ms"] > 0


@pytest.mark.parametrize("command", ["precompute"])
def test_memory_check_states_its_rank_assumption(command, monkeypatch, tmp_path):
    import hfrad.memory

    monkeypatch.setattr(hfrad.memory, "available_bytes", lambda: 1 << 20)
    result = run(command, "cornell", "--patches", "300", "-o", tmp_path / "x.hfr", "--quiet")
    assert result.exit_code == 2 and "assumes a rank" in result.output
