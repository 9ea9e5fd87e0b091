"""Inline commands of Radiance scene files (``!genbox ...``, ``!xform ...``), run without a shell.

A Radiance model may hold a line ``!command args`` whose output is read in its
place. Radiance hands that line to a shell; hfrad does not. The line is split
with :mod:`shlex`, the program must be on :data:`ALLOWED` (Radiance's own
``genbox`` and ``xform``, from the ``pyradiance`` package), every argument is
checked against what that program takes (numbers, names, options), files must
lie in the model's folder or below it, and the program runs from an argument
list with no shell. Anything else is refused with the file and line. The
files ``xform`` transforms are read by hfrad's own reader first (their inline
commands checked the same way) and given to ``xform`` on its standard input,
so ``xform`` never opens a file or runs a command itself.

Sizes are checked before any work: ``xform -a`` arrays and ``-i`` repeats
multiply to at most :data:`MAX_COPIES` copies, and the text a command would
produce to at most :data:`MAX_OUTPUT_BYTES`.
"""

from __future__ import annotations

import math
import re
import shlex
import subprocess
from pathlib import Path

from ..errors import SceneError
from ..validation import clip_token

__all__ = ["ALLOWED", "MAX_COPIES", "MAX_OUTPUT_BYTES", "run_command"]

#: Programs an inline command may run (all from pyradiance's Radiance binaries).
ALLOWED = ("genbox", "xform")

#: Most copies an ``xform`` line may make (the product of its ``-a`` counts and ``-i``).
MAX_COPIES = 10_000

#: Most bytes of scene text one inline command may produce.
MAX_OUTPUT_BYTES = 512 * 2**20

#: Seconds a command may run.
TIMEOUT_S = 300

#: A Radiance identifier hfrad passes to a program: no spaces, no shell characters.
_NAME = re.compile(r"^[A-Za-z0-9_.:+\-]{1,200}$")

#: xform options: how many numbers follow each.
_XFORM_NUMBERS = {"-t": 3, "-rx": 1, "-ry": 1, "-rz": 1, "-s": 1, "-mx": 0, "-my": 0, "-mz": 0, "-i": 1, "-a": 1}
_XFORM_NAMES = ("-n", "-m")


def _binary(name: str) -> str:
    try:
        import pyradiance
    except ImportError:
        raise ImportError(f"reading the inline command '!{name}' of a Radiance file needs Radiance's own tools: "
                          "pip install pyradiance (or pip install 'hfrad[buildings]')") from None
    exe = Path(pyradiance.BINPATH) / name
    if not exe.is_file():
        raise ImportError(f"pyradiance has no '{name}' program at {exe}: pip install --upgrade pyradiance")
    return str(exe)


