"""The examples' README commands write into their output folder (out/), never over committed files."""

from __future__ import annotations

import re
import shlex
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
READMES = sorted((ROOT / "examples").glob("*/README.md"))
#: Options of hfrad commands that name a file or folder to write.
WRITES = {"-o", "--output", "--plan", "--render", "--emission-out", "--csv"}


def _commands(readme: Path) -> list[list[str]]:
    """hfrad and python command lines of the README's bash blocks (continuations joined, comments cut)."""
    blocks = re.findall(r"```bash\n(.*?)```", readme.read_text(encoding="utf-8"), flags=re.S)
    out = []
    for line in "\n".join(blocks).replace("\\\n", " ").splitlines():
        line = line.split("#", 1)[0].strip()
        if line.startswith(("hfrad ", "python ")):
            out.append(shlex.split(line))
    return out


def _committed(folder: Path) -> set[str]:
    try:
        names = subprocess.run(["git", "ls-files", "."], cwd=folder, capture_output=True, text=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("needs git and a checkout")
    return set(names.split())


@pytest.mark.parametrize("readme", READMES, ids=lambda p: p.parent.name)
def test_readme_commands_write_into_out(readme):
    commands = _commands(readme)
    assert any(c[0] == "hfrad" for c in commands)
    committed = _committed(readme.parent)
    targets = [c[i + 1] for c in commands for i, a in enumerate(c[:-1]) if a in WRITES]
    assert targets
    for t in targets:
        assert t == "out" or t.startswith("out/"), f"{readme.parent.name}: writes {t} outside out/"
        assert t not in committed
    # scripts that regenerate committed inputs are not run by the example (commented out)
    assert not [c for c in commands if c[0] == "python" and c[1].startswith("make_")]
