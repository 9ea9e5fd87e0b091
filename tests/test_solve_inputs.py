"""The solvers' constructors and baselines refuse the user's mistakes with InputError naming the argument."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
from conftest import closed_system

from hfrad.errors import InputError
from hfrad.lowrank.factors import LowRank
from hfrad.solve.iterative import gauss_seidel, jacobi
from hfrad.solve.nearfield import NearFieldFactorization
from hfrad.solve.quantized import QuantizedRows
from hfrad.solve.woodbury import HFactorization

N, K = 40, 3


@pytest.fixture(scope="module")
def parts():
    """perm, Q, V, rho_max, reflectance and LowRank of a rank-3 approximation of a small closed system."""
    F, _, rho = closed_system(N, seed=2)
    rho_max = rho.max(axis=1)
    U, s, Vt = np.linalg.svd(rho_max[:, None] * F)
    Q, V = U[:, :K] * s[:K], Vt[:K].T
    lr = LowRank(Q=Q, V=V, achieved_error=float(np.sqrt(np.sum(s[K:] ** 2))), norm=float(np.sqrt(np.sum(s ** 2))),
                 eps=0.5, method="svd")
    return np.arange(N), Q, V, rho_max, rho, lr


def test_a_consistent_factorization_solves(parts):
    perm, Q, V, rho_max, rho, lr = parts
    fac = HFactorization(perm[::-1], Q[::-1], V[::-1], rho_max, rho, lr)   # internal order reversed
    same = HFactorization(perm, Q, V, rho_max, rho, lr)
    E = np.random.default_rng(0).random((N, 3))
    np.testing.assert_allclose(fac.solve(E), same.solve(E), rtol=1e-12)    # the order changes nothing


@pytest.mark.parametrize("change, match", [
    (dict(perm=np.zeros(N, int)), rf"perm must be a permutation of 0\.\.{N - 1}"),
    (dict(perm=np.arange(1, N + 1)), "perm must be a permutation"),
    (dict(perm=np.arange(N, dtype=float)), r"perm must be a 1-D integer array.*float64"),
    (dict(perm=np.arange(N).reshape(2, -1)), r"perm must be a 1-D integer array.*\(2, 20\)"),
    (dict(Q=np.ones((N - 1, K))), rf"Q must be a float array of shape \({N}, k\).*\({N - 1}, {K}\)"),
    (dict(Q=np.ones((N, K), int)), r"Q must be a float array.*int64"),
    (dict(V=np.ones((N, K + 1))), rf"V must be a float array of Q's shape \({N}, {K}\); got shape \({N}, {K + 1}\)"),
    (dict(rho_max=np.ones(N + 1)), rf"rho_max must have one entry per patch \({N}\); got shape \({N + 1},\)"),
    (dict(reflectance=np.full((N, 1), 0.5)), rf"reflectance must have shape \({N}, 3\); got \({N}, 1\)"),
    (dict(capacitance=np.zeros((3, K, K + 1))), rf"capacitance must have shape \(3, {K}, {K}\)"),
])
def test_bad_factorization_arguments(parts, change, match):
    perm, Q, V, rho_max, rho, lr = parts
    args = dict(perm=perm, Q=Q, V=V, rho_max=rho_max, reflectance=rho)
    args.update({k: v for k, v in change.items() if k in args})
    extra = {k: v for k, v in change.items() if k not in args}
    with pytest.raises(InputError, match=match):
        HFactorization(args["perm"], args["Q"], args["V"], args["rho_max"], args["reflectance"], lr, **extra)


def test_bad_near_field_arguments(parts):
    perm, Q, V, rho_max, rho, lr = parts
    with pytest.raises(InputError, match=rf"N \(the near field\) must be a sparse or dense \({N}, {N}\) matrix.*"
                                         rf"\({N}, {N - 1}\)"):
        NearFieldFactorization(perm, Q, V, sp.csr_matrix((N, N - 1)), rho_max, rho, lr)
    with pytest.raises(InputError, match=r"N \(the near field\).*list"):
        NearFieldFactorization(perm, Q, V, [[0.0] * N] * N, rho_max, rho, lr)
    fac = NearFieldFactorization(perm, Q, V, sp.csr_matrix((N, N)), rho_max, rho, lr, quantize=False)
    assert len(fac.distinct_channels) == 3
    with pytest.raises(InputError, match=rf"near_solution must have shape \(3, {N}, {K}\).*\[0, 1, 2\]\); "
                                         rf"got \(1, {N}, {K}\)"):
        NearFieldFactorization(perm, Q, V, fac.N, rho_max, rho, lr, near_solution=fac.Z[:1],
                               capacitance=fac.capacitance_inv)
    # the stored pieces, given back, give the same solve without a set-up
    again = NearFieldFactorization(perm, Q, V, fac.N, rho_max, rho, lr, near_solution=fac.Z,
                                   capacitance=fac.capacitance_inv)
    E = np.random.default_rng(1).random((N, 3))
    np.testing.assert_array_equal(again.solve(E), fac.solve(E))


def test_quantized_rows_shapes():
    with pytest.raises(InputError, match=r"do not match: codes \(4, 3\), scale \(3,\)"):
        QuantizedRows(np.zeros((4, 3), np.int16), np.zeros(3, np.float32))
    with pytest.raises(InputError, match=r"codes \(3,\)"):
        QuantizedRows(np.zeros(3, np.int16), np.zeros((), np.float32))


@pytest.mark.parametrize("solver", [jacobi, gauss_seidel])
def test_iterative_baselines_name_the_bad_array(solver):
    F, _, rho = closed_system(N, seed=2)
    E = np.ones((N, 3))
    with pytest.raises(InputError, match=rf"form_factors must be a square \(n, n\) matrix; got shape \({N}, {N - 1}\)"):
        solver(F[:, 1:], rho, E)
    with pytest.raises(InputError, match=rf"reflectance must have shape \({N}, 3\).*got \({N}, 2\)"):
        solver(F, rho[:, :2], E)
    with pytest.raises(InputError, match=rf"exitance must have shape \({N},\) or \({N}, 3\).*got \({N - 1}, 3\)"):
        solver(F, rho, E[1:])
    B = solver(F, rho, E).radiosity
    Bx = np.stack([np.linalg.solve(np.eye(N) - rho[:, c:c + 1] * F, E[:, c]) for c in range(3)], axis=1)
    np.testing.assert_allclose(B, Bx, rtol=5e-6)           # stops at residual 1e-6; observed 7.5e-7 to 9.9e-7
