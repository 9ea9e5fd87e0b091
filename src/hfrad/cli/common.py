"""What the CLI commands share: scene options, error reporting, progress bars."""

from __future__ import annotations

import contextlib
from typing import Iterator, Optional

import click
import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from ..errors import InputError

console = Console(stderr=True, soft_wrap=True)

# Shared option declarations so every command spells them the same way.
MaxEdgeOption = typer.Option(None, "--max-edge", help="Patches no longer than this (metres): long faces are split, faces under half of it grouped into clusters.")
PatchesOption = typer.Option(None, "--patches", help="Roughly this many patches: faces are split, or grouped into clusters of triangles when fewer patches than faces are asked for.")
UnitScaleOption = typer.Option(1.0, "--unit-scale", help="Multiply coordinates by this to get metres.")
# --emission is the one spelling; --emit (its old name on info and precompute) is accepted too.
EmissionOption = typer.Option(None, "--emission", "--emit",
                              help="Set the exitance of a material or group: NAME=R,G,B or NAME=V (W/m^2); 0 switches "
                                   "it off; other emitters keep theirs. Repeatable.")
AreaLightOption = typer.Option(None, "--area-light", help="Add a rectangular light under the ceiling: R,G,B (W/m^2).")
DefaultReflectanceOption = typer.Option(0.7, "--default-reflectance", help="Grey reflectance for faces with no material.")
QuietOption = typer.Option(False, "--quiet", "-q", help="No progress bars.")
AllowMissingMaterialsOption = typer.Option(False, "--allow-missing-materials",
                                           help="Faces whose material (or .mtl file) is missing get the default "
                                                "reflectance instead of stopping.")
KeepDuplicatesOption = typer.Option(False, "--keep-duplicates", help="Keep faces that duplicate another face (same corners) instead of merging them (their light is then counted twice).")


def fail(message: str, code: int = 2) -> "typer.Exit":
    """Print an error message (no traceback) and exit with ``code``."""
    console.print(f"[bold red]error:[/] {message}", highlight=False)
    raise typer.Exit(code)


#: Where internal errors should be reported.
REPORT_TO = "the hfrad issue tracker (include the command line and this traceback)"


def _is_user_error(exc: BaseException) -> bool:
    """Errors caused by the input, not by hfrad: bad files, values, options, memory, missing extras."""
    from ..errors import FileFormatError, InputError, MemoryLimitError, SceneError, WorkerError

    if isinstance(exc, (SceneError, FileFormatError, MemoryLimitError, InputError, WorkerError, FileNotFoundError,
                        IsADirectoryError, NotADirectoryError, PermissionError)):
        return True
    # an optional dependency missing: hfrad raises ImportError("... pip install X") itself (no
    # module name); an ImportError from the import system (name set) is a broken install or a bug
    return isinstance(exc, ImportError) and exc.name is None and "pip install" in str(exc)


@contextlib.contextmanager
def user_errors() -> Iterator[None]:
    """Bad input: one line and exit code 2. Anything else: the traceback, where to report, exit 1."""
    try:
        yield
    except (typer.Exit, typer.Abort, KeyboardInterrupt, click.exceptions.ClickException):
        raise
    except Exception as exc:  # noqa: BLE001 - sorted into user errors and internal errors below
        if _is_user_error(exc):
            fail(str(exc))
        console.print_exception()
        console.print(f"[bold red]internal error[/] (a bug in hfrad, not in your input): "
                      f"{type(exc).__name__}: {exc}\nplease report it to {REPORT_TO}", highlight=False)
        raise typer.Exit(1) from exc


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

def dtype_option(default: str):
    """``--dtype``: the precision of the numbers a command computes and stores."""
    return typer.Option(default, "--dtype", help=f"Precision: float32 or float64 (default {default}).")


def check_dtype(dtype: str):
    """The numpy dtype of a ``--dtype`` value; InputError naming the allowed values."""
    import numpy as np

    if dtype not in ("float32", "float64"):
        raise InputError(f"--dtype must be float32 or float64; got {dtype!r}")
    return np.dtype(dtype)


def check_memory_for_precompute(n: int, block: int, dtype: str) -> None:
    """Refuse a precompute that would not fit in memory (see ``hfrad precompute --help``)."""
    from ..memory import RANK_ASSUMPTION, precompute_bytes, rank_guess, require

    require(precompute_bytes(n, block, itemsize=check_dtype(dtype).itemsize), f"precomputing {n:,} patches",
            f"use fewer patches (--patches/--max-edge) or a larger --eps (the estimate assumes a rank of "
            f"{rank_guess(n):,}: {RANK_ASSUMPTION})")


def error_figures_line(fac) -> str:
    """The factorization's error figures in words (docs/method.md, section 7)."""
    import warnings

    from ..errors import AccuracyWarning

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", AccuracyWarning)   # said in words below
        est = fac.error_estimate()
    def figs(values):
        return ", ".join(f"{v:.3g}" if v == v and v != float("inf") else "none" for v in values)
    if est.kind == "probes":
        head = (f"guaranteed bound on the relative radiosity error of any solve (R,G,B; {est.norm} norm, failure "
                f"probability {est.failure_probability:g}): {figs(est.bound)}")
    else:
        head = "no pass statistics: only the eq. 5 figure"
    return (f"{head}; eq. 5 bound {figs(est.eq5_bound)} (sigma_max {figs(est.sigma_max)}); "
            "`hfrad solve --residual` gives the tight figure of one solution")


def show_warnings_plainly() -> None:
    """Print library warnings as one 'warning:' line each, without file and line of the source."""
    import warnings

    def show(message, category, filename, lineno, file=None, line=None) -> None:
        console.print(f"[yellow]warning:[/] {message}", highlight=False)

    warnings.showwarning = show


def load_factorization(path):
    """An .hfr file's factorization, which must hold its patches (``fac.scene``)."""
    from ..solve.hfr import load_hfr

    fac = load_hfr(path)
    if fac.scene is None:
        raise InputError(f"{path}: has no patches stored; re-run `hfrad precompute` (it stores them)")
    return fac
