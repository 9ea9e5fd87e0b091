"""Progress reporting: library code calls ``progress(done, total)``; only the CLI draws bars."""

from __future__ import annotations

from typing import Callable, Optional

ProgressCallback = Optional[Callable[[int, int], None]]


def report(progress: ProgressCallback, done: int, total: int) -> None:
    """Call ``progress(done, total)`` if a callback was given."""
    if progress is not None:
        progress(done, total)


StageCallback = Optional[Callable[[str], None]]


def stage(on_stage: StageCallback, name: str) -> None:
    """Call ``on_stage(name)`` if a callback was given: the work called ``name`` starts now."""
    if on_stage is not None:
        on_stage(name)


class StageClock:
    """Wall seconds per named stage of a command, for a summary whose stages add up to its total.

    Call it with a stage's name when that stage starts (it ends when the next starts, or at
    :meth:`stop`); :meth:`add` puts in seconds measured elsewhere (e.g. the stages inside
    ``factorize``, from its ``info``). ``listener(name)``, if given, hears each start (a status line);
    ``start``: the ``time.perf_counter()`` the total counts from (default: now).
    """

    def __init__(self, listener: StageCallback = None, start: float | None = None) -> None:
        import time

        self._now = time.perf_counter
        self.start = self._now() if start is None else float(start)   # a time.perf_counter() value
        self.seconds: dict[str, float] = {}
        self._current: tuple[str, float] | None = None
        self.listener = listener

    def __call__(self, name: str) -> None:
        self.stop()
        self._current = (name, self._now())
        if self.listener is not None:
            self.listener(name)

    def stop(self) -> None:
        """End the running stage (if any)."""
        if self._current is not None:
            name, t = self._current
            self.add(name, self._now() - t)
            self._current = None

    def add(self, name: str, seconds: float) -> None:
        self.seconds[name] = self.seconds.get(name, 0.0) + float(seconds)

    def total(self) -> float:
        """Seconds since the clock was made."""
        return self._now() - self.start

    def summary(self, total: float | None = None) -> str:
        """``'load 1.2 s + clean 0.3 s + ... + other 0.1 s = 48.5 s'``: every stage in the order first
        seen, and ``other`` (the time no stage claims; shown when 0.05 s or more) so the sum is the total."""
        total = self.total() if total is None else float(total)
        parts = list(self.seconds.items())
        rest = total - sum(self.seconds.values())
        if abs(rest) >= 0.05:
            parts.append(("other", rest))
        return " + ".join(f"{k} {v:.1f} s" for k, v in parts) + f" = {total:.1f} s"
