"""Sphinx configuration of hfrad's documentation site.

Build (warnings are errors, as in CI)::

    python3 -m pip install -e ".[docs]"
    python3 -m sphinx -W --keep-going -b html docs docs/_build/html

Pages are Markdown (MyST); the API reference is generated from the numpydoc
docstrings of the names ``hfrad.__all__`` exports, so it follows the package
without a list to keep in step (see :func:`_public_api`).
"""

from __future__ import annotations

import importlib
import inspect
import re
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT / "src"))        # the checkout, even when hfrad is not installed

import hfrad  # noqa: E402

project = "hfrad"
author = "the hfrad authors"
copyright = "2026, the hfrad authors"
release = hfrad.__version__
version = ".".join(release.split(".")[:2])

extensions = [
    "myst_parser",
    "numpydoc",
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.mathjax",
]
source_suffix = {".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build"]

# MyST: headings get anchors (links such as [text](method.md#7-error-figures)), $...$ maths.
myst_enable_extensions = ["dollarmath", "colon_fence", "deflist"]
myst_heading_anchors = 3

# API reference: one page, filled at build time from hfrad.__all__ (see _fill): an autosummary
# table per group, then autodoc of each name. Nothing is generated into the source folder.
autosummary_generate = False
autodoc_typehints = "none"                   # the numpydoc "Parameters" sections carry the types
autodoc_member_order = "bysource"
numpydoc_show_class_members = False          # members are listed by autosummary's class template
numpydoc_class_members_toctree = False
numpydoc_xref_param_type = False
numpydoc_validation_checks: set[str] = set()

html_theme = "furo"
html_title = f"hfrad {release}"
html_static_path: list[str] = []

# Classes the reference documents besides the exports (reached through them: return values).
EXTRA_CLASSES = [
    "hfrad.solve.bounds.ResidualEstimate",
    "hfrad.solve.nearfield.NearFieldFactorization",
    "hfrad.inverse.design.DesignResult",
]


def _public_api() -> dict[str, list[str]]:
    """The names to document, grouped: functions, classes, errors and warnings."""
    groups: dict[str, list[str]] = {"functions": [], "classes": [], "errors": []}
    for name in hfrad.__all__:
        if name.startswith("_"):
            continue
        obj = getattr(hfrad, name)
        if inspect.isclass(obj) and issubclass(obj, BaseException):
            groups["errors"].append(f"hfrad.{name}")
        elif inspect.isclass(obj):
            groups["classes"].append(f"hfrad.{name}")
        elif callable(obj):
            groups["functions"].append(f"hfrad.{name}")
    for dotted in EXTRA_CLASSES:
        module, _, name = dotted.rpartition(".")
        try:
            getattr(importlib.import_module(module), name)
        except (ImportError, AttributeError):     # renamed or moved: left out, not a broken build
            continue
        groups["classes"].append(dotted)
    return groups


def _reference(names: list[str], members: bool = False) -> str:
    """An autosummary table of ``names``, then each documented in full (autodoc + numpydoc)."""
    table = "".join(f"   {n}\n" for n in names)
    body = []
    for n in names:
        obj = _resolve(n)
        if inspect.isclass(obj):
            opts = "   :members:\n   :show-inheritance:\n" if members else "   :show-inheritance:\n"
            body.append(f".. autoclass:: {n}\n{opts}")
        else:
            body.append(f".. autofunction:: {n}\n")
    return ("```{eval-rst}\n.. autosummary::\n   :nosignatures:\n\n" + table + "\n"
            + "\n".join(body) + "```\n")


def _resolve(dotted: str):
    module, _, name = dotted.rpartition(".")
    return getattr(importlib.import_module(module), name)


def _fill(app, docname: str, source: list[str]) -> None:
    text = source[0]
    if "{hfrad-api-" in text:
        groups = _public_api()
        text = text.replace("{hfrad-api-functions}", _reference(groups["functions"]))
        text = text.replace("{hfrad-api-classes}", _reference(groups["classes"], members=True))
        text = text.replace("{hfrad-api-errors}", _reference(groups["errors"]))
    source[0] = text


_BARS = re.compile(r"(?<![\\|])\|([^|\s`][^|`]*?)\|(?!\|)")


def _escape_bars(app, what, name, obj, options, lines: list[str]) -> None:
    """Docstrings write absolute values as ``|x|``; reST would read a substitution.

    Outside inline literals, ``|x|`` becomes ``\\|x\\|`` (grid tables, with a space
    after the bar, are left alone).
    """
    for i, line in enumerate(lines):
        pieces = line.split("``")
        for k in range(0, len(pieces), 2):           # even pieces are outside ``literals``
            pieces[k] = _BARS.sub(r"\\|\1\\|", pieces[k])
        lines[i] = "``".join(pieces)


def setup(app):
    app.connect("source-read", _fill)
    app.connect("autodoc-process-docstring", _escape_bars)
    return {"parallel_read_safe": True}
