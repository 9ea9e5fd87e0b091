"""The layer rule of docs/architecture.md, enforced on every import in the package.

Every module of ``src/hfrad`` is parsed (not imported); every ``import`` and
``from ... import`` statement counts, wherever it is (module level, inside a
function, under ``if TYPE_CHECKING``), relative imports resolved. A module may
import its own package and any package of a strictly lower layer; anything
else (a higher layer, or a different package on the same layer) fails, naming
the file, the line and the rule.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"
PACKAGE = SRC / "hfrad"

#: (layer, unit, module prefixes), lowest first. Keep in step with docs/architecture.md.
LAYERS: list[tuple[int, str, tuple[str, ...]]] = [
    (0, "base", ("hfrad._version", "hfrad.errors", "hfrad.progress", "hfrad.memory", "hfrad.atomic",
                 "hfrad.validation", "hfrad.defaults", "hfrad.jsonfile", "hfrad.resources", "hfrad.integrity")),
    (1, "scene", ("hfrad.scene",)),
    (2, "formfactors", ("hfrad.formfactors",)),
    (3, "lowrank", ("hfrad.lowrank",)),
    (4, "solve", ("hfrad.solve",)),
    (5, "precompute", ("hfrad.precompute",)),
    (6, "distributed", ("hfrad.distributed",)),
    (7, "pipeline", ("hfrad.pipeline",)),
    (7, "render", ("hfrad.render",)),
    (8, "io", ("hfrad.io",)),
    (8, "lighting", ("hfrad.lighting",)),
    (9, "viewer", ("hfrad.viewer",)),
    (9, "inverse", ("hfrad.inverse",)),
    (9, "daylight", ("hfrad.daylight",)),
    (10, "cli", ("hfrad.cli", "hfrad.__main__")),
    (11, "api", ("hfrad",)),          # hfrad/__init__.py: the public facade, lazily importing everything
]


def unit_of(module: str) -> tuple[int, str] | None:
    """(layer, unit) of a dotted module name: the longest matching prefix."""
    best = None
    for layer, unit, prefixes in LAYERS:
        for p in prefixes:
            if module == p or module.startswith(p + "."):
                if best is None or len(p) > best[0]:
                    best = (len(p), layer, unit)
    return None if best is None else (best[1], best[2])


def module_name(path: Path) -> str:
    parts = list(path.relative_to(SRC).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def imported_modules(path: Path, text: str | None = None) -> list[tuple[int, str]]:
    """(line, absolute module) for every hfrad import in ``path``, relative ones resolved.

    ``from pkg import name`` yields ``pkg.name`` when that is a module or
    package of hfrad, else ``pkg``. ``text`` replaces the file's content (for
    testing the checker itself).
    """
    name = module_name(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = []
    text = path.read_text() if text is None else text
    for node in ast.walk(ast.parse(text, filename=str(path))):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names if a.name.split(".")[0] == "hfrad"]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base_parts = package.split(".")
                if node.level > 1:
                    base_parts = base_parts[:len(base_parts) - (node.level - 1)]
                base = ".".join(base_parts + ([node.module] if node.module else []))
            else:
                base = node.module or ""
            if base.split(".")[0] != "hfrad":
                continue
            for a in node.names:
                sub = f"{base}.{a.name}"
                out.append((node.lineno, sub if _is_module(sub) else base))
    return out


def _is_module(dotted: str) -> bool:
    rel = Path(*dotted.split("."))
    return (SRC / rel).with_suffix(".py").exists() or (SRC / rel / "__init__.py").exists()


def all_modules() -> list[Path]:
    return sorted(PACKAGE.rglob("*.py"))


def test_every_module_has_a_layer():
    missing = [module_name(p) for p in all_modules() if unit_of(module_name(p)) is None]
    assert not missing, (f"modules without a layer: {missing}; add them to LAYERS here and to the "
                         "table in docs/architecture.md")


def violations() -> list[str]:
    found = []
    for path in all_modules():
        src = module_name(path)
        src_layer, src_unit = unit_of(src)
        for line, target in imported_modules(path):
            tgt = unit_of(target)
            if tgt is None:
                found.append(f"{path.relative_to(SRC)}:{line}: imports {target}, which has no layer")
                continue
            tgt_layer, tgt_unit = tgt
            if tgt_unit == src_unit or tgt_layer < src_layer:
                continue
            why = "a higher layer" if tgt_layer > src_layer else "another package on the same layer"
            found.append(f"{path.relative_to(SRC)}:{line}: {src} ({src_unit}, layer {src_layer}) imports "
                         f"{target} ({tgt_unit}, layer {tgt_layer}): {why}")
    return found


def test_no_import_goes_up_the_layers():
    found = violations()
    assert not found, "imports against docs/architecture.md:\n" + "\n".join(found)


@pytest.mark.parametrize("source, expected", [
    ("from ..solve.woodbury import HFactorization\n", "hfrad.solve.woodbury"),
    ("from .. import solve\n", "hfrad.solve"),
    ("def f():\n    import hfrad.render.image\n", "hfrad.render.image"),
    ("if TYPE_CHECKING:\n    from hfrad.cli import common\n", "hfrad.cli.common"),
    ("from . import hf\n", "hfrad.lowrank.hf"),
])
def test_the_checker_sees_relative_and_lazy_imports(source, expected):
    # as if the text were hfrad/lowrank/api.py
    found = [t for _, t in imported_modules(PACKAGE / "lowrank" / "api.py", text=source)]
    assert found == [expected]


# -- no import cycles ---------------------------------------------------------------------------

#: Import cycles tolerated for now, each a frozenset of module names with the reason. Keep empty
#: if you can: a cycle means neither module can be read, tested or replaced without the other.
ALLOWED_CYCLES: dict[frozenset[str], str] = {
    # HFactorization.save() (woodbury) lazily calls hfr.save_hfr, and hfr reads files back into
    # HFactorization and NearFieldFactorization (nearfield, a subclass of woodbury's class).
    # Breaking it means moving .save() out of the public class (or a writer registry): an API
    # change, not a file move. Lazy import, so no import-time failure.
    frozenset({"hfrad.solve.hfr", "hfrad.solve.nearfield", "hfrad.solve.woodbury"}):
        "HFactorization.save() writes through hfr, which builds both factorization classes",
}


def import_graph() -> dict[str, set[str]]:
    """Module -> the hfrad modules it imports (every import, lazy ones too; self-imports dropped)."""
    graph = {module_name(p): set() for p in all_modules()}
    for path in all_modules():
        src = module_name(path)
        graph[src] |= {t for _, t in imported_modules(path) if t != src and t in graph}
    return graph


def strongly_connected(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of ``graph`` (Tarjan's algorithm, iterative), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out = []
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            v, children = work[-1]
            for w in children:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                    break
                if w in on_stack:
                    low[v] = min(low[v], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    comp = []
                    while True:
                        w = stack.pop()
                        on_stack.discard(w)
                        comp.append(w)
                        if w == v:
                            break
                    out.append(sorted(comp))
    return out


def import_cycles() -> list[list[str]]:
    return sorted(c for c in strongly_connected(import_graph()) if len(c) > 1)


def test_no_import_cycles():
    cycles = [c for c in import_cycles() if frozenset(c) not in ALLOWED_CYCLES]
    assert not cycles, ("modules that import each other (directly or through others; lazy imports "
                        "count): " + "; ".join(" <-> ".join(c) for c in cycles)
                        + ". Move what both need into a module of its own (docs/architecture.md)")


def test_allowed_cycles_still_exist():
    # an entry whose cycle is gone must leave the list, so the list never hides a new cycle
    stale = [sorted(c) for c in ALLOWED_CYCLES if c not in {frozenset(x) for x in import_cycles()}]
    assert not stale, f"cycles allowed in ALLOWED_CYCLES but no longer present: {stale}"


@pytest.mark.parametrize("graph, expected", [
    ({"a": {"b"}, "b": {"a"}, "c": {"a"}}, [["a", "b"]]),
    ({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": set()}, [["a", "b", "c"]]),
    ({"a": {"b"}, "b": {"c"}, "c": set()}, []),
])
def test_the_cycle_finder_finds_cycles(graph, expected):
    assert sorted(c for c in strongly_connected(graph) if len(c) > 1) == expected


# -- the table of docs/architecture.md says what LAYERS says ------------------------------------

DOC = SRC.parent / "docs" / "architecture.md"


def doc_layers() -> set[tuple[int, str]]:
    """(layer, unit) of every row of the table in docs/architecture.md (units as in LAYERS)."""
    import re

    named = {"base modules": "base", "`hfrad/__init__.py`": "api", "`__main__.py`": "cli"}
    rows = set()
    for line in DOC.read_text().splitlines():
        m = re.match(r"\|\s*(\d+)\s*\|\s*([^|]+?)\s*\|", line)
        if m:
            for cell in m.group(2).split(", "):
                rows.add((int(m.group(1)), named.get(cell, cell.strip("`").rstrip("/").removesuffix(".py"))))
    return rows


def test_the_documented_table_is_the_enforced_one():
    assert doc_layers() == {(layer, unit) for layer, unit, _ in LAYERS}
