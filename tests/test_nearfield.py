"""The near-field / far-field split (METHOD.md s. 8) against the exact dense solve and the plain path."""

from __future__ import annotations

import numpy as np
import pytest

from hfrad import Checkpoint, LocalBackend, PrecomputeOptions
from hfrad.lowrank.nearsplit import NearFieldSplit, near_radius
from hfrad.formfactors import form_factor_matrix
from hfrad.solve.hfr import load_hfr, read_hfr_metadata, save_hfr
from hfrad.pipeline import factorize
from hfrad.precompute.options import near_entries, near_field_pays_from
from hfrad.scene.load import load_scene
from hfrad.solve.nearfield import NearFieldFactorization


@pytest.fixture(scope="module")
def dense():
    """A ~2,000-patch Cornell box and its dense F."""
    scene = load_scene("cornell", patches=2000)
    return scene, form_factor_matrix(scene)


@pytest.fixture(scope="module")
def cornell(dense):
    """The box, ``I - R_c F`` per channel and the exact radiosity (LAPACK, per channel)."""
    scene, F = dense
    n = scene.n_patches
    systems = [np.eye(n) - scene.reflectance[:, c, None] * F for c in range(3)]
    exact = np.stack([np.linalg.solve(A, scene.emission[:, c]) for c, A in enumerate(systems)], axis=1)
    return scene, systems, exact


@pytest.fixture(scope="module")
def pair(cornell):
    scene = cornell[0]
    kw = dict(eps=0.03, dtype="float64", backend=LocalBackend(processes=1),
              options=PrecomputeOptions(block_size=128, one_ray_tol=0))
    return factorize(scene, near_field=None, **kw), factorize(scene, near_field=96, **kw)


def _err(B, exact):
    return np.linalg.norm(B - exact, axis=0) / np.linalg.norm(exact, axis=0)


def test_same_radiosity_as_plain_path_within_reported_error(cornell, pair):
    scene, _, exact = cornell
    plain, near = pair
    assert plain.solver == "woodbury" and isinstance(near, NearFieldFactorization)
    # the radius counts facing neighbours: about that many nonzeros per row move out
    print(f"\nnonzeros per row of N: {near.N.nnz / scene.n_patches:.1f} (asked for 96 facing neighbours)")
    assert 0.9 * 96 <= near.N.nnz / scene.n_patches <= 1.1 * 96  # observed 99.7
    assert near.relative_error <= 0.03  # still relative to the full ||G||_F
    B_plain, B_near = plain.solve(scene.emission), near.solve(scene.emission)
    e_plain, e_near = _err(B_plain, exact), _err(B_near, exact)
    print(f"\nrank plain {plain.rank} near {near.rank} (nnz/row {near.N.nnz / scene.n_patches:.0f}); "
          f"error plain {e_plain} near {e_near}; bound near {near.error_bound()}")
    assert (e_near <= near.error_bound()).all()
    assert (e_near <= e_plain).all()  # the split never costs accuracy at equal eps
    assert near.rank < plain.rank
    # the two paths agree within the error each reports
    assert (_err(B_near, B_plain) <= plain.error_bound() + near.error_bound()).all()


def test_transpose_and_batched_solves(cornell, pair):
    scene, systems, _ = cornell
    near = pair[1]
    rng = np.random.default_rng(0)
    g = rng.standard_normal((scene.n_patches, 3))
    x = near.solve(g, trans="T")
    exact = np.stack([np.linalg.solve(A.T, g[:, c]) for c, A in enumerate(systems)], axis=1)
    assert (_err(x, exact) < 0.01).all()   # observed 2.3-2.5e-3 (eps 0.03)
    E = np.abs(rng.standard_normal((scene.n_patches, 3, 2)))
    Bm = near.solve(E)
    np.testing.assert_allclose(Bm[:, :, 1], near.solve(E[:, :, 1]), rtol=1e-14, atol=1e-14)   # observed 7e-16


