"""HFactorization: Woodbury solves (eq. 4) against exact solves, error figures, colour, adjoint.

Tolerances are about 3x the errors observed (noted beside each); the guaranteed
figures are checked to hold, the eq. 5 figure as the paper states it.
"""

import numpy as np
import pytest
from conftest import closed_system

from hfrad.errors import FactorizationError
from hfrad import factorize_matrix
from hfrad.pipeline import factorize_blocks
from hfrad.solve.bounds import residual_norm




def exact(F, rho, E, transpose=False):
    n = len(F)
    out = np.empty((n, 3))
    for c in range(3):
        A = np.eye(n) - rho[:, c:c + 1] * F
        out[:, c] = np.linalg.solve(A.T if transpose else A, E[:, c])
    return out


@pytest.fixture(scope="module")
def system():
    F, areas, rho = closed_system(300)
    fac = factorize_matrix(F, rho, areas=areas, eps=0.02, block_size=32, dtype=np.float64)
    return F, areas, rho, fac


def area_error(B, Bx, areas):
    w = np.sqrt(areas)[:, None]
    return np.linalg.norm(w * (B - Bx), axis=0) / np.linalg.norm(w * Bx, axis=0)


def test_solve_error_and_its_figures(system):
    F, areas, rho, fac = system
    E = np.random.default_rng(1).random((300, 3))
    B = fac.solve(E)
    Bx = exact(F, rho, E)
    err = np.linalg.norm(B - Bx, axis=0) / np.linalg.norm(Bx, axis=0)
    assert (err < 1e-3).all(), err                             # observed 2.4-3.0e-4
    assert fac.relative_error <= 0.02
    est = fac.error_estimate()
    err_a = area_error(B, Bx, areas)
    assert est.norm == "area" and est.kind == "probes"
    assert (err_a <= est.bound).all(), (err_a, est.bound)      # guaranteed (failure probability 1e-6)
    assert (err <= est.eq5_bound).all()                        # the paper's eq. 5, in the 2-norm
    figure = fac.residual(E, B, form_factors=F)                # the tight per-solution figure
    # observed 9.6-9.9 times the error
    assert (err_a <= figure.bound).all() and (figure.bound <= 20 * err_a).all(), (err_a, figure.bound)
    # the a-posteriori residual is small and consistent with the solve
    blocks = ((s, s + 50, F[:, s:s + 50]) for s in range(0, 300, 50))
    res = residual_norm(blocks, rho, E, B)
    assert (res < 2e-3).all(), res                           # observed 4.2-5.3e-4
    res_exact = residual_norm(((0, 300, F),), rho, E, Bx)
    assert (res_exact < 1e-14).all(), res_exact               # observed 7.3-7.8e-16


def test_furnace_uniform():
    F, _, _ = closed_system(200, seed=3)
    n = len(F)
    rho = np.full((n, 3), 0.5)
    E = np.ones(n)
    for eps, tol in ((0.05, 2e-3), (1e-5, 2e-14)):   # observed 5.1e-4 and 1.8e-15
        fac = factorize_matrix(F, rho, eps=eps, block_size=16, dtype=np.float64)
        B = fac.solve(E)
        np.testing.assert_allclose(B, 2.0, rtol=tol)


def test_transpose_matches_adjoint(system):
    F, _, rho, fac = system
    e = np.random.default_rng(2).standard_normal((300, 3))   # negative allowed for the adjoint
    x = fac.solve(e, trans="T")
    xx = exact(F, rho, e, transpose=True)
    err = np.linalg.norm(x - xx, axis=0) / np.linalg.norm(xx, axis=0)
    assert (err < 2.5e-3).all(), err                          # observed 6.1-7.5e-4


def test_batched_equals_single(system):
    *_, fac = system
    E = np.random.default_rng(3).random((300, 3, 4))
    B = fac.solve(E)
    assert B.shape == (300, 3, 4)
    for i in range(4):
        np.testing.assert_allclose(B[:, :, i], fac.solve(E[:, :, i]), rtol=1e-14)   # observed 9.4e-16
    grey = fac.solve(E[:, 0, 0])
    np.testing.assert_allclose(grey, fac.solve(np.repeat(E[:, :1, 0], 3, axis=1)), rtol=1e-14)   # observed 0


def test_user_order_permutation(system):
    F, _, rho, fac = system
    p = np.random.default_rng(4).permutation(300)
    fac_p = factorize_matrix(F[np.ix_(p, p)], rho[p], eps=0.02, block_size=32, dtype=np.float64,
                             order=np.argsort(p))     # same internal order as fac
    E = np.random.default_rng(5).random((300, 3))
    # observed 0 (the same arithmetic); the margin: BLAS summation order (threads) may differ between runs
    np.testing.assert_allclose(fac_p.solve(E[p]), fac.solve(E)[p], rtol=1e-13)


def test_identity_vs_random_order_within_bound(system):
    F, _, rho, fac = system
    perm = np.random.default_rng(6).permutation(300)
    fac_r = factorize_matrix(F, rho, eps=0.02, block_size=32, dtype=np.float64, order=perm)
    E = np.random.default_rng(7).random((300, 3))
    B1, B2 = fac.solve(E), fac_r.solve(E)
    diff = np.linalg.norm(B1 - B2, axis=0) / np.linalg.norm(B1, axis=0)
    assert (diff < 1e-3).all(), diff                          # observed 2.1-2.9e-4


