"""A factorization's arrays are read-only (also after loading an .hfr file); its costly figures are computed once."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
from conftest import closed_system

import hfrad.solve.nearfield as nearfield
import hfrad.solve.woodbury as woodbury
from hfrad import factorize_matrix
from hfrad.lowrank.factors import LowRank
from hfrad.solve.hfr import load_hfr, save_hfr
from hfrad.solve.nearfield import NearFieldFactorization
from hfrad.solve.quantized import QuantizedRows
from hfrad.solve.stats import PassStatistics

N_PATCHES = 120


def exact(F, rho, E):
    """Radiosity per channel by LAPACK: ``(I - R_c F) B_c = E_c``."""
    return np.stack([np.linalg.solve(np.eye(len(F)) - rho[:, c:c + 1] * F, E[:, c]) for c in range(3)], axis=1)


@pytest.fixture(scope="module")
def system():
    return closed_system(N_PATCHES, seed=5)


@pytest.fixture(scope="module")
def plain(system):
    F, areas, rho = system
    return factorize_matrix(F, rho, areas=areas, eps=0.02, block_size=16, dtype=np.float64)


def near_split(system, *, rank=64, band=8, quantize=None, dtype=np.float64):
    """A near-field factorization built directly: N the entries of G within ``band`` of the diagonal,
    Q V^T the best rank-``rank`` approximation of the rest (the identity order)."""
    F, areas, rho = system
    n = len(F)
    rho_max = rho.max(axis=1)
    G = rho_max[:, None] * F
    near = np.abs(np.subtract.outer(np.arange(n), np.arange(n))) <= band
    N = sp.csr_matrix(np.where(near, G, 0.0))
    U, s, Vt = np.linalg.svd(G - N.toarray())
    Q, V = (U[:, :rank] * s[:rank]).astype(dtype), Vt[:rank].T.astype(dtype)
    lr = LowRank(Q=Q, V=V, achieved_error=float(np.sqrt(np.sum(s[rank:] ** 2))), norm=float(np.linalg.norm(G)),
                 eps=0.05, method="svd")
    stats = PassStatistics(n, areas)
    stats.add(0, n, F, rho_max[:, None])
    return NearFieldFactorization(np.arange(n), Q, V, N, rho_max, rho, lr, quantize=quantize, stats=stats)


def assert_read_only(fac):
    """Every array the solve depends on refuses writes; a solve's result is the caller's to change."""
    arrays = {"perm": fac.perm, "inv_perm": fac.inv_perm, "Q": fac.Q, "V": fac.V, "rho_max": fac.rho_max,
              "reflectance": fac.reflectance, "capacitance_inv": fac.capacitance_inv,
              "lowrank.Q": fac.lowrank.Q, "lowrank.V": fac.lowrank.V, "error_bound": fac.error_bound(),
              "sigma_max": fac.sigma_max(), "eq5_bound": fac.eq5_bound()}
    if fac.stats is not None:
        arrays.update({"stats.sketch": fac.stats.sketch, "stats.row_sums": fac.stats.row_sums})
    if isinstance(fac, NearFieldFactorization):
        arrays.update({"N.data": fac.N.data, "N.indices": fac.N.indices, "N.indptr": fac.N.indptr})
        if isinstance(fac.Z, QuantizedRows):
            arrays.update({"Z.codes": fac.Z.codes, "Z.scale": fac.Z.scale})
        else:
            arrays["Z"] = fac.Z
    for name, a in arrays.items():
        assert not a.flags.writeable, name
    with pytest.raises(ValueError, match="read-only"):
        fac.Q[0, 0] = 1.0
    with pytest.raises(ValueError, match="read-only"):
        fac.reflectance[0] = 0.0
    with pytest.raises(ValueError, match="read-only"):
        fac.error_bound()[0] = 0.0
    B = fac.solve(np.ones((fac.n_patches, 3)))
    assert B.flags.writeable
    B[0, 0] = -1.0   # the caller's own array
    return B


def test_plain_factorization_is_read_only_and_the_callers_arrays_are_not(system, plain):
    F, areas, rho = system
    assert_read_only(plain)
    # the constructor took views: the arrays it was given keep their flags
    Q, V = np.array(plain.Q), np.array(plain.V)
    fac = woodbury.HFactorization(np.arange(N_PATCHES), Q, V, rho.max(axis=1), rho, plain.lowrank)
    assert Q.flags.writeable and V.flags.writeable and not fac.Q.flags.writeable
    assert np.shares_memory(fac.Q, Q)                       # a view, no copy
    # with_reflectance builds a new factorization from the read-only arrays, itself read-only
    rho2 = 0.8 * rho
    other = plain.with_reflectance(rho2)
    assert_read_only(other)
    E = np.random.default_rng(2).random((N_PATCHES, 3))
    Bx = exact(F, rho2, E)
    err = np.linalg.norm(other.solve(E) - Bx, axis=0) / np.linalg.norm(Bx, axis=0)
    assert (err < 1e-3).all(), err                          # observed 1-2e-4 (eps 0.02)


def test_near_field_factorization_is_read_only(system):
    F, areas, rho = system
    w = np.sqrt(areas)[:, None]
    for quantize in (False, True):
        fac = near_split(system, quantize=quantize)
        assert isinstance(fac.Z, QuantizedRows) == quantize
        assert_read_only(fac)
        Bx = exact(F, rho, np.ones((N_PATCHES, 3)))
        B = fac.solve(np.ones((N_PATCHES, 3)))
        err = np.linalg.norm(w * (B - Bx), axis=0) / np.linalg.norm(w * Bx, axis=0)
        assert (err < 3e-3).all(), err                      # observed 6.3-9.0e-4 (rank 64 of 120)
        assert_read_only(fac.with_reflectance(0.9 * rho))


def test_loaded_factorizations_are_read_only(system, plain, tmp_path):
    for fac in (plain, near_split(system, quantize=True, dtype=np.float32)):
        back = load_hfr(save_hfr(fac, tmp_path / "f.hfr"))
        assert type(back) is type(fac)
        assert_read_only(back)
        np.testing.assert_allclose(back.solve(np.ones((N_PATCHES, 3))), fac.solve(np.ones((N_PATCHES, 3))),
                                   rtol=1e-6)               # float32: observed 1e-7


def test_frozen_statistics_refuse_more_columns_and_leave_the_original_writable(system):
    F, areas, rho = system
    stats = PassStatistics(N_PATCHES, areas)
    frozen = stats.frozen()
    with pytest.raises(ValueError, match="read-only"):
        frozen.add(0, N_PATCHES, F, rho.max(axis=1)[:, None])
    stats.add(0, N_PATCHES, F, rho.max(axis=1)[:, None])
    np.testing.assert_allclose(stats.row_sums, 1.0, rtol=1e-12)     # F's rows sum to 1 exactly


def counting(monkeypatch, module, name):
    """Replace ``module.name`` by a wrapper that counts its calls; returns the list of calls."""
    calls = []
    original = getattr(module, name)

    def wrapper(*args, **kwargs):
        calls.append(args)
        return original(*args, **kwargs)

    monkeypatch.setattr(module, name, wrapper)
    return calls


def test_costly_figures_are_computed_once(system, monkeypatch):
    """sigma_max(), error_bound() and eq5_bound() run their power iteration and probes on the first call only."""
    F, areas, rho = system
    fac = factorize_matrix(F, rho, areas=areas, eps=0.02, block_size=16, dtype=np.float64)
    power = counting(monkeypatch, woodbury, "power_sigma_max_scaled")
    probes = counting(monkeypatch, PassStatistics, "operator_error")
    sigma = fac.sigma_max()
    assert len(power) == 1                                  # one block power iteration, every channel
    assert fac.sigma_max() is sigma and len(power) == 1
    bound, eq5 = fac.error_bound(), fac.eq5_bound()
    assert fac.error_bound() is bound and fac.eq5_bound() is eq5 and fac.error_estimate().bound is bound
    assert len(power) == 1 and len(probes) == 1
    assert np.isfinite(bound).all() and np.isfinite(eq5).all()


def test_near_field_figures_are_computed_once(system, monkeypatch, tmp_path):
    fac = near_split(system, quantize=True, dtype=np.float32)
    power = counting(monkeypatch, NearFieldFactorization, "_power_sigma")
    spectral = counting(monkeypatch, nearfield, "spectral_bound")
    for _ in range(2):
        fac.sigma_max(), fac.error_bound(), fac.eq5_bound()
        fac.solve(np.ones((N_PATCHES, 3)))
        fac.solve(np.ones((N_PATCHES, 3)), trans="T")
    assert len(power) == len(fac.distinct_channels) == 3     # rho differs per channel: three distinct D_c
    assert len(spectral) == 1
    # loaded: sigma_max is stored (no power iteration); the 16-bit storage error is bounded on the first call
    back = load_hfr(save_hfr(fac, tmp_path / "q.hfr"))
    v_norm = counting(monkeypatch, nearfield, "power_sigma_max")
    first = back.quantization_error()
    assert back.quantization_error() is first and len(v_norm) == 1
    np.testing.assert_allclose(first, fac.quantization_error(), rtol=1e-6)
    back.error_bound(), back.sigma_max()
    assert len(power) == 3 and len(v_norm) == 1


def test_sizes_as_scipy_superlu_states_them(system, plain):
    """``shape`` is the system's, ``nbytes`` the arrays a solve reads, ``near_entries`` N's stored entries."""
    n, k = N_PATCHES, plain.rank
    assert plain.shape == (n, n) and plain.Q.shape == (n, k)
    assert plain.nbytes == (2 * n * k + 3 * k * k) * plain.dtype.itemsize
    for quantize in (False, True):
        fac = near_split(system, quantize=quantize, dtype=np.float32)
        assert fac.shape == (n, n) and fac.near_entries == fac.N.nnz > 0
        z = fac.Z.codes.nbytes + fac.Z.scale.nbytes if quantize else fac.Z.nbytes
        assert fac.nbytes == ((2 * n * fac.rank + 3 * fac.rank ** 2) * 4 + z
                              + fac.N.nnz * (8 + 4 + 2 * fac.N.indices.itemsize)   # N and its float32 copy
                              + 2 * fac.N.indptr.nbytes)
