"""What the CLI commands share: scene options, error reporting, progress bars."""

from __future__ import annotations

import contextlib
from typing import Iterator, Optional

import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

console = Console(stderr=True, soft_wrap=True)

# Shared option declarations so every command spells them the same way.
MaxEdgeOption = typer.Option(None, "--max-edge", help="Patches no longer than this (metres): long faces are split, faces under half of it grouped into clusters.")
PatchesOption = typer.Option(None, "--patches", help="Roughly this many patches: faces are split, or grouped into clusters of triangles when fewer patches than faces are asked for.")
UnitScaleOption = typer.Option(1.0, "--unit-scale", help="Multiply coordinates by this to get metres.")
EmitOption = typer.Option(None, "--emit", help="Make a material or group emit: NAME=R,G,B (W/m^2). Repeatable.")
AreaLightOption = typer.Option(None, "--area-light", help="Add a rectangular light under the ceiling: R,G,B (W/m^2).")
DefaultReflectanceOption = typer.Option(0.7, "--default-reflectance", help="Grey reflectance for faces with no material.")
QuietOption = typer.Option(False, "--quiet", "-q", help="No progress bars.")
KeepDuplicatesOption = typer.Option(False, "--keep-duplicates", help="Keep faces that duplicate another face (same corners) instead of merging them (their light is then counted twice).")


def fail(message: str, code: int = 2) -> "typer.Exit":
    """Print an error message (no traceback) and exit with ``code``."""
    console.print(f"[bold red]error:[/] {message}", highlight=False)
    raise typer.Exit(code)


@contextlib.contextmanager
def user_errors() -> Iterator[None]:
    """Turn the library's input errors into a one-line message and exit code 2."""
    from ..errors import FileFormatError, MemoryLimitError, SceneError

    try:
        yield
    except (SceneError, FileFormatError, MemoryLimitError, ValueError, FileNotFoundError, ImportError) as exc:
        fail(str(exc))


class _Bar:
    """``progress(done, total)`` callback over a rich task, plus a free-text note column."""

    def __init__(self, bar: Progress, task) -> None:
        self._bar, self._task = bar, task

    def __call__(self, done: int, total: int) -> None:
        self._bar.update(self._task, completed=done, total=total)

    def note(self, text: str) -> None:
        self._bar.update(self._task, note=text)


@contextlib.contextmanager
def progress_bar(description: str, quiet: bool = False) -> Iterator[Optional[_Bar]]:
    """A rich progress bar (done/total, elapsed, ETA, a note); yields None when quiet."""
    if quiet:
        yield None
        return
    with Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                  TimeElapsedColumn(), TimeRemainingColumn(), TextColumn("{task.fields[note]}"),
                  console=console, transient=False) as bar:
        yield _Bar(bar, bar.add_task(description, total=None, note=""))

def check_memory_for_precompute(n: int, block: int) -> None:
    """Refuse a precompute that would not fit in memory (see ``hfrad precompute --help``)."""
    from ..memory import precompute_bytes, require

    require(precompute_bytes(n, block), f"precomputing {n:,} patches",
            "use fewer patches (--patches/--max-edge) or a larger --eps")


def show_warnings_plainly() -> None:
    """Print library warnings as one 'warning:' line each, without file and line of the source."""
    import warnings

    def show(message, category, filename, lineno, file=None, line=None) -> None:
        console.print(f"[yellow]warning:[/] {message}", highlight=False)

    warnings.showwarning = show


def load_factorization(path):
    """An .hfr file's factorization, which must hold its patches (``fac.scene``)."""
    from ..io.hfr import load_hfr

    fac = load_hfr(path)
    if fac.scene is None:
        raise ValueError(f"{path}: has no patches stored; re-run `hfrad precompute` (it stores them)")
    return fac