def test_streaming_equals_in_core(system):
    F, _, rho, fac = system
    perm = np.arange(300)

    def gen():
        for s in range(0, 300, 32):
            yield s, min(s + 32, 300), F[:, s:s + 32].copy()
    fac_s = factorize_blocks(gen(), 300, rho, perm, eps=0.02, dtype=np.float64, n_blocks=10)
    # observed 0 (the same blocks); the margin: BLAS summation order (threads) may differ between runs
    np.testing.assert_allclose(fac_s.Q, fac.Q, rtol=0, atol=1e-13)
    np.testing.assert_allclose(fac_s.V, fac.V, rtol=0, atol=1e-13)


def test_with_reflectance(system):
    F, _, rho, fac = system
    rho2 = rho * np.random.default_rng(8).uniform(0.5, 1.0, rho.shape)
    rho2 = np.minimum(rho2, rho.max(1, keepdims=True))
    fac2 = fac.with_reflectance(rho2)
    fresh = factorize_matrix(F, rho2, eps=0.02, block_size=32, dtype=np.float64)
    E = np.random.default_rng(9).random((300, 3))
    Bx = exact(F, rho2, E)
    for f in (fac2, fresh):
        err = np.linalg.norm(f.solve(E) - Bx, axis=0) / np.linalg.norm(Bx, axis=0)
        assert (err < 7e-4).all(), err                        # observed 1.6-2.3e-4
    bad = rho.copy()
    bad[17, 1] = rho[17].max() + 0.05
    with pytest.raises(ValueError, match="patch 17"):
        fac.with_reflectance(bad)


@pytest.mark.parametrize("E, msg", [
    (np.ones(299), r"\(300,\), \(300, 3\) or \(300, 3, m\).*got \(299,\)"),
    (np.ones((300, 2)), r"got \(300, 2\)"),
    (np.full(300, np.nan), "NaN"),
    (-np.ones((300, 3)), "negative"),
])
def test_bad_inputs(system, E, msg):
    *_, fac = system
    with pytest.raises(ValueError, match=msg):
        fac.solve(E)


def test_bad_factorize_inputs(system):
    F, _, rho, _ = system
    with pytest.raises(ValueError, match="reflectance"):
        factorize_matrix(F, np.full((300, 3), 1.0))
    with pytest.raises(ValueError, match="method"):
        factorize_matrix(F, rho, method="qr")
    with pytest.raises(ValueError, match="permutation"):
        factorize_matrix(F, rho, order=np.zeros(300, int))


def test_float32_and_singular():
    F, _, rho = closed_system(120, seed=11)
    fac = factorize_matrix(F, rho, eps=0.01, block_size=16)
    assert fac.Q.dtype == np.float32 and fac.V.dtype == np.float32
    assert fac.capacitance_inv.dtype == np.float32 and fac.capacitance_inv.shape == (3, fac.rank, fac.rank)
    E = np.random.default_rng(0).random((120, 3))
    Bx = exact(F, rho, E)
    err = np.linalg.norm(fac.solve(E) - Bx, axis=0) / np.linalg.norm(Bx, axis=0)
    assert (err < 7e-4).all(), err                            # observed 1.1-2.3e-4 (float32 factors)
    # rank-1 RF = 1 1^T / n has eigenvalue 1: I - V^T Q = 0 is singular
    from hfrad.solve.woodbury import HFactorization
    with pytest.raises(FactorizationError, match="singular"):
        HFactorization(fac.perm, np.ones((120, 1)), np.full((120, 1), 1.0 / 120), np.full(120, 0.5),
                       np.full((120, 3), 0.5), fac.lowrank)


def test_keeps_only_q_v_and_small_factors(system):
    """Memory: nothing n x k beyond Q and V (no Y_c); three k x k inverses in the factors' dtype."""
    F, _, rho, fac = system
    n, k = fac.Q.shape
    assert fac.V.shape == (n, k) and 0 < k < n
    arrays = {name: v for name, v in vars(fac).items() if isinstance(v, np.ndarray)}
    assert arrays["capacitance_inv"].shape == (3, k, k) and arrays["capacitance_inv"].dtype == fac.dtype
    big = {name for name, v in arrays.items() if v.size >= n * k and name != "capacitance_inv"}
    assert big == {"Q", "V"}, big
    assert sum(v.nbytes for v in arrays.values()) <= (2 * n * k + 3 * k * k + 20 * n) * 8


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_capacitance_precision(dtype):
    """M_c from float32 products solves as accurately as from float64 ones (vs the exact dense solve), both trans."""
    from hfrad.solve.woodbury import capacitance, invert_capacitance, low_rank_correction
    F, _, rho = closed_system(300)
    fac = factorize_matrix(F, rho, eps=0.02, block_size=32, dtype=dtype)
    E = np.random.default_rng(10).random((300, 3, 2))
    Ei = E[fac.perm]
    for adjoint in (False, True):
        Bx = np.stack([exact(F, rho, E[:, :, j], transpose=adjoint) for j in range(2)], axis=2)
        B = {}
        for setup in (np.float32, np.float64):
            M = capacitance(fac.Q, fac.V, fac._D, dtype=setup)
            inv = np.stack([invert_capacitance(M[c], "M", fac.dtype) for c in range(3)])
            B[setup] = (Ei + low_rank_correction(fac.Q, fac.V, fac._D, inv, Ei, adjoint))[fac.inv_perm]
            err = np.linalg.norm(B[setup] - Bx) / np.linalg.norm(Bx)
            assert err < 1e-3, (adjoint, setup, err)                             # observed 2.3e-4
        diff = np.linalg.norm(B[np.float32] - B[np.float64]) / np.linalg.norm(Bx)
        assert diff < 3e-7, (adjoint, diff)                                       # observed 2-6e-8


