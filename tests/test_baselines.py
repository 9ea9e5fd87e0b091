"""Baselines (LAPACK SVD, randomized SVD, one-pass sketch) meet eps with the same semantics."""

import numpy as np
import pytest

from hfrad.lowrank.baselines import randomized_factorization, sketch_factorization, svd_factorization


@pytest.fixture(scope="module")
def matrix():
    rng = np.random.default_rng(0)
    n = 300
    U, _ = np.linalg.qr(rng.standard_normal((n, n)))
    W, _ = np.linalg.qr(rng.standard_normal((n, n)))
    s = np.exp(-np.arange(n) / 20.0)
    return (U * s) @ W.T, s


def optimal_rank(s, eps):
    tail = np.append(np.cumsum((s ** 2)[::-1])[::-1], 0.0)
    return int(np.argmax(tail <= eps ** 2 * np.sum(s ** 2)))


@pytest.mark.parametrize("method", [svd_factorization, randomized_factorization, sketch_factorization])
@pytest.mark.parametrize("eps", [0.05, 0.02, 0.01])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_meets_eps(matrix, method, eps, dtype):
    A, s = matrix
    kw = {} if method is svd_factorization else {"rng": 0}
    lr = method(A, eps=eps, dtype=dtype, **kw)
    direct = np.linalg.norm(A - lr.Q.astype(np.float64) @ lr.V.T.astype(np.float64))
    assert direct <= eps * np.linalg.norm(A) * (1 + (1e-3 if dtype == np.float32 else 1e-9))
    assert lr.achieved_error == pytest.approx(direct, rel=1e-2 if dtype == np.float32 else 1e-6)
    k_opt = optimal_rank(s, eps)
    if method is svd_factorization:
        assert abs(lr.rank - k_opt) <= 1
    elif method is randomized_factorization:
        assert lr.rank <= k_opt + max(2, int(0.05 * k_opt))
    else:
        assert lr.rank <= 1.5 * k_opt + 2


def test_absolute(matrix):
    A, _ = matrix
    lr = randomized_factorization(A, eps=0.05, relative=False, dtype=np.float64, rng=1)
    assert np.linalg.norm(A - lr.Q @ lr.V.T) <= 0.05
