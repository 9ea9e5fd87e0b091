"""Every ```python snippet of README.md and the documentation (docs/**/*.md) runs, as documented.

The snippets of one file run in order in one namespace (a later snippet may use
an earlier one's names), in a temporary working folder that holds a link to the
repository's ``examples/`` (the tutorials read ``examples/office/...`` as a
user's clone has it). A file whose snippets need ../shared/scenes is skipped with
that reason when it is absent. A snippet that needs what a test cannot have (a
Dask cluster, a user's building) starts with a line ``# doc-only: REASON``: it is
compiled (its syntax is checked) but not run. Pages whose snippets take more
than a few seconds (a clustered mesh, worker processes) are marked slow
(``SLOW``) and run with ``pytest -m slow``.
"""

from __future__ import annotations

import re
import tempfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
FILES = [ROOT / "README.md",
         *sorted(p for p in DOCS.rglob("*.md") if "_build" not in p.relative_to(DOCS).parts)]
SNIPPET = re.compile(r"^```python\n(.*?)^```", re.S | re.M)
# pages whose snippets take tens of seconds on two cores: numba's clustered kernel compiled
# for an 8K-triangle mesh; a LocalCluster of worker processes; a 400-patch office with a design
SLOW = {"tutorials/real-mesh.md", "tutorials/cluster-run.md", "tutorials/inverse-design.md"}
TUTORIALS = ("real-mesh", "relighting", "inverse-design", "cluster-run")


def snippets(path: Path) -> list[str]:
    return SNIPPET.findall(path.read_text(encoding="utf-8"))


def _name(path: Path) -> str:
    return path.relative_to(DOCS).as_posix() if path.is_relative_to(DOCS) else path.name


def test_the_api_docs_have_snippets():
    assert len(snippets(DOCS / "api.md")) >= 5
    assert snippets(ROOT / "README.md")


def test_every_tutorial_has_code_that_runs():
    for name in TUTORIALS:
        code = [c for c in snippets(DOCS / "tutorials" / f"{name}.md") if not c.startswith("# doc-only:")]
        assert code, f"tutorials/{name}.md has no python snippet that the tests run"


def test_no_page_points_outside_the_repository():
    """A user's clone has no ../shared: pages name public scenes by their source instead."""
    for path in FILES + [ROOT / "benchmarks" / "README.md"]:
        text = path.read_text(encoding="utf-8")
        assert "../shared" not in text and "/work/" not in text, path


def test_the_readme_links_and_pictures_resolve():
    """The README is read on a forge, not built by Sphinx: its relative links are checked here."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    targets = re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text)
    local = [t for t in targets if "://" not in t]
    assert len(local) >= 8, local
    missing = [t for t in local if not (ROOT / t).exists()]
    assert not missing, missing


def _cases():
    for path in FILES:
        if not snippets(path):
            continue
        marks = [pytest.mark.slow] if _name(path) in SLOW else []
        yield pytest.param(path, marks=marks, id=_name(path))


@pytest.mark.parametrize("path", list(_cases()))
def test_snippets_run(path, tmp_path, monkeypatch):
    code = snippets(path)
    if any("../shared" in c for c in code) and not (ROOT.parent / "shared" / "scenes").exists():
        pytest.skip("needs ../shared/scenes (not in a user's clone)")
    (tmp_path / "examples").symlink_to(ROOT / "examples", target_is_directory=True)
    monkeypatch.chdir(tmp_path)
    # a snippet's tempfile.mkdtemp() (as a user would write it) lands in this test's folder, not in /tmp
    # for good: a run of the suite left one folder with a .hfr behind each time
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    namespace: dict = {"__name__": f"docs_{path.stem}"}
    for i, c in enumerate(code):
        code_object = compile(c, f"{_name(path)}[snippet {i + 1}]", "exec")
        if c.startswith("# doc-only:"):
            continue
        try:
            exec(code_object, namespace)
        except Exception as exc:  # name the snippet, keep the traceback
            raise AssertionError(f"{_name(path)}, python snippet {i + 1} failed: {exc!r}") from exc