def _number(text: str, where: str, what: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise SceneError(f"{where}: {what}: expected a number, got {clip_token(text)}") from None
    if not math.isfinite(value) or abs(value) > 1e30:
        raise SceneError(f"{where}: {what}: {clip_token(text)} is not a finite number of at most 1e30")
    return value


def _name(text: str, where: str, what: str) -> str:
    if not _NAME.match(text):
        raise SceneError(f"{where}: {what} {clip_token(text)} is not a plain Radiance name "
                         "(letters, digits, _ . : + -)")
    return text


def confined(folder: Path, name: str, where: str, what: str = "file") -> Path:
    """``folder / name`` when it lies in ``folder`` or below it (no ``..``, absolute path or link out).

    Raises
    ------
    SceneError
        The path leaves the folder, or is not a file.
    """
    root = folder.resolve()
    try:
        target = (folder / name).resolve()
    except (OSError, RuntimeError):
        raise SceneError(f"{where}: cannot resolve the {what} name {clip_token(name)}") from None
    if target != root and root not in target.parents:
        raise SceneError(f"{where}: {what} {clip_token(name)} lies outside the model's folder "
                         f"{clip_token(str(root))}; hfrad reads only files in the model's folder and below it")
    if not target.is_file():
        raise SceneError(f"{where}: {what} {clip_token(name)} not found in {clip_token(str(root))}")
    return target


def _genbox_args(argv: list[str], where: str) -> list[str]:
    """``genbox mat name xsize ysize zsize [-i] [-b bevel]``; ``-r`` (round edges: spheres, cylinders) refused."""
    if len(argv) < 6:
        raise SceneError(f"{where}: genbox needs 'genbox material name xsize ysize zsize', got "
                         f"{clip_token(' '.join(argv))}")
    out = [_name(argv[1], where, "genbox material"), _name(argv[2], where, "genbox name")]
    for k, text in enumerate(argv[3:6]):
        if _number(text, where, f"genbox size {'xyz'[k]}") <= 0:
            raise SceneError(f"{where}: genbox size {'xyz'[k]} must be > 0, got {clip_token(text)}")
        out.append(text)
    rest = argv[6:]
    while rest:
        opt = rest.pop(0)
        if opt == "-i":
            out.append(opt)
        elif opt == "-b" and rest:
            _number(rest[0], where, "genbox -b")
            out += [opt, rest.pop(0)]
        elif opt == "-r":
            raise SceneError(f"{where}: genbox -r (rounded edges) makes spheres and cylinders, which hfrad does "
                             "not read; use -b (bevel: polygons) or no option")
        else:
            raise SceneError(f"{where}: genbox option {clip_token(opt)} is not allowed (allowed: -i, -b N)")
    return out


def _xform_args(argv: list[str], folder: Path, where: str) -> tuple[list[str], list[Path], int]:
    """(transform arguments, files, copies) of an ``xform`` line; files confined to ``folder``."""
    args: list[str] = []
    files: list[Path] = []
    copies = 1
    rest = argv[1:]
    while rest:
        opt = rest.pop(0)
        if opt in _XFORM_NUMBERS:
            count = _XFORM_NUMBERS[opt]
            if len(rest) < count:
                raise SceneError(f"{where}: xform {opt} needs {count} number(s)")
            values = [_number(rest[k], where, f"xform {opt}") for k in range(count)]
            if opt in ("-a", "-i"):
                if not (values[0] == int(values[0]) and values[0] >= 1):
                    raise SceneError(f"{where}: xform {opt} needs a whole number >= 1, got {clip_token(rest[0])}")
                copies *= int(values[0])
                if copies > MAX_COPIES:
                    raise SceneError(f"{where}: xform makes {copies:,} copies or more (its -a and -i counts "
                                     f"multiplied); hfrad reads at most {MAX_COPIES:,}")
            args += [opt] + rest[:count]
            del rest[:count]
        elif opt in _XFORM_NAMES:
            if not rest:
                raise SceneError(f"{where}: xform {opt} needs a name")
            args += [opt, _name(rest.pop(0), where, f"xform {opt}")]
        elif opt.startswith("-"):
            raise SceneError(f"{where}: xform option {clip_token(opt)} is not allowed (allowed: "
                             f"{', '.join(list(_XFORM_NUMBERS) + list(_XFORM_NAMES))})")
        else:
            files.append(confined(folder, opt, where, "xform file"))
    if not files:
        raise SceneError(f"{where}: xform without a file (it would read the standard input); name a .rad file")
    return args, files, copies


def _run(argv: list[str], stdin: str, where: str) -> str:
    try:
        done = subprocess.run(argv, input=stdin.encode(), capture_output=True, timeout=TIMEOUT_S, check=False)
    except subprocess.TimeoutExpired:
        raise SceneError(f"{where}: {Path(argv[0]).name} ran longer than {TIMEOUT_S} s") from None
    if done.returncode != 0:
        err = done.stderr.decode(errors="replace").strip().splitlines()
        raise SceneError(f"{where}: {Path(argv[0]).name} failed (exit {done.returncode}): "
                         f"{clip_token(err[-1] if err else '')}")
    return done.stdout.decode(errors="replace")


def run_command(line: str, folder: Path, where: str, read_file) -> str:
    """The scene text an inline command line produces.

    Parameters
    ----------
    line : str
        The line without its leading ``!``.
    folder : Path
        The model's folder: files the command names must lie in it or below.
    where : str
        ``file:line`` for messages.
    read_file : callable (Path, str) -> str
        hfrad's own reader of a nested ``.rad`` file: its primitives as plain
        text with no inline command left (``where`` of the including line given).

    Raises
    ------
    SceneError
        A program not on :data:`ALLOWED`, shell syntax, a bad argument, a path
        out of the folder, too many copies or too much output, or the program failing.
    ImportError
        pyradiance is not installed (with the pip command).
    """
    try:
        argv = shlex.split(line, comments=False, posix=True)
    except ValueError as exc:
        raise SceneError(f"{where}: cannot split the inline command {clip_token(line)}: {exc}") from None
    if not argv:
        raise SceneError(f"{where}: empty inline command '!'")
    program = argv[0]
    if program not in ALLOWED:
        raise SceneError(f"{where}: inline command {clip_token(program)} is not allowed; hfrad runs only "
                         f"{', '.join('!' + a for a in ALLOWED)} (Radiance's own, without a shell). Expand the "
                         "line with Radiance first and put its output in the file")
    if program == "genbox":
        return _run([_binary("genbox")] + _genbox_args(argv, where), "", where)
    args, files, copies = _xform_args(argv, folder, where)
    text = "".join(read_file(path, where) for path in files)
    if len(text.encode()) * copies > MAX_OUTPUT_BYTES:
        raise SceneError(f"{where}: xform would write about {len(text.encode()) * copies / 2**20:,.0f} MiB "
                         f"({copies:,} copies); hfrad reads at most {MAX_OUTPUT_BYTES / 2**20:,.0f} MiB per command")
    return _run([_binary("xform")] + args, text, where)
