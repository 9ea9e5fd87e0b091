"""The near-field sweeps (Chebyshev-accelerated Neumann series) against LAPACK on small systems."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from hfrad.solve.neumann import ALL_ROWS_SHARE, _Support, neumann_solve, spectral_bound


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
    assert 0.8 <= bound <= 0.8 * 1.01      # Collatz-Wielandt: never below; stops within 1% (observed 0.19%)


@pytest.mark.parametrize("rate", [0.5, 0.9])
def test_forward_and_adjoint_converge_to_the_exact_solve(rate):
    M, D, b = _system(rate)
    rho = spectral_bound(M)
    x, sweeps = neumann_solve(M, b, rho=rho, post=D, tol=1e-10)
    y, _ = neumann_solve(M.T.tocsr(), b, rho=rho, pre=D, tol=1e-10)
    exact, adjoint = _exact(M, D, b), _exact(M, D, b, adjoint=True)
    # tol 1e-10: observed 8e-12 / 3e-11 (rate 0.5, forward / adjoint), 4.2e-10 / 4.0e-10 (rate 0.9)
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
    assert rel <= 1e-5 / (1 - 0.9)          # tol / (1 - rho); observed 3.5e-5


def test_no_answer_where_the_series_cannot_converge():
    """Spectral radius above 1 (rows of F above 1 on overlapping faces): None, not a wrong answer."""
    M, D, b = _system(1.3, seed=2)
    rho = spectral_bound(M)
    assert rho >= 1.3
    assert neumann_solve(M, b, rho=rho, post=D) == (None, 0)
    x, sweeps = neumann_solve(M, b, rho=0.99, post=D)       # a wrong bound: refused, not a wrong answer
    assert x is None and sweeps < 200


def _chain(n: int = 400, rate: float = 0.8):
    """A reciprocal near field on a line of patches: each linked to the two on either side."""
    rng = np.random.default_rng(3)
    w = rng.uniform(0.5, 1.0, n - 1)
    S = sp.diags([w, w], [-1, 1]) + sp.diags([w[:-1] / 2, w[:-1] / 2], [-2, 2])
    M = (sp.diags(1.0 / rng.uniform(0.5, 2.0, n)) @ S).tocsr()
    return (M * (rate / spectral_bound(M, iterations=500, rtol=1e-6))).tocsr()


@pytest.mark.parametrize("adjoint", [False, True])
def test_sweeping_only_the_reached_rows_gives_the_same_solution(adjoint):
    """A lamp (two emitting rows) on a 400-row chain: the tracked support starts at the lamp's
    neighbours and grows one ring a sweep; the answer is the exact solve's, like the full sweeps'."""
    M = _chain()
    D = np.random.default_rng(4).uniform(0.6, 1.0, (400, 3))
    b = np.zeros((400, 3))
    b[200:202] = [5.0, 4.0, 3.0]
    MT = M.T.tocsr()
    A, pattern = (MT, M) if adjoint else (M, MT)
    scales = {"pre": D} if adjoint else {"post": D}
    full, sweeps = neumann_solve(A, b, rho=spectral_bound(M), tol=1e-12, **scales)
    local, local_sweeps = neumann_solve(A, b, rho=spectral_bound(M), tol=1e-12,
                                        reach=(pattern.indptr, pattern.indices), **scales)
    exact = _exact(M, D, b, adjoint=adjoint)
    assert local_sweeps == sweeps
    assert np.abs(local - exact).max() <= 2e-12 * np.abs(exact).max()       # observed 4-5e-13
    assert np.abs(local - full).max() <= 1e-13 * np.abs(full).max()        # observed 0: the same sums


def test_the_support_grows_one_ring_a_sweep_then_covers_every_row():
    M = _chain()
    MT = M.T.tocsr()
    b = np.zeros((400, 1))
    b[200] = 1.0
    support = _Support((MT.indptr, MT.indices), b)
    assert support.rows().tolist() == list(range(198, 203))      # the lamp and two on either side
    assert support.rows().tolist() == list(range(196, 205))
    sweeps = 2
    while (rows := support.rows()).size < 400:
        sweeps += 1
        assert rows.size == 1 + 4 * sweeps                       # two more rows on either side
    assert 4 * sweeps + 1 >= ALL_ROWS_SHARE * 400 - 4            # all rows once half are reached
