"""Baseline solvers: LU, Jacobi, Gauss-Seidel, Southwell and GMRES reach the exact radiosity."""

import numpy as np
import pytest
from conftest import closed_system

from hfrad.solve.denselu import LUFactorization, solve_direct
from hfrad.solve.iterative import gauss_seidel, gmres, jacobi, southwell





@pytest.fixture(scope="module")
def system():
    F, areas, rho = closed_system(150, seed=5)
    E = np.zeros((150, 3))
    E[:10] = np.random.default_rng(0).random((10, 3)) * 100.0
    B = np.column_stack([np.linalg.solve(np.eye(150) - rho[:, c:c + 1] * F, E[:, c]) for c in range(3)])
    return F, areas, rho, E, B


def test_direct(system):
    F, _, rho, E, B = system
    np.testing.assert_allclose(solve_direct(F, rho, E), B, rtol=1e-10)
    lu = LUFactorization(F, rho)
    x = lu.solve(E, trans="T")
    for c in range(3):
        np.testing.assert_allclose((np.eye(150) - rho[:, c:c + 1] * F).T @ x[:, c], E[:, c], atol=1e-9)


@pytest.mark.parametrize("solver", [jacobi, gauss_seidel, southwell, gmres])
def test_converges(system, solver):
    F, areas, rho, E, B = system
    rtol = 1e-8
    kw = {"areas": areas} if solver is southwell else {}
    out = solver(F, rho, E, rtol=rtol, **kw)
    assert out.converged
    assert out.radiosity.shape == (150, 3)
    assert (out.residual <= rtol * (1 + 1e-6)).all()
    assert (out.iterations > 0).all()
    # residual rtol and cond(I - RF) <= (1 + ||RF||) / (1 - ||RF||) bound the error
    err = np.linalg.norm(out.radiosity - B, axis=0) / np.linalg.norm(B, axis=0)
    assert (err < 1e-6).all(), err


def test_iteration_counts_are_ordered(system):
    F, areas, rho, E, _ = system
    it_j = jacobi(F, rho, E, rtol=1e-6).iterations
    it_gs = gauss_seidel(F, rho, E, rtol=1e-6).iterations
    assert (it_gs <= it_j).all()
    sw = southwell(F, rho, E, areas=areas, rtol=1e-6)
    assert (sw.iterations >= 10).all()          # at least every emitter shot once


def test_zero_emission(system):
    F, _, rho, _, _ = system
    out = gauss_seidel(F, rho, np.zeros(150))
    assert out.converged and not out.radiosity.any()
