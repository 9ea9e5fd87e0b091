"""operator_factorization: G ~= Q V^T from products G X and G^T X only, against LAPACK's SVD."""

from __future__ import annotations

import numpy as np
import pytest

from hfrad.errors import AccuracyWarning, InputError
from hfrad.lowrank.baselines import svd_factorization
from hfrad.lowrank.operator import _truncated_svd, operator_factorization
from hfrad.resources import blas_threads


@pytest.fixture(autouse=True)
def one_blas_thread():
    """The matrices are small: OpenBLAS's threads only spin against other processes (10x slower
    on a loaded two-core machine)."""
    with blas_threads(1):
        yield


def spectrum_matrix(n: int, s: np.ndarray, seed: int = 0) -> np.ndarray:
    """An (n, n) matrix with singular values ``s`` (random orthogonal factors)."""
    rng = np.random.default_rng(seed)
    U = np.linalg.qr(rng.standard_normal((n, n)))[0]
    W = np.linalg.qr(rng.standard_normal((n, n)))[0]
    return (U * s) @ W.T


def factor(G: np.ndarray, dtype=np.float64, **kw):
    Gd = G.astype(dtype)
    calls = {"matmat": 0, "rmatmat": 0}

    def matmat(X):
        calls["matmat"] += 1
        return Gd @ X

    def rmatmat(X):
        calls["rmatmat"] += 1
        return Gd.T @ X

    lr = operator_factorization(matmat, rmatmat, G.shape[0], float(np.square(G).sum()), dtype=dtype, rng=0, **kw)
    return lr, calls


def true_error(G, lr) -> float:
    return float(np.linalg.norm(G - lr.Q.astype(np.float64) @ lr.V.T.astype(np.float64)))


@pytest.fixture(scope="module")
def cornell_G():
    from hfrad import load_scene
    from hfrad.formfactors.blocks import form_factor_matrix
    scene = load_scene("cornell", patches=600)
    rho_max = np.asarray(scene.reflectance).max(axis=1)
    return rho_max[:, None] * form_factor_matrix(scene)


@pytest.mark.parametrize("decay", [0.9, 0.98])
@pytest.mark.parametrize("eps", [0.05, 0.01])
def test_decaying_spectrum_meets_eps_near_the_optimal_rank(decay, eps):
    n = 400
    G = spectrum_matrix(n, decay ** np.arange(n))
    lr, calls = factor(G, eps=eps, block=32)
    optimal = svd_factorization(G, eps=eps, dtype=np.float64).rank
    assert lr.relative_error <= eps
    assert true_error(G, lr) <= eps * np.linalg.norm(G) * (1 + 1e-9)
    assert optimal <= lr.rank <= optimal + 2
    # computed, not estimated: the achieved error is the true one to rounding
    assert abs(lr.achieved_error / true_error(G, lr) - 1) < 1e-6
    # V orthonormal, Q = U S with U orthonormal
    np.testing.assert_allclose(lr.V.T @ lr.V, np.eye(lr.rank), atol=1e-10)
    s = np.linalg.norm(lr.Q, axis=0)
    np.testing.assert_allclose((lr.Q / s).T @ (lr.Q / s), np.eye(lr.rank), atol=1e-10)
    # the products counted are the calls made: one matmat and (power=1) one rmatmat per pass, plus B's
    assert lr.info["products"] == calls["matmat"] + calls["rmatmat"]
    assert calls["matmat"] == calls["rmatmat"] == 2 * len(lr.info["rank_trace"])
    assert lr.method == "operator" and lr.info["converged"]


def test_float32_factors_and_their_error_figure():
    n = 400
    G = spectrum_matrix(n, 0.95 ** np.arange(n), seed=3)
    lr, _ = factor(G, dtype=np.float32, eps=0.02, block=32)
    assert lr.Q.dtype == lr.V.dtype == np.float32
    optimal = svd_factorization(G, eps=0.02, dtype=np.float64).rank
    assert optimal <= lr.rank <= optimal + 2
    err = true_error(G, lr)
    assert err <= 0.02 * np.linalg.norm(G) * (1 + 1e-4)
    # in float32, ||G||^2 - ||B||^2 carries a few units of rounding of ||G||^2 (observed ~3)
    assert abs(lr.achieved_error ** 2 - err ** 2) <= 30 * np.finfo(np.float32).eps * np.square(G).sum()


