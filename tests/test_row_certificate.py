"""RowCertificate: ||A^1/2 diag(rho) (F - F~) A^-1/2||_F from a sample of exact rows, redrawn many times."""

from __future__ import annotations

import numpy as np
import pytest

from hfrad.errors import InputError
from hfrad.formfactors.certify import FAILURE, RowCertificate

N = 600
REDRAWS = 2000


def constructed(heavy_gain: float, seed: int = 0):
    """(F, F~, rho, areas, e): a dense F, an approximation off by small errors everywhere and
    ``heavy_gain`` times larger in 6 rows; ``e`` (n,) the true per-row ``||D_i||^2``."""
    rng = np.random.default_rng(seed)
    areas, rho = rng.uniform(0.5, 2.0, N), rng.uniform(0.3, 0.8, N)
    F = rng.uniform(0.0, 1.0, (N, N)) / N
    err = rng.standard_normal((N, N)) * 1e-4 / N
    heavy = rng.choice(N, 6, replace=False)
    err[heavy] *= heavy_gain * rng.uniform(0.5, 1.5, (6, 1))
    D = np.sqrt(areas)[:, None] * rho[:, None] * err / np.sqrt(areas)[None, :]
    return F, F - err, rho, areas, (D ** 2).sum(axis=1), heavy


def redraw(F, Fa, rho, areas, m, weights=None):
    """(estimates^2, upper figures) of REDRAWS certificates."""
    out = np.empty((REDRAWS, 2))
    for seed in range(REDRAWS):
        c = RowCertificate.draw(N, m, weights, seed=seed)
        out[seed] = c.estimate(F[c.rows], Fa[c.rows], rho, areas)
    return out[:, 0] ** 2, out[:, 1]


def noisy_predictor(e, heavy, seed=1):
    """Weights that follow e within a factor ~e^0.5 and miss one heavy row by 50x."""
    w = e * np.exp(np.random.default_rng(seed).normal(0.0, 0.5, e.size))
    w[heavy[0]] = e[heavy[0]] / 50
    return w


@pytest.mark.parametrize("weighted", [False, True])
def test_the_squared_estimate_is_unbiased_with_heavy_rows(weighted):
    F, Fa, rho, areas, e, heavy = constructed(heavy_gain=10.0)
    true2 = e.sum()
    assert e[heavy].sum() / true2 > 0.3            # the heavy rows carry a good part of ||D||^2
    est2, _ = redraw(F, Fa, rho, areas, 64, noisy_predictor(e, heavy) if weighted else None)
    se = est2.std() / np.sqrt(REDRAWS) / true2     # observed: 1.1% stratified, 0.4% weighted
    assert se < 0.015                              # fine enough to see a bias of a few %
    assert abs(est2.mean() / true2 - 1) < 0.03     # observed: -0.8% stratified, +0.8% weighted


def test_weighted_upper_figure_fails_at_most_twice_as_often_as_stated():
    F, Fa, rho, areas, e, heavy = constructed(heavy_gain=40.0)
    true = np.sqrt(e.sum())
    assert e[heavy].sum() / e.sum() > 0.8           # errors in few rows, one of them unpredicted
    _, upper = redraw(F, Fa, rho, areas, 64, noisy_predictor(e, heavy))
    assert np.mean(upper < true) <= 2 * FAILURE


def test_stratified_upper_figure_fails_at_most_twice_as_often_as_stated_where_errors_spread():
    F, Fa, rho, areas, e, _ = constructed(heavy_gain=1.0)
    _, upper = redraw(F, Fa, rho, areas, 64)
    assert np.mean(upper < np.sqrt(e.sum())) <= 2 * FAILURE


def test_stratified_upper_figure_is_not_dependable_where_few_rows_carry_the_error():
    """Why weights: 6 rows with a third of ||D||^2, drawn uniformly, are all missed in a third of
    the draws, and the sample variance misses them too (observed: 34% failures)."""
    F, Fa, rho, areas, e, _ = constructed(heavy_gain=10.0)
    _, upper = redraw(F, Fa, rho, areas, 64)
    assert np.mean(upper < np.sqrt(e.sum())) > 4 * FAILURE


def test_every_row_drawn_gives_the_exact_norm():
    F, Fa, rho, areas, e, _ = constructed(heavy_gain=10.0)
    c = RowCertificate.draw(N, N, seed=3)
    np.testing.assert_array_equal(np.sort(c.rows), np.arange(N))
    est, upper = c.estimate(F[c.rows], Fa[c.rows], rho, areas)
    assert est == pytest.approx(np.sqrt(e.sum()), rel=1e-12) and upper >= est


def test_draws_are_determined_by_the_seed():
    w = np.random.default_rng(0).uniform(0, 1, N)
    for weights in (None, w):
        a, b = RowCertificate.draw(N, 50, weights, seed=7), RowCertificate.draw(N, 50, weights, seed=7)
        c = RowCertificate.draw(N, 50, weights, seed=8)
        np.testing.assert_array_equal(a.rows, b.rows)
        np.testing.assert_array_equal(a.scale, b.scale)
        assert not np.array_equal(a.rows, c.rows)
    strata = RowCertificate.draw(N, 50, seed=7).rows
    assert (strata // (N // 50) == np.arange(50)).all()      # one row in each stratum, in order


def test_bad_arguments():
    with pytest.raises(InputError, match="m must be"):
        RowCertificate.draw(N, 1)
    with pytest.raises(InputError, match="weights must have shape"):
        RowCertificate.draw(N, 10, np.ones(3))
    with pytest.raises(InputError, match="weights must be finite and >= 0"):
        RowCertificate.draw(N, 10, -np.ones(N))
    c = RowCertificate.draw(N, 10, seed=0)
    with pytest.raises(InputError, match=r"exact_rows must have shape \(10, 600\)"):
        c.estimate(np.zeros((9, N)), np.zeros((10, N)), np.ones(N), np.ones(N))
    with pytest.raises(InputError, match="areas must be > 0"):
        c.estimate(np.zeros((10, N)), np.zeros((10, N)), np.ones(N), np.zeros(N))
