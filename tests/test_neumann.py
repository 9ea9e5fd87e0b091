"""The Neumann series of the near-field solve against LAPACK on small random systems."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from hfrad.solve.neumann import neumann_solve


def _system(rate: float, n: int = 300, seed: int = 0):
    """A sparse nonnegative M scaled so that ||M||_inf = rate, per-column scales in (0.5, 1)."""
    rng = np.random.default_rng(seed)
    M = sp.random(n, n, density=0.05, random_state=seed, format="csr")
    M = sp.diags(rate / np.asarray(M.sum(axis=1)).ravel().clip(1e-12)) @ M
    return M.tocsr(), rng.uniform(0.5, 1.0, (n, 2)), rng.random((n, 2))


def test_forward_and_adjoint_converge_to_the_exact_solve():
    M, D, b = _system(0.8)
    n = M.shape[0]
    Md = M.toarray()
    x, sweeps = neumann_solve(M, b, post=D, tol=1e-10)
    y, _ = neumann_solve(M.T.tocsr(), b, pre=D, tol=1e-10)
    for c in range(2):
        exact = np.linalg.solve(np.eye(n) - D[:, c, None] * Md, b[:, c])
        adjoint = np.linalg.solve((np.eye(n) - D[:, c, None] * Md).T, b[:, c])
        assert np.abs(x[:, c] - exact).max() <= 1e-9 * np.abs(exact).max()
        assert np.abs(y[:, c] - adjoint).max() <= 1e-9 * np.abs(adjoint).max()
    assert sweeps < 120          # contraction <= 0.8: 1e-10 within ~100 sweeps


def test_stopping_tolerance_bounds_the_error():
    M, D, b = _system(0.9, seed=1)
    exact = np.linalg.solve(np.eye(M.shape[0]) - D[:, :1] * M.toarray(), b[:, 0])
    x, _ = neumann_solve(M, b[:, :1], post=D[:, :1], tol=1e-5)
    rel = np.abs(x[:, 0] - exact).max() / np.abs(exact).max()
    assert rel <= 1e-5 * 0.9 / 0.1    # tol r / (1 - r)


def test_divergent_series_is_refused():
    """Contraction above 1 (rows of F above 1 on overlapping faces): None, not a wrong answer."""
    M, _, b = _system(1.3, seed=2)
    x, sweeps = neumann_solve(M, b)
    assert x is None and sweeps < 200
