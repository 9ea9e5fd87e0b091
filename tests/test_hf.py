"""HF: the achieved Frobenius error meets eps and equals the sum of discards (orthogonality)."""

import numpy as np
import pytest

from hfrad.lowrank.hf import hierarchical_factorization


def known_spectrum(n, seed=0, decay=25.0):
    rng = np.random.default_rng(seed)
    U, _ = np.linalg.qr(rng.standard_normal((n, n)))
    W, _ = np.linalg.qr(rng.standard_normal((n, n)))
    s = np.exp(-np.arange(n) / decay)
    return (U * s) @ W.T, s


def col_blocks(A, b):
    return [A[:, i:i + b] for i in range(0, A.shape[1], b)]


def optimal_rank(s, err):
    tail = np.append(np.cumsum((s ** 2)[::-1])[::-1], 0.0)
    return int(np.argmax(tail <= err ** 2 * (1 + 1e-9)))


@pytest.fixture(scope="module")
def matrix():
    return known_spectrum(400)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("b", [16, 64, 100])
@pytest.mark.parametrize("eps", [0.05, 0.02, 0.01])
def test_error_meets_eps(matrix, eps, b, dtype):
    A, _ = matrix
    lr = hierarchical_factorization(col_blocks(A, b), 400, eps=eps, dtype=dtype)
    direct = np.linalg.norm(A - lr.Q.astype(np.float64) @ lr.V.T.astype(np.float64))
    normA = np.linalg.norm(A)
    assert direct <= eps * normA
    assert lr.Q.dtype == dtype and lr.V.shape == (400, lr.rank)
    assert lr.norm == pytest.approx(normA, rel=1e-9)   # observed 1.3e-10 (float32), 1e-16 (float64)
    # reported = sqrt(sum of discards) = actual error: the discards are orthogonal
    # observed at most 1.4e-12 (float64), 2.3e-6 (float32) over the 9 eps x b cases
    assert lr.achieved_error == pytest.approx(direct, rel=1e-11 if dtype == np.float64 else 2e-5)


def test_absolute_mode(matrix):
    A, _ = matrix
    lr = hierarchical_factorization(col_blocks(A, 64), 400, eps=0.1, relative=False, dtype=np.float64)
    assert np.linalg.norm(A - lr.Q @ lr.V.T) <= 0.1
    # observed 2.8e-16; up to 1.4e-12 in float64 in test_error_meets_eps (the same figures)
    assert lr.achieved_error == pytest.approx(np.linalg.norm(A - lr.Q @ lr.V.T), rel=1e-11)
    assert lr.target_error == 0.1


def test_generator_equals_sequence(matrix):
    A, _ = matrix
    lr1 = hierarchical_factorization(col_blocks(A, 64), 400, eps=0.02, dtype=np.float64)
    gen = (A[:, i:i + 64].copy() for i in range(0, 400, 64))
    lr2 = hierarchical_factorization(gen, 400, eps=0.02, dtype=np.float64, n_blocks=7)
    # observed 0 (the same arithmetic); the margin: the load probe may change the BLAS threads between runs
    np.testing.assert_allclose(lr2.Q, lr1.Q, atol=1e-13)
    np.testing.assert_allclose(lr2.V, lr1.V, atol=1e-13)
    with pytest.raises(ValueError, match="n_blocks"):
        hierarchical_factorization(iter(col_blocks(A, 64)), 400)


def test_rank_near_optimal_on_smooth_kernel():
    x = np.sort(np.random.default_rng(1).random(600))
    y = np.random.default_rng(2).random((600, 2))
    P = np.column_stack([x, y[:, 0] * 0.3])
    A = 1.0 / (0.05 + np.sum((P[:, None] - P[None]) ** 2, axis=-1))
    s = np.linalg.svd(A, compute_uv=False)
    for eps in (0.05, 0.01):
        lr = hierarchical_factorization(col_blocks(A, 64), 600, eps=eps, dtype=np.float64)
        k_opt = optimal_rank(s, lr.achieved_error)
        assert lr.relative_error <= eps
        assert lr.rank <= 1.25 * k_opt + 1, (lr.rank, k_opt)   # observed k_opt + 1 (10 for 9, 20 for 19)


@pytest.mark.parametrize("n, b", [(1, 1), (5, 1), (30, 30), (30, 7)])
def test_edge_sizes(n, b):
    A = np.random.default_rng(n).random((n, n))
    lr = hierarchical_factorization(col_blocks(A, b), n, eps=0.01, dtype=np.float64)
    assert np.linalg.norm(A - lr.Q @ lr.V.T) <= 0.01 * np.linalg.norm(A) + 1e-14