def test_exact_low_rank_and_seed_determinism():
    rng = np.random.default_rng(5)
    G = rng.standard_normal((300, 12)) @ rng.standard_normal((12, 300))
    a, _ = factor(G, eps=1e-6, block=8, power=0)
    b, _ = factor(G, eps=1e-6, block=8, power=0)
    assert a.rank == 12 and a.relative_error <= 1e-6
    np.testing.assert_array_equal(a.Q, b.Q)
    np.testing.assert_array_equal(a.V, b.V)


def test_cornell_box_G(cornell_G):
    G = cornell_G
    for eps in (0.05, 0.02):
        lr, _ = factor(G, eps=eps)
        optimal = svd_factorization(G, eps=eps, dtype=np.float64).rank
        assert lr.relative_error <= eps
        assert true_error(G, lr) <= eps * np.linalg.norm(G) * (1 + 1e-9)
        assert optimal <= lr.rank <= optimal + 3, (eps, lr.rank, optimal)
        assert abs(lr.achieved_error / true_error(G, lr) - 1) < 1e-6


def test_zero_matrix_has_rank_zero():
    G = np.zeros((50, 50))
    lr, calls = factor(G, eps=0.05)
    assert lr.rank == 0 and lr.Q.shape == (50, 0) and lr.achieved_error == 0.0
    assert calls == {"matmat": 0, "rmatmat": 0}


def test_max_rank_caps_the_basis_and_warns():
    n = 200
    G = spectrum_matrix(n, 0.99 ** np.arange(n), seed=1)
    seen = []
    with pytest.warns(AccuracyWarning, match="max_rank=20"):
        lr, _ = factor(G, eps=0.01, block=16, max_rank=20, progress=lambda done, total: seen.append((done, total)))
    assert lr.rank == 20 and not lr.info["converged"]
    assert seen == [(16, 20), (20, 20)]
    assert abs(lr.achieved_error / true_error(G, lr) - 1) < 1e-6     # still the true error


def test_bad_arguments_and_products():
    G = np.eye(10)
    with pytest.raises(InputError, match="block"):
        factor(G, eps=0.1, block=0)
    with pytest.raises(InputError, match="norm2"):
        operator_factorization(lambda X: X, lambda X: X, 10, -1.0, eps=0.1)
    with pytest.raises(InputError, match=r"matmat\(X\) must return an array of shape \(10, 4\)"):
        operator_factorization(lambda X: X[:5], lambda X: X, 10, 10.0, eps=0.1, block=4)


def test_range_share_trades_basis_for_rank_within_the_target():
    """A low-rank G plus flat noise (an H-matrix's own error): a larger range_share stops the range
    finder earlier (fewer products), keeps a somewhat larger rank, and still meets the target."""
    n = 400
    rng = np.random.default_rng(3)
    G = spectrum_matrix(n, 0.9 ** np.arange(n)) + 2.5e-4 * rng.standard_normal((n, n))   # noise 4% of ||G||
    norm = np.linalg.norm(G)
    runs = {share: factor(G, eps=0.05, block=16, range_share=share)[0] for share in (0.5, 0.95)}
    for lr in runs.values():
        assert true_error(G, lr) <= 0.05 * norm * (1 + 1e-9)
    assert runs[0.95].info["vectors"] < runs[0.5].info["vectors"]
    assert runs[0.5].rank <= runs[0.95].rank
    with pytest.raises(InputError, match="range_share"):
        factor(G, eps=0.05, range_share=0.0)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_lanczos_meets_eps_with_half_the_products(cornell_G, dtype):
    """method="lanczos" (block Golub-Kahan, randUBV): each block's G^T P_i, which B needs, starts the
    next block, so a block costs two products instead of four (power=1). On a decaying spectrum and on
    the Cornell box's G it meets the target at the optimal rank (+2) with at most 60% of power's
    products (measured 50-57%: 52 against 96 at 2,000 patches), and its figure is the true error."""
    for G, eps, block in ((spectrum_matrix(400, 0.98 ** np.arange(400)), 0.02, 32), (cornell_G, 0.05, 32)):
        optimal = svd_factorization(G, eps=eps, dtype=np.float64).rank
        power, _ = factor(G, dtype=dtype, eps=eps, block=block)
        lr, calls = factor(G, dtype=dtype, eps=eps, block=block, method="lanczos")
        assert optimal <= lr.rank <= optimal + 2, (lr.rank, optimal)
        err = true_error(G, lr)
        assert err <= eps * np.linalg.norm(G) * (1 + (1e-4 if dtype == np.float32 else 1e-9))
        assert abs(lr.achieved_error / err - 1) < (1e-3 if dtype == np.float32 else 1e-6)
        assert calls["matmat"] == calls["rmatmat"] == len(lr.info["rank_trace"])
        assert lr.info["products"] <= 0.6 * power.info["products"], (lr.info["products"], power.info["products"])
        np.testing.assert_allclose(lr.V.T.astype(np.float64) @ lr.V, np.eye(lr.rank),
                                   atol=1e-5 if dtype == np.float32 else 1e-10)