def test_with_reflectance_and_hfr_round_trip(cornell, pair, tmp_path):
    scene, _, _ = cornell
    near = pair[1]
    darker = near.with_reflectance(0.5 * scene.reflectance)
    assert isinstance(darker, NearFieldFactorization)
    assert darker.solve(scene.emission).sum() < near.solve(scene.emission).sum()
    path = save_hfr(near, tmp_path / "near.hfr")
    assert read_hfr_metadata(path)["solver"] == near.solver
    back = load_hfr(path)
    assert isinstance(back, NearFieldFactorization) and back.N.nnz == near.N.nnz
    np.testing.assert_allclose(back.solve(scene.emission), near.solve(scene.emission), rtol=1e-14)   # observed 0
    # a stored Z of the wrong shape is refused by name, not used
    import h5py

    from hfrad.errors import FileFormatError
    with h5py.File(path, "r+") as f:
        Z = f["factors/near_solution"][...]
        del f["factors/near_solution"]
        f["factors"].create_dataset("near_solution", data=Z[:, :-1])
    with pytest.raises(FileFormatError, match="near_solution"):
        load_hfr(path)


def test_split_moves_exactly_the_near_pairs():
    rng = np.random.default_rng(1)
    c = rng.random((300, 3))
    r = near_radius(c, 20)
    G = rng.random((300, 300)) + 0.1
    split = NearFieldSplit(c, r)
    rest = np.concatenate([split.split(G[:, s:s + 64].copy(), s) for s in range(0, 300, 64)], axis=1)
    N = split.matrix().toarray()
    near = np.linalg.norm(c[:, None] - c[None], axis=2) <= r
    np.testing.assert_array_equal(N != 0, near)
    np.testing.assert_array_equal(N + rest, G)   # entries moved, not changed (observed exact)
    assert 15 <= near.sum(axis=1).mean() <= 25   # 20 asked for, observed 20.2


def test_checkpoint_resume_keeps_the_near_field(tmp_path):
    """An interrupted run resumes with its near field, here in worker processes (same blocks)."""
    scene = load_scene("cornell", patches=600)
    kw = dict(eps=0.03, dtype="float64", near_field=48, backend=LocalBackend(processes=1),
              options=PrecomputeOptions(block_size=64))
    full = factorize(scene, **kw)
    ckpt = tmp_path / "run.partial"

    class Interrupt(Exception):
        pass

    def stop(info):
        if info["blocks"] == 5:
            raise Interrupt

    with pytest.raises(Interrupt):
        factorize(scene, status=stop, checkpoint=Checkpoint(ckpt, interval=0.0), **kw)
    resumed = factorize(scene, checkpoint=ckpt, **kw | {"backend": LocalBackend(processes=2)})  # resume in worker processes
    assert resumed.N.nnz == full.N.nnz and resumed.rank == full.rank
    # observed 1.6e-14 (worker processes: BLAS summation order)
    np.testing.assert_allclose(resumed.solve(scene.emission), full.solve(scene.emission), rtol=2e-13)


def test_near_field_option():
    assert near_entries(None, 10 ** 6) == 0 and near_entries(32, 10) == 32
    assert near_entries("auto", 100) == 0 and near_entries("auto", 10 ** 6) > 0
    with pytest.raises(ValueError, match="near_field"):
        near_entries("big", 100)


def test_near_field_auto_where_it_pays():
    """"auto" splits where the measured crossover says it pays (benchmarks/results/nearfield-pays.json).

    eps 0.02: 10K patches 1.26x faster without the split, 20K even; eps 0.05: 5K even,
    10K 1.42x faster with it; an absolute eps keeps the 2,000-patch floor.
    """
    assert near_entries("auto", 10_000, 0.02) == 0 and near_entries("auto", 20_000, 0.02) > 0
    assert near_entries("auto", 10_000, 0.05) > 0 and near_entries("auto", 4_000, 0.05) == 0
    assert near_field_pays_from(0.05) == 5060 and near_field_pays_from(0.02) == 20_000
    assert near_field_pays_from(0.5) == 2000                   # never below the floor
    assert near_field_pays_from(1e-3, relative=False) == 2000  # absolute eps: no rank to judge by
    assert near_field_pays_from(0.01) > near_field_pays_from(0.02)   # tighter eps: later
    # a clustered real mesh: from the floor (Sponza, the conference room and Sibenik at ~3,100 patches,
    # eps 0.02: rank 1,961 / 1,949 / 2,153 without the split, 748 / 236 / 423 with it)
    assert near_field_pays_from(0.02, clustered=True) == 2000
    assert near_entries("auto", 2_500, 0.02, clustered=True) > 0 and near_entries("auto", 1_999, 0.02, clustered=True) == 0
    assert near_entries("auto", 2_500, 0.02) == 0