def test_zero_blocks():
    A = np.zeros((50, 50))
    A[:, 20:30] = np.random.default_rng(0).random((50, 10))
    lr = hierarchical_factorization(col_blocks(A, 8), 50, eps=1e-6, dtype=np.float64)
    np.testing.assert_allclose(lr.Q @ lr.V.T, A, atol=1e-14 * np.linalg.norm(A))   # rank 10 exactly: observed 7e-16
    z = hierarchical_factorization(col_blocks(np.zeros((50, 50)), 8), 50, eps=0.02)
    assert z.rank == 0 and z.Q.shape == (50, 0) and z.V.shape == (50, 0) and z.achieved_error == 0


def test_deterministic_signs(matrix):
    A, _ = matrix
    lr1 = hierarchical_factorization(col_blocks(A, 64), 400, eps=0.05)
    lr2 = hierarchical_factorization(col_blocks(A, 64), 400, eps=0.05)
    np.testing.assert_array_equal(lr1.Q, lr2.Q)


def test_bad_arguments(matrix):
    A, _ = matrix
    with pytest.raises(ValueError, match="eps"):
        hierarchical_factorization(col_blocks(A, 64), 400, eps=-1)
    with pytest.raises(ValueError, match=r"block 0 must have shape \(399, b\)"):
        hierarchical_factorization(col_blocks(A, 64), 399)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_gram_leaf_matches_the_svd_leaf(dtype):
    """The Gram leaf (tall blocks, budget well above rounding) keeps the SVD leaf's rank, or one
    more (it picks the rank within 90% of the budget), and its reported discard is the true
    ||A - U S V^T||_F^2."""
    from hfrad.lowrank import hf
    rng = np.random.default_rng(3)
    n, b = 4000, 64
    A = (rng.standard_normal((n, 20)) @ rng.standard_normal((20, b)) * np.exp(-np.arange(b) / 6)
         + 1e-3 * rng.standard_normal((n, b))).astype(dtype)
    norm2 = float(np.sum(np.square(A, dtype=np.float64)))
    budget2 = 0.5 * 0.02 ** 2 * norm2
    gram = hf._leaf_gram(A, norm2, norm2, budget2, 0)
    U, s, _ = hf._svd(A, "test")
    k, d2 = hf.truncation_rank(s, budget2)
    true2 = float(np.sum(np.square(A.astype(np.float64) - (gram.U * gram.s) @ gram.V.T)))
    print(f"\nrank gram {gram.s.size} svd {k}; discard gram {gram.discarded2 / norm2:.4e} "
          f"svd {d2 / norm2:.4e} true {true2 / norm2:.4e}")
    assert k <= gram.s.size <= k + 1
    # observed: float64 exact to rounding, float32 2.4e-7 ||A||^2 off (float32 sums)
    assert abs(gram.discarded2 - true2) <= 1e-6 * norm2
    # U from one Cholesky QR of A V_k: orthonormal to the rounding of one product (observed
    # 1.1e-7 in float32, 2.0e-15 in float64; Householder gave ~1e-6 in float32)
    Ug = gram.U.astype(np.float64)
    assert np.abs(Ug.T @ Ug - np.eye(gram.s.size)).max() <= 10 * np.finfo(dtype).eps
    assert true2 <= budget2


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_cholesky_qr_refuses_nearly_dependent_columns(dtype):
    """The leaf's one-pass Cholesky QR gives way (None: Householder runs) where the columns are
    far from orthogonal, and otherwise is an SVD of Y."""
    from hfrad.lowrank import hf
    rng = np.random.default_rng(4)
    Y = rng.standard_normal((3000, 5)).astype(dtype)
    U, s, Wt = hf._cholesky_qr_svd(Y)
    # observed 0.8 (float32) and 3.5 (float64) machine epsilons of max |Y|
    np.testing.assert_allclose((U * s) @ Wt, Y, atol=10 * np.finfo(dtype).eps * np.abs(Y).max())
    Y[:, 4] = Y[:, 3] + 1e-4 * Y[:, 0]
    assert hf._cholesky_qr_svd(Y) is None
    assert hf._cholesky_qr_svd(np.zeros((10, 2), dtype)) is None


