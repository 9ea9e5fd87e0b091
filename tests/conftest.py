"""Shared test fixtures and builders."""

import signal
import warnings

import numpy as np
import pytest


def default_sigint() -> None:
    """``preexec_fn`` for a child that a test interrupts: SIGINT back to its default action.

    A process started with SIGINT ignored keeps it ignored (an exec keeps SIG_IGN), and a
    pytest-xdist worker may have it ignored, so a test's Ctrl-C would not reach the child: what
    a terminal's foreground command has is the default action.
    """
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@pytest.fixture(autouse=True)
def _sigint_kept():
    """A test that leaves this process's SIGINT action changed gets it restored, with a warning
    naming it: the action is inherited by the children later tests start."""
    before = signal.getsignal(signal.SIGINT)
    yield
    after = signal.getsignal(signal.SIGINT)
    if after is not before and before is not None:
        signal.signal(signal.SIGINT, before)
        warnings.warn(f"this test changed SIGINT's action ({before!r} -> {after!r}); restored", stacklevel=1)


def closed_system(n, seed=0):
    """A closed reciprocal 'radiosity' system: F >= 0, rows sum to 1, A_i F_ij = A_j F_ji.

    F = diag(1/A) S diag(...) with S = D K D symmetric, scaled (symmetric Sinkhorn) so
    that S's rows sum to the areas; K is a smooth kernel of random points (low rank-ish).
    """
    rng = np.random.default_rng(seed)
    x = rng.random((n, 3))
    x = x[np.argsort(x[:, 0])]
    areas = rng.uniform(0.9, 1.1, n)
    K = 1.0 / (1.0 + np.sum((x[:, None] - x[None]) ** 2, axis=-1) / 0.1)
    np.fill_diagonal(K, 0.0)
    d = np.ones(n)
    for _ in range(500):
        d = np.sqrt(d * areas / (K @ d))
    S = d[:, None] * K * d[None]
    S = 0.5 * (S + S.T)
    F = S / areas[:, None]
    F /= F.sum(axis=1, keepdims=True)      # exact row sums; reciprocity holds to ~1e-12
    rho = rng.uniform(0.1, 0.9, (n, 3))
    return F, areas, rho


class Interrupt(Exception):
    """Raised by :func:`interrupt_at` to stop a factorization part way (checkpoint tests)."""


def interrupt_at(blocks: int):
    """A ``status`` callback for ``factorize`` that raises :class:`Interrupt` once ``blocks`` are done."""
    def status(info):
        if info["blocks"] == blocks:
            raise Interrupt
    return status


def run_cli(*args):
    """Invoke the ``hfrad`` command line in-process; arguments may be paths or numbers."""
    from typer.testing import CliRunner

    from hfrad.cli import app

    return CliRunner().invoke(app, [str(a) for a in args])