def test_clustered_near_field_grows_with_the_patches():
    """A clustered mesh's "auto" near field: 120 a row to 4,000 patches, more beyond, 400 at most;
    a box's (not clustered) stays at 120 (Sponza, eps 0.02, 20,102 patches: rank 4,518 with 120
    a row, 1,876 with 400)."""
    sizes = [2_000, 3_129, 4_000, 5_000, 10_000, 20_102, 163_000]
    grown = [near_entries("auto", n, 0.02, clustered=True) for n in sizes]
    assert grown[:3] == [120, 120, 120]
    assert grown[2] < grown[3] < grown[4] < grown[5]
    assert grown[5:] == [400, 400]
    assert near_entries("auto", 163_000, 0.02) == 120
    assert near_entries(64, 20_102, 0.02, clustered=True) == 64        # a number is taken as it is


def test_plan_reads_whether_the_scene_is_clustered(monkeypatch):
    """plan_precompute passes the scene's clustering to the "auto" policy (floor lowered to this size)."""
    from hfrad.precompute import options as opts
    from hfrad.scene.cluster import cluster
    from hfrad.scene.load import load_scene

    clustered = cluster(load_scene("cornell", patches=1200), patches=300)
    plain = load_scene("cornell", patches=clustered.n_patches)
    assert clustered.is_clustered and not plain.is_clustered
    monkeypatch.setattr(opts, "NEAR_FIELD_MIN_PATCHES", 100)
    plan = (lambda scene: opts.plan_precompute(scene, 0.02, near_field="auto"))
    assert plan(clustered).near_entries > 0 and plan(plain).near_entries == 0