def test_capacitance_grey_shortcut_equals_direct():
    """M_c via V^T Q minus the coloured patches' rows equals the direct V^T D_c Q."""
    from hfrad.solve.woodbury import capacitance
    rng = np.random.default_rng(12)
    n, k = 200, 17
    Q, V = rng.standard_normal((n, k)), rng.standard_normal((n, k)) / n
    D = np.ones((n, 3))
    D[:30, 0], D[40:50, 2] = rng.random(30), rng.random(10)       # few coloured patches: the shortcut
    direct = np.stack([np.eye(k) - V.T @ (D[:, c:c + 1] * Q) for c in range(3)])
    np.testing.assert_allclose(capacitance(Q, V, D), direct, rtol=0, atol=2e-15)   # observed 2.2e-16
    D = rng.random((n, 3))                                          # all coloured: the direct products
    direct = np.stack([np.eye(k) - V.T @ (D[:, c:c + 1] * Q) for c in range(3)])
    np.testing.assert_allclose(capacitance(Q, V, D), direct, rtol=0, atol=2e-15)   # observed 0


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_thin_products_match_numpy(dtype):
    """The streaming kernels of the solve equal numpy's products (zero rows skipped, BLAS above THIN_MAX)."""
    from hfrad.solve import thin
    rng = np.random.default_rng(13)
    A = rng.standard_normal((1000, 37)).astype(dtype)
    tol = 1e-6 if dtype == np.float32 else 3e-15                  # observed 2.6e-7 / 6.7e-16 (relative to max)
    for r in (1, 3, thin.THIN_MAX + 1):
        S, X = rng.standard_normal((37, r)), rng.standard_normal((1000, r))
        X[rng.random(1000) < 0.9] = 0.0                             # most patches do not emit
        for got, ref in ((thin.matmul(A, S), A.astype(np.float64) @ S),
                         (thin.tmatmul(A, X), A.astype(np.float64).T @ X)):
            assert got.dtype == dtype and got.shape == ref.shape
            assert np.abs(got - ref).max() <= tol * np.abs(ref).max(), (r, np.abs(got - ref).max())
    np.testing.assert_array_equal(thin.tmatmul(A, np.zeros((1000, 3))), 0.0)


def _machine(monkeypatch, others_per_second: float, cores: int = 4):
    """A ``cores``-core machine whose other processes use ``others_per_second`` cores (fake /proc)."""
    from hfrad import resources

    clock = {"t": 0.0}
    monkeypatch.setattr(resources.os, "sched_getaffinity", lambda pid: set(range(cores)))
    monkeypatch.setattr(resources.os, "sysconf", lambda name: 100)                  # 100 ticks a second
    monkeypatch.setattr(resources.time, "perf_counter", lambda: clock["t"])
    monkeypatch.setattr(resources, "_machine_jiffies", lambda: (int(100 * others_per_second * clock["t"]), 0))
    monkeypatch.setattr(resources, "_jiffies", lambda pids: 0)
    monkeypatch.setattr(resources, "_quick", {"t": None, "busy": 0, "mine": 0, "spare": None})
    return resources, clock


@pytest.mark.parametrize("others, expected", [(0.0, 4), (0.4, 4), (1.6, 2), (3.5, 1), (9.0, 1)])
def test_a_solve_uses_the_cores_other_processes_leave(monkeypatch, others, expected):
    resources, clock = _machine(monkeypatch, others)
    assert resources.spare_cores_now() == 4            # no reading yet: every core
    clock["t"] = 2.0
    assert resources.spare_cores_now() == expected     # measured over the 2 s since
    clock["t"] = 2.5
    assert resources.spare_cores_now() == expected     # reused within a second
    clock["t"] = 100.0
    assert resources.spare_cores_now() == 4            # a stale reading says nothing of now


def test_solve_threads_lower_numba_inside_only(monkeypatch):
    import numba

    resources, clock = _machine(monkeypatch, 9.0, cores=numba.config.NUMBA_NUM_THREADS)
    resources.spare_cores_now()
    clock["t"] = 2.0
    before = numba.get_num_threads()
    with resources.solve_threads():
        inside = numba.get_num_threads()
    assert inside == 1 and numba.get_num_threads() == before
