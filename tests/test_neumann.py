"""The near-field sweeps (Chebyshev-accelerated Neumann series) against LAPACK on small systems."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from hfrad.solve.neumann import neumann_solve, spectral_bound


def _system(rate: float, n: int = 300, seed: int = 0):
    """``M = diag(1 / area) S`` (S symmetric, nonnegative, sparse: a reciprocal near field) scaled to
    spectral radius ``rate``; per-column channel scales D in (0.5, 1] and right-hand sides."""
    rng = np.random.default_rng(seed)
    S = sp.random(n, n, density=0.04, random_state=seed, format="csr")
    S = S + S.T
    M = sp.diags(1.0 / rng.uniform(0.5, 2.0, n)) @ S
    radius = np.abs(np.linalg.eigvals(M.toarray())).max()
    D = rng.uniform(0.5, 1.0, (n, 2))
    D[:, 1] = 1.0                                   # one channel at D = 1: the full radius
    return (M * (rate / radius)).tocsr(), D, rng.random((n, 2))


def _exact(M, D, b, adjoint=False):
    n = M.shape[0]
    out = []
    for c in range(b.shape[1]):
        A = np.eye(n) - D[:, c, None] * M.toarray()
        out.append(np.linalg.solve(A.T if adjoint else A, b[:, c]))
    return np.stack(out, axis=1)


def test_spectral_bound_is_an_upper_bound_and_tight():
    M, _, _ = _system(0.8)
    bound = spectral_bound(M)
    assert 0.8 <= bound <= 0.8 * 1.01      # Collatz-Wielandt: never below; stops within 1%


@pytest.mark.parametrize("rate", [0.5, 0.9])
def test_forward_and_adjoint_converge_to_the_exact_solve(rate):
    M, D, b = _system(rate)
    rho = spectral_bound(M)
    x, sweeps = neumann_solve(M, b, rho=rho, post=D, tol=1e-10)
    y, _ = neumann_solve(M.T.tocsr(), b, rho=rho, pre=D, tol=1e-10)
    exact, adjoint = _exact(M, D, b), _exact(M, D, b, adjoint=True)
    assert np.abs(x - exact).max() <= 1e-9 * np.abs(exact).max()
    assert np.abs(y - adjoint).max() <= 1e-9 * np.abs(adjoint).max()
    _, plain = neumann_solve(M, b, rho=0.0, post=D, tol=1e-10)
    print(f"\nrate {rate}: Chebyshev {sweeps} sweeps, plain series {plain}")
    # per sweep rho / (1 + sqrt(1 - rho^2)) instead of rho: 0.27 / 0.53 of the plain sweeps
    assert sweeps <= {0.5: 0.6, 0.9: 0.4}[rate] * plain


def test_stopping_tolerance_bounds_the_error():
    M, D, b = _system(0.9, seed=1)
    exact = _exact(M, D, b)
    x, _ = neumann_solve(M, b, rho=spectral_bound(M), post=D, tol=1e-5)
    rel = np.abs(x - exact).max() / np.abs(exact).max()
    assert rel <= 1e-5 / (1 - 0.9)          # tol / (1 - rho)


def test_no_answer_where_the_series_cannot_converge():
    """Spectral radius above 1 (rows of F above 1 on overlapping faces): None, not a wrong answer."""
    M, D, b = _system(1.3, seed=2)
    rho = spectral_bound(M)
    assert rho >= 1.3
    assert neumann_solve(M, b, rho=rho, post=D) == (None, 0)
    x, sweeps = neumann_solve(M, b, rho=0.99, post=D)       # a wrong bound: refused, not a wrong answer
    assert x is None and sweeps < 200