def test_panel_solver_equals_superlu():
    """Many right-hand sides through L and U in panels: SuperLU's own solve to rounding."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import splu

    from hfrad.solve.sparselu import PanelSolver

    rng = np.random.default_rng(3)
    n = 400
    N = sp.random(n, n, density=0.03, random_state=4, format="csr") * 0.05
    lu = splu((sp.identity(n) - N - N.T).tocsc(), permc_spec="MMD_AT_PLUS_A")
    X = rng.standard_normal((n, 150))                      # 2 full panels and a partial one
    exact = np.column_stack([lu.solve(X[:, j].copy()) for j in range(X.shape[1])])
    # observed 1.8e-15 of max |exact|
    np.testing.assert_allclose(PanelSolver(lu).solve(X), exact, rtol=0, atol=2e-14 * np.abs(exact).max())
    single = PanelSolver(lu, np.float32).solve(X)
    assert single.dtype == np.float32
    rel = np.abs(single - exact).max() / np.abs(exact).max()
    print(f"\nfloat32 panels: {rel:.2e} relative")
    assert rel <= 1e-5   # observed 1.9e-6


def test_grey_channels_share_one_near_solution(dense, pair):
    """Equal D_c: one Z and one K for all three channels, and still the exact radiosity."""
    scene, F = dense
    grey = np.repeat(scene.reflectance.mean(axis=1, keepdims=True), 3, axis=1)
    fac = pair[1].with_reflectance(grey)
    assert fac.distinct_channels == [0] and fac.Z.shape == (1, scene.n_patches, fac.rank)
    assert pair[1].Z.shape[0] == 3      # the box's red and green walls: three distinct channels
    assert (fac.capacitance_inv[0] == fac.capacitance_inv[2]).all()
    exact = np.linalg.solve(np.eye(scene.n_patches) - grey[:, :1] * F, scene.emission)
    err = _err(fac.solve(scene.emission), exact)
    print(f"\ngrey: error {err}")
    assert (err < 0.005).all()   # observed 0.0022, as the coloured channels (0.002-0.0024)


def test_neumann_series_equals_the_sparse_lu(cornell, pair, monkeypatch):
    """The relighting solve's Neumann series gives SuperLU's answer to its stopping tolerance,
    forward and adjoint; where the series fails the solver falls back to SuperLU."""
    import hfrad.solve.nearfield as nearfield
    from hfrad.solve.neumann import NEUMANN_TOL

    scene = cornell[0]
    near = pair[1]
    g = np.random.default_rng(5).random((scene.n_patches, 3))
    series = {t: near.solve(g, trans=t) for t in "NT"}
    sweeps = near.last_sweeps
    monkeypatch.setattr(nearfield, "neumann_solve", lambda *a, **k: (None, 0))
    for t in "NT":
        lu = near.solve(g, trans=t)
        assert near.last_sweeps == 0
        rel = np.abs(series[t] - lu).max() / np.abs(lu).max()
        print(f"\ntrans={t}: series vs SuperLU {rel:.2e} (adjoint sweeps {sweeps})")
        assert rel <= NEUMANN_TOL        # observed 1.9e-6 (N) / 2.5e-6 (T)


def test_quantized_near_solution(dense, cornell, tmp_path):
    """float32 factors store Z_c in 16 bits: the same radiosity within the stated bound, half the bytes,
    and the error figures still bound the error against the exact solve."""
    from hfrad.solve.nearfield import QUANTIZE_SHARE
    from hfrad.solve.quantized import QuantizedRows

    scene, _, exact = cornell
    F = dense[1]
    fac = factorize(scene, near_field=96, eps=0.03, backend=LocalBackend(processes=1),
                    options=PrecomputeOptions(block_size=128, one_ray_tol=0))
    assert fac.dtype == np.float32 and isinstance(fac.Z, QuantizedRows)
    assert fac.near_solution_storage == "int16 rows" and "int16 rows" in repr(fac)
    share = fac.quantization_error() / fac.achieved_error
    plain = NearFieldFactorization(fac.perm, fac.Q, fac.V, fac.N, fac.rho_max, fac.reflectance, fac.lowrank,
                                   quantize=False, stats=fac.stats, scene=scene)
    assert plain.Z.dtype == np.float32 and not plain.quantization_error().any()
    assert fac.Z.nbytes < 0.51 * plain.Z.nbytes
    B, B_plain = fac.solve(scene.emission), plain.solve(scene.emission)
    moved, err = _err(B, B_plain), _err(B, exact)
    print(f"\nquantization: operator bound {share} of the achieved error, radiosity moved {moved}, "
          f"error {err} (float Z {_err(B_plain, exact)}), bound {fac.error_bound()} (float Z {plain.error_bound()})")
    assert (share <= QUANTIZE_SHARE).all()            # observed 2.4-2.8e-3
    assert (moved <= 2e-5).all()                      # observed 3.8-4.5e-6
    # the a-posteriori figure against the exact F bounds the error, and is as tight as with float Z
    res, res_plain = fac.residual(scene.emission, B, form_factors=F), plain.residual(scene.emission, B_plain,
                                                                                   form_factors=F)
    print(f"residual bound {res.bound} (float Z {res_plain.bound})")
    # observed: the error 0.17-0.18 of the bound; the bounds' ratio 0.99996-1.00005
    assert (err <= res.bound).all() and (res.bound <= 1.0005 * res_plain.bound).all()
    np.testing.assert_allclose(fac.error_bound(), plain.error_bound(), rtol=5e-4)   # observed 1.4e-4
    # forced either way
    assert isinstance(plain.with_reflectance(scene.reflectance).Z, np.ndarray)
    # the file keeps the codes: the same solve after loading, and the figures recomputed from the scales
    back = load_hfr(save_hfr(fac, tmp_path / "q.hfr"))
    assert isinstance(back.Z, QuantizedRows)
    np.testing.assert_array_equal(back.solve(scene.emission), B)
    # observed 4e-16; the margin: a power iteration (to 1e-7) bounds ||V||, and may stop a step apart
    np.testing.assert_allclose(back.quantization_error(), fac.quantization_error(), rtol=1e-6)


def test_float32_set_up_capacitance_and_radiosity_against_the_dense_solve():
    """float32 factors, 16-bit Z_c: ``V^T Z_c`` by float32 slabs equals the float64 product to float32
    rounding (observed 1e-7 relative), and the radiosity is within its error figures of LAPACK's."""
    from hfrad.solve.quantized import QuantizedRows

    scene = load_scene("cornell", patches=500)
    F = form_factor_matrix(scene)
    fac = factorize(scene, eps=0.03, dtype="float32", near_field=32, backend=LocalBackend(processes=1),
                    options=PrecomputeOptions(block_size=64, one_ray_tol=0))
    assert isinstance(fac, NearFieldFactorization) and fac.rank > 0
    for z in range(len(fac.distinct_channels)):
        Zz = fac.Z[z]
        Zd = Zz.decode() if isinstance(Zz, QuantizedRows) else Zz
        K64 = fac.V.T.astype(np.float64) @ Zd.astype(np.float64)
        assert np.abs(fac._vt_times(Zz, slab=128) - K64).max() <= 1e-6 * np.abs(K64).max()
    exact = np.stack([np.linalg.solve(np.eye(scene.n_patches) - scene.reflectance[:, c, None] * F,
                                      scene.emission[:, c]) for c in range(3)], axis=1)
    w = np.sqrt(scene.areas)[:, None]
    err = np.linalg.norm(w * (fac.solve(scene.emission) - exact), axis=0) / np.linalg.norm(w * exact, axis=0)
    assert (err < 0.01).all()                                  # observed 0.21-0.26% at eps 0.03
    assert (err <= fac.error_estimate().bound).all()


