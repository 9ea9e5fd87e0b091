"""Exceptions and warnings raised by hfrad.

All derive from builtin bases so that ``except ValueError`` keeps working.
"""

from __future__ import annotations

import numpy as np


class InputError(ValueError):
    """A bad argument or option value from the user: names it, what was expected and what was got.

    The command line turns it (and the other errors below except
    FactorizationError) into one line and exit code 2; any other exception is
    an internal error and keeps its traceback.
    """


class SceneError(ValueError):
    """Bad scene input: names the file, face or material and what is wrong."""


class FactorizationError(np.linalg.LinAlgError):
    """A factorization failed; the message names the block."""


class FileFormatError(ValueError):
    """A file written by hfrad is truncated, corrupted or of a newer version."""


class MemoryLimitError(MemoryError):
    """A requested array would not fit in the memory allowed for it."""


class WriteError(OSError):
    """A file could not be written (no space left, read-only or missing folder, permission, I/O error);
    the message names the file the user asked for, not the temporary name."""


class WorkerError(RuntimeError):
    """A worker process died before handing back its work (killed, out of memory, or a script
    that starts workers without an ``if __name__ == "__main__":`` guard)."""


class AccuracyWarning(RuntimeWarning):
    """The result is usable but may be inaccurate (e.g. 1 - sigma_max is tiny)."""
