"""Every ```python snippet of README.md and docs/*.md runs, as documented.

The snippets of one file run in order in one namespace (a later snippet may use
an earlier one's names), in a temporary working folder. A file whose snippets
need ../shared/scenes is skipped with that reason when it is absent. A snippet
that needs what a test cannot have (a Dask cluster, a user's building) starts
with a line ``# doc-only: REASON``: it is compiled (its syntax is checked) but
not run.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FILES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
SNIPPET = re.compile(r"^```python\n(.*?)^```", re.S | re.M)


def snippets(path: Path) -> list[str]:
    return SNIPPET.findall(path.read_text(encoding="utf-8"))


def test_the_api_docs_have_snippets():
    assert len(snippets(ROOT / "docs" / "api.md")) >= 5
    assert snippets(ROOT / "README.md")


@pytest.mark.parametrize("path", [p for p in FILES if snippets(p)], ids=lambda p: p.name)
def test_snippets_run(path, tmp_path, monkeypatch):
    code = snippets(path)
    if any("../shared" in c for c in code) and not (ROOT.parent / "shared" / "scenes").exists():
        pytest.skip("needs ../shared/scenes (not in a user's clone)")
    monkeypatch.chdir(tmp_path)
    namespace: dict = {"__name__": f"docs_{path.stem}"}
    for i, c in enumerate(code):
        code_object = compile(c, f"{path.name}[snippet {i + 1}]", "exec")
        if c.startswith("# doc-only:"):
            continue
        try:
            exec(code_object, namespace)
        except Exception as exc:  # name the snippet, keep the traceback
            raise AssertionError(f"{path.name}, python snippet {i + 1} failed: {exc!r}") from exc
