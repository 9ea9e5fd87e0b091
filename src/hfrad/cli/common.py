"""What the CLI commands share: scene options, error reporting, progress bars."""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import functools
import inspect
from typing import Iterator, List, Optional

import click
import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from ..errors import InputError

console = Console(stderr=True, soft_wrap=True)

# Shared option declarations so every command spells them the same way.
MaxEdgeOption = typer.Option(None, "--max-edge", help="Patches no longer than this (metres): long faces are split, faces under half of it grouped into clusters. Makes at least area / (0.433 max_edge^2) patches (an equilateral triangle of edge h has area 0.433 h^2); memory for that many is checked before cutting.")
PatchesOption = typer.Option(None, "--patches", help="Roughly this many patches: faces are split, or grouped into clusters of triangles when fewer patches than faces are asked for. Memory for that many is checked before cutting.")
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
KeepDuplicatesOption = typer.Option(False, "--keep-duplicates", help="Keep faces that duplicate another face (same corners) or overlap one in its plane instead of merging duplicates and cutting overlaps to one layer (their light is then counted twice).")


@dataclasses.dataclass(frozen=True)
class SceneOptions:
    """The scene options every scene-reading command shares, as one object (see :func:`scene_options`).

    The fields are the keywords of :func:`hfrad.cli.info.load_scene_from_options`:
    ``load_scene_from_options(scene, **dataclasses.asdict(options))``.
    """

    max_edge: Optional[float] = None
    patches: Optional[int] = None
    unit_scale: float = 1.0
    emit: Optional[List[str]] = None
    area_light: Optional[str] = None
    default_reflectance: float = 0.7
    allow_missing_materials: bool = False
    keep_duplicates: bool = False


#: The command-line options of :class:`SceneOptions`: (field, annotation, typer option), in --help order.
_SCENE_PARAMETERS = [("max_edge", Optional[float], MaxEdgeOption), ("patches", Optional[int], PatchesOption),
                     ("unit_scale", float, UnitScaleOption), ("emit", Optional[List[str]], EmissionOption),
                     ("area_light", Optional[str], AreaLightOption),
                     ("default_reflectance", float, DefaultReflectanceOption),
                     ("allow_missing_materials", bool, AllowMissingMaterialsOption),
                     ("keep_duplicates", bool, KeepDuplicatesOption)]


def scene_options(command):
    """Give a command the shared scene options (one definition): it declares ``scene_options: SceneOptions``.

    The options (``--max-edge``, ``--patches``, ``--unit-scale``, ``--emission``,
    ``--area-light``, ``--default-reflectance``, ``--allow-missing-materials``,
    ``--keep-duplicates``) take the place of that parameter in the command's
    signature, which is what typer reads; the command receives them packed.
    """
    signature = inspect.signature(command, eval_str=True)
    shared = [inspect.Parameter(name, inspect.Parameter.POSITIONAL_OR_KEYWORD, default=option, annotation=kind)
              for name, kind, option in _SCENE_PARAMETERS]
    params = []
    for p in signature.parameters.values():
        params += shared if p.name == "scene_options" else [p]

    @functools.wraps(command)
    def with_scene_options(*args, **kwargs):
        packed = SceneOptions(**{name: kwargs.pop(name) for name, _, _ in _SCENE_PARAMETERS})
        return command(*args, scene_options=packed, **kwargs)

    with_scene_options.__signature__ = signature.replace(parameters=params)
    with_scene_options.__annotations__ = {p.name: p.annotation for p in params}
    del with_scene_options.__wrapped__     # typer reads the signature above, not the command's
    return with_scene_options


def quote(value: object, limit: int = 200) -> str:
    """``repr`` of a value a user gave, cut to about ``limit`` characters for an error line."""
    text = repr(value)
    return text if len(text) <= limit else text[:limit - 20] + f"... ({len(text):,} characters)"


def fail(message: str, code: int = 2) -> "typer.Exit":
    """Print an error message (no traceback) and exit with ``code``."""
    from rich.markup import escape

    # escaped: a message quoting "[nan, 0.5]" or "[section]" must not be read as rich markup and vanish
    console.print(f"[bold red]error:[/] {escape(str(message))}", highlight=False)
    raise typer.Exit(code)


#: Where internal errors should be reported.
REPORT_TO = "the hfrad issue tracker (include the command line and this traceback)"


#: typer >= 0.16 carries its own copy of click: its usage errors are of that copy's classes.
_CLICK_ERRORS = tuple({click.exceptions.ClickException,
                       next(c for c in typer.BadParameter.__mro__ if c.__name__ == "ClickException")})

#: errno values of the machine's file system, not of hfrad: full disk, read-only or missing folder, ...
_SYSTEM_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EIO, errno.EROFS, errno.EACCES, errno.EPERM,
                  errno.ENOENT, errno.ENOTDIR, errno.EISDIR, errno.ENAMETOOLONG, errno.EEXIST}


