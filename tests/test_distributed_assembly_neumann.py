"""The cluster's assembly without sparse LUs (hfrad.distributed.assembly, neumann=True): Z_c by Neumann sweeps
per column panel, as accurate as the LU path (checked against float64 LU solves and LAPACK)."""

from __future__ import annotations

import numpy as np
import pytest

import hfrad.precompute.local as local
from hfrad import LocalBackend, PrecomputeOptions, factorize
from hfrad.distributed.assembly import NeumannColumns, SETUP_TOL
from hfrad.solve.prefetch import channel_scales, near_matrix
from hfrad.scene.load import load_scene
from hfrad.precompute.assemble import assemble
from hfrad.solve.nearfield import channel_solver
from hfrad.solve.neumann import spectral_bound
from hfrad.solve.quantized import QuantizedRows
from hfrad.solve.stats import PassStatistics


@pytest.fixture(scope="module")
def inputs():
    """A 600-patch Cornell box: what the local precompute passes to assemble(), and its result."""
    seen = {}
    real = local.assemble
    mp = pytest.MonkeyPatch()

    def capture(scene, options, lowrank, stats, near=None, *, backend=None):
        seen.update(options=options, lowrank=lowrank, state=stats.state(), near=near)
        return real(scene, options, lowrank, stats, near, backend=backend)

    mp.setattr(local, "assemble", capture)
    scene = load_scene("cornell", patches=600)
    fac = factorize(scene, eps=0.03, dtype="float32", near_field=32, backend=LocalBackend(processes=1),
                    options=PrecomputeOptions(block_size=64))
    mp.undo()
    return scene, seen, fac


def test_neumann_columns_equal_float64_lu_solves(inputs):
    """A_c^{-1} D_c Q by sweeps: within SETUP_TOL / (1 - rho) of float64 SuperLU (observed ~1e-8), closer
    than the float32 LU panels the local path stores."""
    scene, seen, fac = inputs
    options = seen["options"]
    N = near_matrix(seen["near"], scene.n_patches)
    rho = spectral_bound(N)
    assert 0 < rho < 1
    distinct, d = channel_scales(scene.reflectance, options.perm)
    Q = seen["lowrank"].Q
    for c in distinct:
        X = d[c][:, None].astype(Q.dtype) * Q
        exact = channel_solver(N, d[c], np.float64, c).solve(X.astype(np.float64))
        sweeps = NeumannColumns(N, d[c], np.float64, c, rho)
        got = sweeps.solve(X)
        assert sweeps.last_sweeps > 0
        assert np.abs(got - exact).max() <= 2 * SETUP_TOL / (1 - rho) * np.abs(exact).max()
        lu32 = channel_solver(N, d[c], np.float32, c).solve(X)
        assert np.abs(got - exact).max() <= np.abs(lu32 - exact).max() + SETUP_TOL * np.abs(exact).max()


def test_no_convergence_falls_back_to_the_lu(inputs):
    scene, seen, fac = inputs
    N = near_matrix(seen["near"], scene.n_patches)
    d = np.ones(scene.n_patches)
    X = np.random.default_rng(1).standard_normal((scene.n_patches, 5))
    sweeps = NeumannColumns(N, d, np.float64, 0, rho=1.0)      # a bound of 1: the series is not tried
    got = sweeps.solve(X)
    assert sweeps.last_sweeps == 0
    exact = channel_solver(N, d, np.float64).solve(X)
    assert np.abs(got - exact).max() <= 1e-12 * np.abs(exact).max()


@pytest.mark.slow
def test_cluster_assembly_by_sweeps_matches_the_serial_one(inputs):
    """assemble_on_cluster(neumann=True) on 3 in-process workers: no LU piece; the serial (LU) object's
    storage, K_c^{-1} and radiosity to float32 rounding, its error figures; radiosity within them of LAPACK's."""
    pytest.importorskip("distributed")
    from hfrad.distributed import connect
    from hfrad.distributed.assembly import assemble_on_cluster
    from hfrad.formfactors import form_factor_matrix

    scene, seen, _ = inputs
    stats = PassStatistics.from_state(seen["state"])
    serial = assemble(scene, seen["options"], seen["lowrank"], stats, seen["near"])
    records = []
    with connect(workers=3, processes=False) as cluster:
        fac = assemble_on_cluster(cluster, scene, seen["options"], seen["lowrank"], stats, seen["near"],
                                  columns=16, neumann=True, records=records)
    pieces = [r["piece"] for r in records]
    assert "channel_solver" not in pieces and pieces.count("spectral_bound") == 1
    assert pieces.count("near_columns") == len(fac.distinct_channels) * -(-fac.rank // 16)
    assert type(fac) is type(serial) and fac.rank == serial.rank
    assert fac.near_solution_storage == serial.near_solution_storage
    if isinstance(serial.Z, QuantizedRows):   # 16-bit codes: a code apart at most (Z within 1e-6 relative)
        assert np.abs(fac.Z.codes.astype(int) - serial.Z.codes.astype(int)).max() <= 1
    K, K0 = fac.capacitance_inv.astype(np.float64), serial.capacitance_inv.astype(np.float64)
    assert np.abs(K - K0).max() <= 1e-5 * np.abs(K0).max()
    B, B0 = fac.solve(scene.emission), serial.solve(scene.emission)
    assert np.abs(B - B0).max() <= 1e-5 * np.abs(B0).max()
    # the figures read Z through its 16-bit row scales (maxima of Z's rows): observed 1.4e-5 apart
    est, est0 = fac.error_estimate(), serial.error_estimate()
    np.testing.assert_allclose(est.bound, est0.bound, rtol=1e-4)
    F = form_factor_matrix(scene)
    exact = np.stack([np.linalg.solve(np.eye(scene.n_patches) - scene.reflectance[:, c, None] * F,
                                      scene.emission[:, c]) for c in range(3)], axis=1)
    w = np.sqrt(scene.areas)[:, None]
    err = np.linalg.norm(w * (B - exact), axis=0) / np.linalg.norm(w * exact, axis=0)
    assert (err <= est.bound).all()
