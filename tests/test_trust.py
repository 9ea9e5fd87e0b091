"""Answers a user can trust (issue 10): guaranteed error figures, energy checks, damaged files, checkpoints.

The guarantees are checked against what we did not write: numpy's 2-norms of
the exact dense operators and dense LAPACK solves.
"""

from __future__ import annotations

import warnings

import h5py
import numpy as np
import pytest
from conftest import Interrupt, interrupt_at

import hfrad
from hfrad.errors import AccuracyWarning, FileFormatError
from hfrad.solve.bounds import power_sigma_max, power_sigma_max_scaled
from hfrad.solve.stats import probe_alpha


@pytest.fixture(scope="module")
def cornell():
    scene = hfrad.load_scene("cornell", patches=300)
    F = hfrad.form_factor_matrix(scene)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", AccuracyWarning)
        fac = hfrad.factorize_matrix(F, scene.reflectance, areas=scene.areas, eps=0.02, dtype="float64",
                              order=hfrad.scene.zorder.patch_order(scene.centroids, "zorder"))
        fac.error_estimate()
    return scene, F, fac


def _weighted(M, areas):
    a = np.sqrt(areas)
    return a[:, None] * M / a[None, :]


@pytest.mark.parametrize("probes", [1, 2])
def test_probe_alpha_fails_as_often_as_stated(probes):
    """Halko et al. (2011) Lemma 4.1 with ``probe_alpha``, drawn 20,000 times on a rank-one M.

    ``||M|| <= alpha sqrt(2/pi) max_i ||M omega_i||`` must fail in at most ``failure`` of
    the draws; on a rank-one M the lemma is nearly attained (0.0998 and 0.0950 expected
    here), so an alpha too small fails the first assertion and one too large the second.
    """
    failure, trials, n = 0.1, 20_000, 30
    rng = np.random.default_rng(7)
    a, b = rng.standard_normal(n), rng.standard_normal(n)
    M = np.outer(a / np.linalg.norm(a), b / np.linalg.norm(b))         # ||M||_2 = 1
    omega = rng.standard_normal((trials, probes, n))
    figure = probe_alpha(probes, failure) * np.sqrt(2 / np.pi) * np.linalg.norm(omega @ M.T, axis=2).max(axis=1)
    rate = np.mean(figure < np.linalg.norm(M, 2))
    assert rate <= failure + 3 * np.sqrt(failure * (1 - failure) / trials), rate
    assert rate >= 0.85 * failure, rate


def test_figures_bound_the_exact_operator_norms(cornell):
    scene, F, fac = cornell
    est = fac.error_estimate()
    G_user = (fac.Q @ fac.V.T)[np.ix_(fac.inv_perm, fac.inv_perm)]           # Q V^T in the user's order
    for c in range(3):
        RcF = scene.reflectance[:, [c]] * F
        exact_contraction = np.linalg.norm(_weighted(RcF, scene.areas), 2)
        assert exact_contraction <= est.contraction[c] <= 1.5 * exact_contraction    # observed 1.20-1.35x
        D = (fac.reflectance[:, c] / fac.rho_max)[:, None]
        M = _weighted(RcF - D * G_user, scene.areas)
        exact_error = np.linalg.norm(M, 2)
        assert exact_error <= est.operator_error[c], (exact_error, est.operator_error[c])
        # the probes measure about the Frobenius norm, times their safety factor: loose but bounded
        assert est.operator_error[c] <= 3 * np.linalg.norm(M), (est.operator_error[c], np.linalg.norm(M))
        # sigma_max of eq. 5, by power iteration on the factors, against LAPACK
        Qc = fac.Q * (fac._D[:, c:c + 1])
        assert power_sigma_max(Qc, fac.V) == pytest.approx(np.linalg.norm(Qc @ fac.V.T, 2), rel=1e-6)
        # the block iteration of every channel at once (what fac.sigma_max() runs), against LAPACK too
        assert fac.sigma_max()[c] == pytest.approx(np.linalg.norm(Qc @ fac.V.T, 2), rel=1e-6)
    assert power_sigma_max_scaled(fac.Q, fac.V, np.zeros((fac.n_patches, 2))).tolist() == [0.0, 0.0]


def test_bounds_hold_against_the_dense_solve(cornell):
    from hfrad.solve.denselu import solve_direct

    scene, F, fac = cornell
    rng = np.random.default_rng(0)
    w = np.sqrt(scene.areas)[:, None]
    for E in (scene.emission, rng.random((scene.n_patches, 3)) * (rng.random((scene.n_patches, 1)) < 0.05)):
        exact = solve_direct(F, scene.reflectance, E)
        B = fac.solve(E)
        err = np.linalg.norm(w * (B - exact), axis=0) / np.linalg.norm(w * exact, axis=0)
        assert (err <= fac.error_bound()).all()
        figure = fac.residual(E, B, form_factors=F)
        assert (err <= figure.bound).all(), (err, figure.bound)
        assert (figure.bound <= 10 * err).all(), (err, figure.bound)     # observed 5x: tight


