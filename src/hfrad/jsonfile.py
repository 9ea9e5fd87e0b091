"""Reading JSON (and TOML) that a user gives, safely: a deeply nested document is a clear error.

``json.loads`` of ``[[[[...]]]]`` nested 100,000 deep raises RecursionError,
which is no ``ValueError``: the callers' ``except json.JSONDecodeError``
misses it and the command line would print "internal error". These
wrappers turn it into a :class:`json.JSONDecodeError` (a ``ValueError``)
saying how deep the document goes and where, so every reader that already
reports bad JSON in one line reports this one too.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

__all__ = ["loads_json", "loads_toml", "nesting_error"]


def _too_deep_at(text: str, limit: int) -> tuple[int, int]:
    """(position, depth) where ``text``'s nesting of [ and { first exceeds ``limit`` (strings skipped)."""
    depth, in_string, escaped = 0, False, False
    for pos, ch in enumerate(text):
        if in_string:
            if escaped:
                escaped = False
            elif ch == "\\":
                escaped = True
            elif ch == '"':
                in_string = False
        elif ch == '"':
            in_string = True
        elif ch in "[{":
            depth += 1
            if depth > limit:
                return pos, depth
        elif ch in "]}":
            depth -= 1
    return 0, depth


def nesting_error(text: str, kind: str = "JSON") -> json.JSONDecodeError:
    """A ``JSONDecodeError`` for a document nested too deeply for the parser, pointing at where it gets so."""
    import sys

    limit = max(1, sys.getrecursionlimit() // 2)
    pos, _ = _too_deep_at(text, limit)
    return json.JSONDecodeError(f"{kind} nested too deeply (more than about {limit} levels of [ or {{)", text, pos)


def loads_json(text: "str | bytes") -> Any:
    """``json.loads(text)``; a document nested too deeply raises ``json.JSONDecodeError`` too.

    Raises
    ------
    json.JSONDecodeError
        Not valid JSON, or nested deeper than the parser can go (the message says so).
    """
    try:
        return json.loads(text)
    except RecursionError:
        if isinstance(text, (bytes, bytearray)):
            text = text.decode("utf-8", "replace")
        raise nesting_error(text) from None


def loads_toml(text: str) -> dict:
    """``tomllib.loads(text)``; a document nested too deeply raises a ``ValueError`` saying so."""
    import tomllib

    try:
        return tomllib.loads(text)
    except RecursionError:
        raise nesting_error(text, "TOML") from None


def read_document(path: "str | Path", *, what: str, error: type[Exception]) -> Any:
    """The data of a user's ``.json`` or ``.toml`` file (chosen by its suffix), not yet validated.

    Parameters
    ----------
    path : str or Path
    what : str
        What the file is, for the messages ("spec", "layout").
    error : exception class
        Raised, naming the file, when the text is not valid JSON/TOML, too deeply nested, or not UTF-8.

    Raises
    ------
    FileNotFoundError
        No such file.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such {what} file")
    kind = "TOML" if path.suffix.lower() == ".toml" else "JSON"
    try:
        text = path.read_text(encoding="utf-8")
        return loads_toml(text) if kind == "TOML" else loads_json(text)
    except (ValueError, TypeError) as exc:  # JSONDecodeError, TOMLDecodeError and UnicodeDecodeError
        raise error(f"{path}: not valid {kind}: {exc}") from None