def _is_user_error(exc: BaseException) -> bool:
    """Errors caused by the input or the machine, not by hfrad: bad files, values, options, memory, a full
    disk, missing extras."""
    from ..errors import FileFormatError, InputError, MemoryLimitError, SceneError, WorkerError, WriteError

    if isinstance(exc, (SceneError, FileFormatError, MemoryLimitError, InputError, WorkerError, WriteError,
                        FileNotFoundError, IsADirectoryError, NotADirectoryError, PermissionError)):
        return True
    if isinstance(exc, OSError) and exc.errno in _SYSTEM_ERRNOS:
        return True
    # an optional dependency missing: hfrad raises ImportError("... pip install X") itself (no
    # module name); an ImportError from the import system (name set) is a broken install or a bug
    return isinstance(exc, ImportError) and exc.name is None and "pip install" in str(exc)


@contextlib.contextmanager
def user_errors() -> Iterator[None]:
    """Bad input: one line and exit code 2. Anything else: the traceback, where to report, exit 1."""
    try:
        yield
    except (typer.Exit, typer.Abort, KeyboardInterrupt) + _CLICK_ERRORS:
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

@contextlib.contextmanager
def stage_clock(quiet: bool = False, start: float | None = None):
    """A :class:`hfrad.progress.StageClock` (total from ``start``, a ``time.perf_counter()``) whose
    stage names show on a status line while the block runs (loading, cleaning and cutting a scene
    print nothing else); the clock goes on counting after the block, without the line."""
    from ..progress import StageClock

    if quiet:
        yield StageClock(start=start)
        return
    with console.status("starting") as line:
        def show(name: str) -> None:
            done = ", ".join(f"{k} {v:.1f} s" for k, v in clock.seconds.items())
            line.update(f"{name}..." + (f" (done: {done})" if done else ""))

        clock = StageClock(show, start=start)
        try:
            yield clock
        finally:
            clock.listener = None


#: The summary's names of the stages inside ``factorize`` (keys of ``fac.lowrank.info``), in order.
FACTORIZE_STAGES = (("time_setup", "ray budget and estimate"), ("time_formfactors", "form factors"),
                    ("time_statistics", "pass statistics"), ("time_hf", "HF"),
                    ("time_factorization", "operator factorization"), ("time_certificate", "far-field certificate"),
                    ("time_checkpoints", "checkpoints"), ("time_assemble", "solver set-up (near field, capacitance inverses)"))


def add_factorize_stages(clock, fac, wall: float) -> None:
    """Put the stages of a local ``factorize`` (``fac.lowrank.info``) on ``clock``, and what of its
    ``wall`` seconds none of them claims as ``factorize, other``."""
    info = fac.lowrank.info
    inside = 0.0
    for key, name in FACTORIZE_STAGES:
        if key in info:
            clock.add(name, info[key])
            inside += info[key]
    clock.add("factorize, other", wall - inside)


def estimate_line(seconds: float, pass_over_kernel: float | None = None) -> str:
    """The form-factor estimate said before the pass (``status``'s ``estimate`` and ``pass_over_kernel``)."""
    from ..precompute.local import ESTIMATE_COLUMNS, PASS_OVER_KERNEL

    factor = PASS_OVER_KERNEL if pass_over_kernel is None else pass_over_kernel
    return (f"estimate: form factors about {seconds:,.0f} s on this machine as loaded now (the kernel timed on "
            f"{ESTIMATE_COLUMNS} columns; the rays and the rest of the pass as {factor - 1:g} times the kernel; "
            "the first run after an install also compiles the ray code, once, which can take minutes)")


def dtype_option(default: str):
    """``--dtype``: the precision of the numbers a command computes and stores."""
    return typer.Option(default, "--dtype", help=f"Precision: float32 or float64 (default {default}).")


def check_dtype(dtype: str):
    """The numpy dtype of a ``--dtype`` value; InputError naming the allowed values."""
    import numpy as np

    if dtype not in ("float32", "float64"):
        raise InputError(f"--dtype must be float32 or float64; got {dtype!r}")
    return np.dtype(dtype)


def check_output(path, *, option: str = "-o/--output"):
    """Refuse at once an output that could not be written at the end (missing or read-only folder, a
    directory at that name): :func:`hfrad.atomic.check_writable`, before any work."""
    from pathlib import Path

    from ..atomic import check_writable

    if path is None:
        return None
    if str(path) == "":
        raise InputError(f"{option}: empty file name")
    return check_writable(Path(path))


def check_output_folder(folder, files=(), *, option: str = "-o/--output"):
    """Create ``folder`` (with its parents) for a command's output ``files`` and check each can be written,
    or refuse in one line: a file of that name, a read-only or unwritable place, a folder at a file's name."""
    from pathlib import Path

    from ..atomic import check_writable
    from ..errors import WriteError

    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise WriteError(f"cannot write into {folder} ({option}): it is a file, not a folder")
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise WriteError(f"cannot create the folder {folder} ({option}): {exc.strerror or exc}") from None
    for name in files:
        check_writable(folder / name)
    return folder


def check_space_for_hfr(path, fac) -> None:
    """Refuse to write an .hfr file the disk has no room for (HDF5 cannot fail cleanly half way)."""
    from ..atomic import check_space
    from ..solve.hfr import hfr_bytes

    check_space(path, hfr_bytes(fac))


