"""Progress reporting: library code calls ``progress(done, total)``; only the CLI draws bars."""

from __future__ import annotations

from typing import Callable, Optional

ProgressCallback = Optional[Callable[[int, int], None]]


def report(progress: ProgressCallback, done: int, total: int) -> None:
    """Call ``progress(done, total)`` if a callback was given."""
    if progress is not None:
        progress(done, total)
