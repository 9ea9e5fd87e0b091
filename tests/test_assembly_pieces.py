"""The assembly step in pieces: the near-field set-up's pure functions in any panels, in this
process or on a LocalCluster, give the object the serial :func:`hfrad.precompute.assemble.assemble` gives."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse.linalg import splu

import hfrad
import hfrad.precompute.local as local
from hfrad import LocalBackend, PrecomputeOptions
from hfrad.formfactors import form_factor_matrix
from hfrad.scene.load import load_scene
from hfrad.precompute.assemble import assemble
from hfrad.solve.nearfield import InProcess, NearFieldFactorization, channel_solver, near_columns, solver_order
from hfrad.solve.quantized import QuantizedRows
from hfrad.solve.stats import PassStatistics


def _inputs(monkeypatch, n: int, *, block_size: int, **kw):
    """The scene and the arguments the local precompute passes to assemble() (captured), and its result."""
    seen = {}
    real = local.assemble

    def capture(scene, options, lowrank, stats, near=None, *, backend=None):
        seen.update(options=options, lowrank=lowrank, state=stats.state(), near=near)
        return real(scene, options, lowrank, stats, near, backend=backend)

    monkeypatch.setattr(local, "assemble", capture)
    scene = load_scene("cornell", patches=n)
    fac = hfrad.factorize(scene, backend=LocalBackend(processes=1),
                          options=PrecomputeOptions(block_size=block_size, one_ray_tol=0), **kw)
    return scene, seen, fac


def _stats(seen) -> PassStatistics:
    return PassStatistics.from_state(seen["state"])


def _codes(Z):
    return Z.codes if isinstance(Z, QuantizedRows) else Z


def test_reused_order_solves_the_other_matrix():
    """A matrix factored in another one's fill-reducing order (same pattern) solves its own system:
    SuperLU's solve of it to rounding (observed 1e-16 relative)."""
    rng = np.random.default_rng(5)
    n = 600
    N = sp.random(n, n, density=0.02, random_state=6, format="csr")
    N = (N + N.T) * 0.04                                  # symmetric pattern, as the near field's
    d1, d2 = np.ones(n), rng.uniform(0.2, 1.0, n)
    first = channel_solver(N, d1, np.float64)
    second = channel_solver(N, d2, np.float64, 1, solver_order(first))
    A2 = (sp.identity(n) - sp.diags(d2) @ N).tocsc()
    X = rng.standard_normal((n, 70))
    exact = np.column_stack([splu(A2).solve(X[:, j].copy()) for j in range(X.shape[1])])
    got = near_columns(second, np.ones(n), X)
    assert np.abs(got - exact).max() <= 1e-12 * np.abs(exact).max()
    # the order was not recomputed: the one passed in
    assert np.array_equal(second.order, first.order)


class _Panels(InProcess):
    """In this process, in narrow column panels, every channel factored on its own (as on Dask)."""

    columns = 7
    share_order = False


def test_any_panels_give_the_same_object(monkeypatch):
    """Column panels of 7 and fresh orderings: Z identical (16-bit codes and scales), K_c^{-1}
    to float32 rounding, the same radiosity and error figures."""
    scene, seen, fac = _inputs(monkeypatch, 500, eps=0.03, block_size=64, dtype="float32", near_field=32)
    assert isinstance(fac, NearFieldFactorization) and fac.rank > 7
    other = NearFieldFactorization(fac.perm, fac.Q, fac.V, fac.N, fac.rho_max, fac.reflectance, fac.lowrank,
                                   scene=scene, stats=fac.stats, runner=_Panels())
    assert other.near_solution_storage == fac.near_solution_storage
    assert np.array_equal(_codes(other.Z), _codes(fac.Z))
    if isinstance(fac.Z, QuantizedRows):
        assert np.array_equal(other.Z.scale, fac.Z.scale)
    K, K0 = other.capacitance_inv.astype(np.float64), fac.capacitance_inv.astype(np.float64)
    assert np.abs(K - K0).max() <= 1e-5 * np.abs(K0).max()
    B, B0 = other.solve(scene.emission), fac.solve(scene.emission)
    assert np.abs(B - B0).max() <= 1e-5 * np.abs(B0).max()
    np.testing.assert_allclose(other.quantization_error(), fac.quantization_error(), rtol=1e-12)
    np.testing.assert_allclose(other.error_estimate().bound, fac.error_estimate().bound, rtol=1e-5)


@pytest.mark.slow
def test_on_a_local_cluster_equals_the_serial_assembly_and_the_dense_solve(monkeypatch):
    """assemble_on_cluster on 2 workers: the serial assemble()'s object (Z identical, K_c^{-1} and
    radiosity to float32 rounding, same error figures), its radiosity within those figures of LAPACK's,
    and a record per piece."""
    pytest.importorskip("distributed")
    from hfrad.distributed import connect
    from hfrad.distributed.assembly import assemble_on_cluster

    scene, seen, _ = _inputs(monkeypatch, 600, eps=0.03, block_size=64, dtype="float32", near_field=32)
    serial = assemble(scene, seen["options"], seen["lowrank"], _stats(seen), seen["near"])
    records = []
    with connect(workers=2, processes=False) as cluster:
        fac = assemble_on_cluster(cluster, scene, seen["options"], seen["lowrank"], _stats(seen), seen["near"],
                                  columns=16, records=records)
    assert type(fac) is type(serial) and fac.rank == serial.rank
    assert np.array_equal(_codes(fac.Z), _codes(serial.Z))
    K, K0 = fac.capacitance_inv.astype(np.float64), serial.capacitance_inv.astype(np.float64)
    assert np.abs(K - K0).max() <= 1e-5 * np.abs(K0).max()
    E = np.zeros((scene.n_patches, 3, 2))
    E[:, :, 0] = scene.emission
    E[::7, 1, 1] = 1.0
    B, B0 = fac.solve(E), serial.solve(E)
    assert np.abs(B - B0).max() <= 1e-5 * np.abs(B0).max()
    est, est0 = fac.error_estimate(), serial.error_estimate()
    np.testing.assert_allclose(est.bound, est0.bound, rtol=1e-5)
    np.testing.assert_allclose(est.operator_error, est0.operator_error, rtol=1e-5)
    # against LAPACK on the exact F: within the stated bound
    F = form_factor_matrix(scene)
    exact = np.stack([np.linalg.solve(np.eye(scene.n_patches) - scene.reflectance[:, c, None] * F,
                                      scene.emission[:, c]) for c in range(3)], axis=1)
    w = np.sqrt(scene.areas)[:, None]
    err = np.linalg.norm(w * (B[:, :, 0] - exact), axis=0) / np.linalg.norm(w * exact, axis=0)
    assert (err <= est.bound).all()
    pieces = {r["piece"] for r in records}
    assert {"channel_solver", "near_columns", "row_maxima", "column_products"} <= pieces
    distinct = len(fac.distinct_channels)
    assert sum(r["piece"] == "channel_solver" for r in records) == distinct
    assert sum(r["piece"] == "near_columns" for r in records) == distinct * -(-fac.rank // 16)