def test_a_bit_flipped_hfr_is_refused(tmp_path):
    scene = hfrad.load_scene("cornell", patches=150)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", AccuracyWarning)
        fac = hfrad.factorize(scene, eps=0.05)
        path = fac.save(tmp_path / "c.hfr")
        back = hfrad.load(path)                                   # intact: loads, same figures
        np.testing.assert_array_equal(back.error_estimate().operator_error, fac.error_estimate().operator_error)
    with h5py.File(path, "r") as f:
        chunk = f["factors/Q"].id.get_chunk_info(0)
    raw = bytearray(path.read_bytes())
    middle = chunk.byte_offset + chunk.size // 2
    raw[middle:middle + 4] = bytes(b ^ 0x5A for b in raw[middle:middle + 4])
    damaged = tmp_path / "damaged.hfr"
    damaged.write_bytes(bytes(raw))
    with pytest.raises(FileFormatError, match=r"damaged\.hfr: dataset /factors/Q is damaged"):
        hfrad.load(damaged)
    # a changed header number is caught by the attributes' digest
    edited = tmp_path / "edited.hfr"
    edited.write_bytes(path.read_bytes())
    with h5py.File(edited, "r+") as f:
        f.attrs["achieved_error"] = 0.0
    with pytest.raises(FileFormatError, match="header attributes are damaged"):
        hfrad.load(edited)


def test_duplicate_faces_are_reported_as_an_energy_error():
    """Two copies of the floor: every patch that sees the floor sends out more light than it has."""
    base = hfrad.load_scene("cornell")
    floor = np.flatnonzero(base.group == base.groups.index("floor"))
    doubled = base.replace(faces=np.vstack([base.faces, base.faces[floor]]),
                           material=np.concatenate([base.material, base.material[floor]]),
                           group=np.concatenate([base.group, base.group[floor]]),
                           reflectance=np.vstack([base.reflectance, base.reflectance[floor]]),
                           emission=np.vstack([base.emission, base.emission[floor]]),
                           parent=np.concatenate([base.parent, base.parent[floor]]), occluder_vertices=None,
                           occluder_faces=None)
    scene = hfrad.subdivide(doubled, patches=200)
    with pytest.warns(AccuracyWarning, match=r"send out more light than they receive.*white.*worst: patch \d+"):
        hfrad.factorize(scene, eps=0.05)


def test_checkpoint_of_another_kernel_is_not_resumed(tmp_path, monkeypatch):
    import hfrad.formfactors.kernel as kernel

    scene = hfrad.load_scene("cornell", patches=300)
    ckpt = tmp_path / "run.partial"
    with pytest.raises(Interrupt):
        hfrad.factorize(scene, eps=0.05, status=interrupt_at(3), checkpoint=hfrad.Checkpoint(ckpt, interval=0.0),
                        options=hfrad.PrecomputeOptions(block_size=32))
    assert ckpt.exists()
    monkeypatch.setattr(kernel, "KERNEL_VERSION", "a newer kernel")
    with pytest.raises(ValueError, match="another scene or other parameters"):
        hfrad.factorize(scene, eps=0.05, checkpoint=ckpt, options=hfrad.PrecomputeOptions(block_size=32))


def test_resumed_statistics_equal_a_straight_run(tmp_path):
    scene = hfrad.load_scene("cornell", patches=300)
    ckpt = tmp_path / "run.partial"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", AccuracyWarning)
        straight = hfrad.factorize(scene, eps=0.05, dtype="float64",
                                   options=hfrad.PrecomputeOptions(block_size=32))
        with pytest.raises(Interrupt):
            hfrad.factorize(scene, eps=0.05, dtype="float64", status=interrupt_at(5),
                            checkpoint=hfrad.Checkpoint(ckpt, interval=0.0),
                            options=hfrad.PrecomputeOptions(block_size=32))
        resumed = hfrad.factorize(scene, eps=0.05, dtype="float64", checkpoint=ckpt,
                                  options=hfrad.PrecomputeOptions(block_size=32))
    np.testing.assert_allclose(resumed.stats.row_sums, straight.stats.row_sums, rtol=1e-12)
    np.testing.assert_allclose(resumed.stats.sketch, straight.stats.sketch, rtol=1e-10, atol=1e-14)


def test_a_nan_in_a_column_block_is_refused_before_lapack():
    from conftest import closed_system
    from hfrad.pipeline import factorize_blocks

    F, _, rho = closed_system(64)
    F[10, 40] = np.nan
    blocks = ((s, s + 16, F[:, s:s + 16]) for s in range(0, 64, 16))
    with pytest.raises(hfrad.InputError, match="column block 32:48 has a NaN.*row 10, column 40"):
        factorize_blocks(blocks, 64, rho, np.arange(64), eps=0.05, n_blocks=4)