def test_leaf_takes_the_gram_path_when_the_budget_norm_exceeds_the_block(monkeypatch):
    """With the near-field split the budget comes from the block's norm *before* its near
    entries were moved out (larger than ||A||^2). The Gram leaf must measure its discard on A
    itself and be kept: measuring it against the larger norm once sent every near-field leaf
    through the Gram matrix *and* a full gesdd of the tall block."""
    from hfrad.lowrank import hf
    rng = np.random.default_rng(5)
    n, b = 4000, 64
    A = (rng.standard_normal((n, 12)) @ rng.standard_normal((12, b))).astype(np.float32)
    a2 = float(np.sum(np.square(A, dtype=np.float64)))
    norm2 = 4.0 * a2                       # the near entries held 3/4 of the block's mass
    budget2 = 0.5 * 0.02 ** 2 * norm2
    tall_svds = []
    real_svd = hf._svd
    monkeypatch.setattr(hf, "_svd", lambda M, where: (tall_svds.append(M.shape), real_svd(M, where))[1])
    node = hf._leaf(A, norm2, budget2, 0)
    assert not [shape for shape in tall_svds if shape[0] == n], tall_svds
    true2 = float(np.sum(np.square(A.astype(np.float64) - (node.U * node.s) @ node.V.T)))
    assert node.norm2 == norm2             # merges keep budgeting from the full norm
    assert abs(node.discarded2 - true2) <= 3e-13 * a2   # rank 12 exactly: observed 3.0e-14
    assert true2 <= budget2


# -- BLAS threads on a shared machine -------------------------------------------------

def _busy(monkeypatch, cores_used):
    from hfrad import resources
    monkeypatch.setattr(resources, "other_processes_cores", lambda window=0.1: cores_used)
    monkeypatch.setattr(resources, "_busy_cache", [float("-inf"), 0.0])
    monkeypatch.setattr(resources.os, "sched_getaffinity", lambda pid: {0, 1, 2, 3})   # a 4-core machine
    return resources


@pytest.mark.parametrize("others, limit, expected", [(0.0, 4, 4), (0.4, 4, 4), (0.6, 4, 3), (1.5, 4, 3),
                                                     (2.7, 4, 1), (9.0, 4, 1), (0.0, 2, 2), (3.0, 1, 1)])
def test_spare_blas_threads_leave_the_cores_other_processes_use(monkeypatch, others, limit, expected):
    resources = _busy(monkeypatch, others)
    assert resources.spare_blas_threads(limit) == expected


def test_other_processes_cores_is_a_share_of_the_machine():
    from hfrad import resources
    used = resources.other_processes_cores(0.05)
    import os
    if used is None:
        pytest.skip("no /proc on this system")
    assert 0.0 <= used <= 1.5 * os.cpu_count()


def test_merges_on_a_busy_machine_run_on_one_blas_thread_and_give_the_same_factors(monkeypatch, matrix):
    """The cap lowers the caller's threads inside the stream only, and the factors do not depend on it."""
    threadpoolctl = pytest.importorskip("threadpoolctl")
    A, _ = matrix
    with threadpoolctl.threadpool_limits(limits=2, user_api="blas"):
        from hfrad.lowrank import hf
        resources = _busy(monkeypatch, 0.0)
        free = hierarchical_factorization(col_blocks(A, 50), 400, eps=0.02, dtype=np.float64)
        resources = _busy(monkeypatch, 8.0)
        seen = []
        merge = hf.merge_nodes
        monkeypatch.setattr(hf, "merge_nodes", lambda *a: (seen.append(resources.blas_threads_now()), merge(*a))[1])
        busy = hierarchical_factorization(col_blocks(A, 50), 400, eps=0.02, dtype=np.float64)
        assert resources.blas_threads_now() == 2   # restored after each push
    assert seen and set(seen) == {1}
    assert busy.rank == free.rank
    # one BLAS thread against two: summation order only, observed 5e-17 of ||A||_F
    np.testing.assert_allclose(busy.Q @ busy.V.T, free.Q @ free.V.T, atol=1e-15 * np.linalg.norm(A))


def test_user_errors_of_the_low_rank_entry_points_are_input_errors():
    import numpy as np
    import pytest

    from hfrad.errors import InputError
    from hfrad.lowrank import hierarchical_factorization, lowrank_from_blocks, svd_factorization
    from hfrad.lowrank.hf import HFStream

    with pytest.raises(InputError, match="leaf_share must be in"):
        HFStream(10, 2, leaf_share=1.5)
    with pytest.raises(InputError, match="eps must be a finite number"):
        HFStream(10, 2, eps=float("nan"))
    stream = HFStream(10, 1)
    with pytest.raises(InputError, match=r"column block 0 must have shape \(10, b\)"):
        stream.push(np.ones((9, 5)))
    with pytest.raises(InputError, match="expected a 2-D matrix"):
        svd_factorization(np.ones(5), eps=0.1)
    with pytest.raises(InputError, match="must be known up front"):
        hierarchical_factorization(iter([np.ones((4, 2))]), 4, eps=0.1)
    blocks = [(0, 2, np.ones((4, 2))), (3, 4, np.ones((4, 1)))]
    with pytest.raises(InputError, match="must be consecutive: expected start 2, got 3"):
        lowrank_from_blocks(iter(blocks), 4, np.ones(4), np.arange(4), eps=0.1, relative=True,
                            dtype=np.float64, n_blocks=2)