def test_sparse_lu_within_its_memory_estimate(pair):
    """The memory check's LU entries (n c^1.5, hfrad.memory.near_lu_entries) hold the LU SuperLU makes
    of a real N, and are not a figure that cannot fail: measured 0.44-0.50 of it on the Cornell box
    (1,508 and 2,974 patches, c = 120), 0.53-0.84 at 9,986-60,568 patches (benchmarks/README.md)."""
    from hfrad.memory import near_lu_entries
    from hfrad.solve.nearfield import factor_near

    split = pair[1]
    lu = factor_near(split.N, split._D[:, 0])
    ratio = (lu.L.nnz + lu.U.nnz) / near_lu_entries(split.n_patches, split.params["near_field"])
    assert 0.3 <= ratio <= 1.0, ratio


def test_near_field_set_up_refused_with_the_number(monkeypatch):
    """The set-up's sparse LUs are estimated before the pass and refused with the number (a 60,568-patch
    clustered run was killed at 24.3 GB by the OOM killer before they were counted); without the near
    field the same memory is enough."""
    import hfrad.memory as memory
    from hfrad.errors import MemoryLimitError

    scene = load_scene("cornell", patches=300)
    need = memory.near_setup_bytes(scene.n_patches, 120)
    monkeypatch.setattr(memory, "available_bytes", lambda: int(need / 0.8) - 1)
    with pytest.raises(MemoryLimitError, match=r"near field's set-up for 3\d\d patches \(120 entries a row\) "
                                               r"needs about [0-9.]+ MB"):
        factorize(scene, 0.05, near_field=120, backend=LocalBackend(processes=1))
    assert factorize(scene, 0.05, near_field=None, backend=LocalBackend(processes=1)).rank > 0


def test_set_up_by_neumann_sweeps_above_the_factored_entries(cornell, pair, monkeypatch):
    """Above NEAR_LU_MOST_ENTRIES entries a row (clustered meshes: LUs of 10-17 times N's entries) the set-up
    takes A_c^{-1} D_c Q by Neumann sweeps, no LU: the same Z to the sweeps' tolerance, the same
    radiosity to float rounding, and no LU in the memory estimate."""
    import hfrad.memory as memory
    from hfrad.solve.nearfield import SETUP_TOL

    scene, _, exact = cornell
    lu = pair[1]
    assert lu.near_setup == "lu" and lu.lowrank.info["near_setup"] == "lu"
    monkeypatch.setattr(memory, "NEAR_LU_MOST_ENTRIES", 64)          # below the pair's 96
    kw = dict(eps=0.03, dtype="float64", backend=LocalBackend(processes=1),
              options=PrecomputeOptions(block_size=128, one_ray_tol=0))
    swept = factorize(scene, near_field=96, **kw)
    assert swept.near_setup == "neumann" and swept.lowrank.info["near_setup"] == "neumann"
    assert swept.rank == lu.rank
    Z, Z_lu = np.asarray(swept.Z, np.float64), np.asarray(lu.Z, np.float64)
    # the sweeps stop at SETUP_TOL (relative residual): Z within SETUP_TOL / (1 - rho) of the LU's
    # (observed 4.1e-8 of its largest entry, 0.41 SETUP_TOL)
    assert np.abs(Z - Z_lu).max() <= 2 * SETUP_TOL * np.abs(Z_lu).max()
    B, B_lu = swept.solve(scene.emission), lu.solve(scene.emission)
    assert np.abs(B - B_lu).max() <= 5e-9 * np.abs(B_lu).max()         # observed 5.4e-10
    n = scene.n_patches
    assert memory.near_field_bytes(n, 96) == memory.NEAR_N_BYTES * n * 96      # no LU counted