def warn_disk_for_hfr(path, n: int, dtype: str) -> None:
    """Before a precompute: warn when the output's disk may be too small for the .hfr (the rank is guessed,
    so this is a warning; :func:`check_space_for_hfr` refuses with the real size before writing)."""
    import warnings
    from pathlib import Path

    from ..atomic import free_bytes
    from ..memory import factors_bytes, human, rank_guess

    k = rank_guess(n)
    need = factors_bytes(n, k, check_dtype(dtype).itemsize) + 200 * n   # factors + patches
    try:
        free = free_bytes(Path(path).parent)
    except OSError:
        return
    if need > free:
        warnings.warn(f"{path} may need up to {human(need)} (rank guessed as {k:,}) but its disk has "
                      f"{human(free)} free; the write is checked again, with the real size, before it starts")


def check_count(value, option: str, *, low: int = 1, high: int | None = None, why: str = "") -> None:
    """An integer option within [low, high]; InputError naming the option, the range and the value."""
    if value is None:
        return
    if value < low or (high is not None and value > high):
        span = f">= {low:,}" if high is None else f"between {low:,} and {high:,}"
        raise InputError(f"{option} must be a whole number {span}{'; ' + why if why else ''}; got {value:,}")


def check_choice(value: str, option: str, allowed) -> str:
    """``value`` if it is one of ``allowed``, else InputError listing them (for options like --method)."""
    if value not in allowed:
        raise InputError(f"{option} must be one of {', '.join(allowed)}; got {quote(value)}")
    return value


#: Most worker processes per core worth starting (each holds a copy of the scene's ray caster).
MAX_PROCESSES_PER_CORE = 4

#: Most visibility rays per patch pair (32 x 32 points per triangle); the cost grows in proportion.
MAX_SAMPLES = 1024


def check_samples(samples) -> None:
    """``--samples``: 0 (no visibility) or a perfect square up to :data:`MAX_SAMPLES`."""
    check_count(samples, "--samples", low=0, high=MAX_SAMPLES,
                why="visibility rays per patch pair; time and memory grow in proportion")


def precompute_estimate(n: int, block: int, dtype: str, far_field: str = "auto", near_entries: int = 0,
                        clustered: bool = False) -> int:
    """Bytes a precompute of n patches is estimated to need (:func:`hfrad.memory.precompute_peak_bytes`:
    the pass, or the near field's set-up with ``near_entries`` a row where that is larger)."""
    from ..formfactors.bfloat16 import value_dtype
    from ..formfactors.hmatrix import default_values
    from ..memory import precompute_peak_bytes

    return precompute_peak_bytes(n, block, far_field=far_field, near_entries=near_entries,
                                 itemsize=check_dtype(dtype).itemsize, clustered=clustered,
                                 hmatrix_value_bytes=value_dtype(default_values(n)).itemsize)


def check_memory_for_precompute(n: int, block: int, dtype: str, *, count: str = "", far_field: str = "auto",
                                near_entries: int = 0, clustered: bool = False) -> None:
    """Refuse a precompute that would not fit in memory (see ``hfrad precompute --help``); ``count``
    qualifies the patch count in the message ("at least" for an estimate before cutting)."""
    from ..memory import RANK_ASSUMPTION, rank_guess, require

    require(precompute_estimate(n, block, dtype, far_field, near_entries, clustered),
            f"precomputing {count + ' ' if count else ''}{n:,} patches"
            + (f" with {near_entries} near-field entries a row" if near_entries else ""),
            f"use fewer patches (--patches/--max-edge), a larger --eps or a smaller --near-field (the estimate "
            f"assumes a rank of {rank_guess(n):,}: {RANK_ASSUMPTION})")


def error_figures_line(fac, residual=None, solution=None) -> str:
    """The factorization's error figures in words, the one to rely on first (docs/method.md, section 7):
    :func:`hfrad.solve.bounds.accuracy_lines`; ``solution``: a solve's SolutionError, said first."""
    import warnings

    from ..errors import AccuracyWarning
    from ..solve.bounds import accuracy_lines

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", AccuracyWarning)   # said in words below
        est = fac.error_estimate()
    return "\n".join(accuracy_lines(est, residual=residual, achieved_error=fac.relative_error, solution=solution))


def show_warnings_plainly() -> None:
    """Print library warnings as one 'warning:' line each, without file and line of the source."""
    import warnings

    def show(message, category, filename, lineno, file=None, line=None) -> None:
        console.print(f"[yellow]warning:[/] {message}", highlight=False)

    warnings.showwarning = show


def load_factorization(path):
    """An .hfr file's factorization, which must hold its patches (``fac.scene``)."""
    from pathlib import Path

    from ..solve.hfr import load_hfr

    if not Path(path).exists():
        raise InputError(f"{path}: no such file (a factorization from `hfrad precompute SCENE -o FILE.hfr`)")
    if Path(path).is_dir():
        raise InputError(f"{path}: is a folder, not a factorization file (.hfr)")
    fac = load_hfr(path)
    if fac.scene is None:
        raise InputError(f"{path}: has no patches stored; re-run `hfrad precompute` (it stores them)")
    return fac