def test_lanczos_tops_up_a_block_whose_krylov_directions_ran_out():
    """Equal singular values (an orthogonal G): G^T P_i lies in the span of the blocks already applied, so the
    next block is drawn afresh (Gaussian columns off them); the basis still grows a full block at a time."""
    n = 120
    G = np.linalg.qr(np.random.default_rng(2).standard_normal((n, n)))[0]
    lr, calls = factor(G, eps=0.5, block=16, method="lanczos")
    assert lr.info["converged"] and true_error(G, lr) <= 0.5 * np.linalg.norm(G) * (1 + 1e-9)
    assert [size for size, _ in lr.info["rank_trace"]] == list(range(16, lr.info["basis"] + 1, 16))
    assert lr.rank == int(np.ceil(0.75 * n))                 # ||G - G_k||^2 = n - k <= 0.25 n
    with pytest.raises(InputError, match="method"):
        factor(G, eps=0.5, method="krylov")


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_truncated_svd_of_B_agrees_with_lapacks(dtype):
    """The Gram route to B's SVD (B wide, l x n) gives LAPACK's singular values, a right factor as
    orthonormal and B's truncation error; a kept singular value too small for the Gram (budget 0 on
    a rank-deficient B) takes LAPACK's SVD."""
    rng = np.random.default_rng(3)
    l, n = 48, 5000
    B = ((rng.standard_normal((l, l)) * np.logspace(0, -3, l)) @ rng.standard_normal((l, n))).astype(dtype)
    U0, s0, _ = np.linalg.svd(B.astype(np.float64), full_matrices=False)
    budget2 = float(np.sum(s0[30:] ** 2)) * 1.0001
    U, s, Wt, discarded2 = _truncated_svd(B, budget2, dtype)
    assert s.size == 30 and Wt.shape == (30, n) and Wt.dtype == dtype
    # observed (float32 B / float64 B): s 4.7e-15 / 3.9e-15 of s_1 off, the discard 1e-11 / 3e-12
    # relative, W 3e-9 / 8e-13 and U 3e-15 from orthonormal, the residual 1e-13 / 1e-17 of s_1 off
    np.testing.assert_allclose(s, s0[:30], rtol=0, atol=1e-13 * s0[0])
    np.testing.assert_allclose(discarded2, np.sum(s0[30:] ** 2), rtol=1e-10)
    orth = 3e-8 if dtype == np.float32 else 5e-12
    assert np.abs(Wt.astype(np.float64) @ Wt.T - np.eye(30)).max() < orth
    assert np.abs(U.T @ U - np.eye(30)).max() < 1e-13
    R = B.astype(np.float64) - (U * s) @ Wt.astype(np.float64)
    assert abs(np.linalg.norm(R) - np.sqrt(np.sum(s0[30:] ** 2))) < 1e-12 * s0[0]
    low = (rng.standard_normal((l, 5)) @ rng.standard_normal((5, n))).astype(dtype)     # rank 5 of 48
    U, s, Wt, _ = _truncated_svd(low, 0.0, dtype)
    # LAPACK's factors: 1e-6 / 2e-15 from orthonormal (the Gram's would be far off: GRAM_FLOOR = 0 fails)
    assert s.size == l and np.abs(Wt.astype(np.float64) @ Wt.T - np.eye(l)).max() < (1e-5 if dtype == np.float32 else 1e-13)
