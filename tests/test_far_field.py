"""The sampled far field (issue 43): column blocks of F from a small share of the pairs.

Checked against the exact form factors of the same engine: the certificate's estimate of
``||G - G~||`` within 2x of the measured error on three scenes and its upper figure above it, rows with a shadow edge
across a column group computed exactly, and ``hfrad.factorize(far_field="sampled")`` end to
end against the exact pass (radiosity, the operator figure, the .hfr round trip). The
admissibility is made tighter than the default (``eta``, small blocks) so that scenes of a
few thousand patches have far rows at all.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import Interrupt, interrupt_at

import hfrad
from hfrad.errors import InputError
from hfrad.formfactors.budget import ray_budget
from hfrad.formfactors.engine import FormFactorEngine
from hfrad.formfactors.farfield import FarFieldOptions, SampledFarField
from hfrad.scene.load import load_scene
from hfrad.scene.zorder import zorder_permutation
from hfrad.solve.hfr import load_hfr, save_hfr

BLOCK = 64
EPS = 0.05
FAR = FarFieldOptions(eta=0.5, rows=32, certify_rows=128)
CORNELL = 1200


def _sampled_against_exact(scene, options=FAR):
    """Every column block sampled and exact: (measured ||G - G~||, certificate, producer, partial rows exact)."""
    n = scene.n_patches
    perm = zorder_permutation(scene.centroids)
    rho = scene.reflectance.max(axis=1)[perm]
    w = np.asarray(scene.areas)[perm]
    engine = FormFactorEngine(scene, ray_budget=ray_budget(scene, EPS / 4))
    producer = SampledFarField(scene, engine, perm, BLOCK, rho, EPS, weights=w, options=options)
    reference = FormFactorEngine(scene, ray_budget=ray_budget(scene, EPS / 4))
    kernel = FormFactorEngine(scene, samples=0)
    err2, partial_exact = 0.0, []
    for j in range(-(-n // BLOCK)):
        pieces, _ = producer.block(j)
        block = pieces.to_dense()
        cols = perm[j * BLOCK:(j + 1) * BLOCK]
        exact = reference.block(perm, cols)
        d = (exact - block) * rho[:, None] * np.sqrt(w[:, None] / w[None, j * BLOCK:(j + 1) * BLOCK])
        err2 += float((d * d).sum())
        K = kernel.block(perm, cols)
        V = np.divide(exact, K, out=np.ones_like(exact), where=K > 1e-9)
        partial = ((V > 0.05) & (V < 0.95)).any(axis=1)      # rows with a shadow edge across the group
        if partial.any():
            partial_exact.append(float((np.abs(block[partial] - exact[partial]).max(axis=1) < 1e-12).mean()))
    for e in (reference, kernel):
        e.close()
    producer.close()
    return np.sqrt(err2), producer.certificate.frobenius(), producer, partial_exact


@pytest.fixture(scope="module")
def cornell_run():
    return _sampled_against_exact(load_scene("cornell", patches=CORNELL))


@pytest.mark.parametrize("name,patches", [("furnace", 1000), ("perpendicular", 800)])
def test_certificate_within_2x_of_the_measured_error(name, patches):
    true, (estimate, upper), producer, _ = _sampled_against_exact(load_scene(name, patches=patches))
    stats = producer.stats.as_dict(producer.n)
    assert stats["skeleton_mean"] > 0 and stats["pairs_share"] < 0.95     # the far field was sampled
    # observed: furnace 0.98, perpendicular 1.07
    assert 0.5 * true <= estimate <= 2.0 * true, (true, estimate)
    # the upper figure (stated to fail in 2.5% of draws) above the error, not far: observed 1.12, 1.35
    assert true <= upper <= 2.0 * true, (true, upper)


def test_certificate_within_2x_on_the_cornell_box(cornell_run):
    true, (estimate, upper), producer, _ = cornell_run
    assert 0.5 * true <= estimate <= 2.0 * true, (true, estimate)   # observed 1.01
    assert true <= upper <= 2.0 * true, (true, upper)               # observed 1.17


def test_shadow_edges_are_computed_exactly(cornell_run):
    """Rows whose view of a column group is partly blocked (a shadow edge of the Cornell box's
    blocks across the group) are found by the cluster tests and probes and computed exactly."""
    _, _, producer, partial_exact = cornell_run
    stats = producer.stats.as_dict(producer.n)
    assert stats["mixed_pairs"] > 0 and stats["probe_rays"] > 0
    # observed: 80% of those rows exact on average over the blocks (the rest hold little of F)
    assert np.mean(partial_exact) >= 0.7, partial_exact


@pytest.mark.slow
def test_a_group_that_does_not_compress_is_halved():
    """A column group whose far rows need more skeleton columns than allowed is halved and the
    halves tried again (not computed pair by pair over every row at once); the certificate
    still measures what the blocks hold."""
    options = FarFieldOptions(eta=0.5, rows=32, certify_rows=128, max_skeleton_share=0.05)
    true, (estimate, _), producer, _ = _sampled_against_exact(load_scene("cornell", patches=CORNELL), options)
    stats = producer.stats.as_dict(producer.n)
    assert stats["split_groups"] > 0 and stats["skeleton_mean"] > 0      # observed 24 halvings
    assert 0.5 * true <= estimate <= 2.0 * true, (true, estimate)      # observed 0.96


@pytest.mark.slow
def test_sampled_far_field_error_within_its_share(cornell_run):
    """Relative to ||G||, the far field's error stays near its share of eps (0.2 * 0.05 = 1%)."""
    true, *_ = cornell_run
    scene = load_scene("cornell", patches=CORNELL)
    G = hfrad.form_factor_matrix(scene) * scene.reflectance.max(axis=1)[:, None]
    w = np.asarray(scene.areas)
    norm = np.sqrt(((G ** 2) * w[:, None] / w[None, :]).sum())
    assert true / norm <= 1.5 * FAR.share * EPS, true / norm


@pytest.fixture(scope="module")
def factorizations():
    scene = load_scene("cornell", patches=CORNELL)
    options = hfrad.PrecomputeOptions(block_size=BLOCK, far=FAR)
    exact = hfrad.factorize(scene, EPS, far_field="exact", near_field=None, options=options)
    sampled = hfrad.factorize(scene, EPS, far_field="sampled", near_field=None, options=options)
    return scene, exact, sampled


def test_factorize_sampled_agrees_with_the_exact_pass(factorizations):
    scene, exact, sampled = factorizations
    far = sampled.lowrank.info["far_field"]
    # the far part was decomposed (skeleton columns from the kernel)
    assert far["skeleton_mean"] > 0 and far["kernel_pairs"] > 0
    # and handed on in pieces (dense rows + W X): HF never formed those blocks (issue 43, item 3)
    assert far["piece_blocks"] > 0 and far["dense_row_share"] < 0.9
    assert sampled.params["far_field"] == "sampled"
    assert exact.params["far_field"] == "exact" and "far_field" not in exact.lowrank.info
    E = np.asarray(scene.emission, float)
    Be, Bs = exact.solve(E), sampled.solve(E)
    w = np.asarray(scene.areas)[:, None]
    diff = np.sqrt((w * (Bs - Be) ** 2).sum(axis=0) / (w * (Be - E) ** 2).sum(axis=0))
    # the exact pass's own error here, from its per-solve figure: the two agree within it
    _, figure = exact.solve(E, return_error=True)
    assert (diff <= np.ravel(figure.bound)).all(), (diff, figure.bound)


@pytest.mark.slow
def test_operator_figure_covers_the_sampled_error(factorizations):
    scene, exact, sampled = factorizations
    # the sampled factorization's operator figure includes the far field's certified error
    far = sampled.lowrank.info["far_field"]
    figure = sampled.error_estimate().operator_error
    assert (figure >= far["error_upper"]).all()
    # ... and bounds the measured ||R_c F - Q_c V^T|| (area norm, 2-norm <= Frobenius)
    F = hfrad.form_factor_matrix(scene)
    perm = sampled.perm
    G = (F * scene.reflectance.max(axis=1)[:, None])[np.ix_(perm, perm)]
    approx = sampled.lowrank.Q.astype(np.float64) @ sampled.lowrank.V.astype(np.float64).T
    w = np.asarray(scene.areas)[perm]
    M = np.sqrt(w)[:, None] * (G - approx) / np.sqrt(w)[None, :]
    assert np.linalg.norm(M, 2) <= figure.max()


def test_hfr_round_trip_keeps_the_certificate(factorizations, tmp_path):
    _, _, sampled = factorizations
    path = tmp_path / "s.hfr"
    save_hfr(sampled, path)
    back = load_hfr(path)
    np.testing.assert_array_equal(back.error_estimate().operator_error, sampled.error_estimate().operator_error)
    assert back.params["far_field"] == "sampled"


def test_dask_leaves_run_the_same_sampled_far_field(factorizations, tmp_path):
    """On Dask the leaves take their blocks from the same producer: the same factorization, counters,
    certificate and per-solve figure as this process's run (issue 43, item 5: one precompute, two backends)."""
    from hfrad.distributed import connect

    scene, _, local = factorizations
    options = hfrad.PrecomputeOptions(block_size=BLOCK, far=FAR)
    parts = hfrad.Checkpoint(tmp_path / "parts", keep=True)
    with connect(workers=2, processes=False) as cluster:
        run = lambda: hfrad.factorize(scene, EPS, far_field="sampled", near_field=None, options=options,  # noqa: E731
                                      backend=hfrad.DaskBackend(scheduler=cluster), checkpoint=parts)
        dist = run()
        again = run()        # from the saved parts: the tallies travel with them
    assert again.lowrank.info["tasks_resumed"] > 0
    assert again.lowrank.info["far_field"] == dist.lowrank.info["far_field"]
    assert dist.params["far_field"] == "sampled" and dist.params["backend"] == "dask"
    assert dist.rank == local.rank
    far, far_local = dist.lowrank.info["far_field"], local.lowrank.info["far_field"]
    counters = ("pairs", "traced_pairs", "kernel_pairs", "probe_rays", "blocks", "groups", "exact_groups",
                "piece_blocks", "skeleton_mean", "skeleton_max", "certify_pairs")
    assert {k: far[k] for k in counters} == {k: far_local[k] for k in counters}
    assert far["error_upper"] == pytest.approx(far_local["error_upper"], rel=1e-12)
    E = np.asarray(scene.emission, float)
    (B, err), (B_local, err_local) = dist.solve(E, return_error=True), local.solve(E, return_error=True)
    # the same blocks and truncations; the merges' BLAS rounding differs (float32 factors): observed 8e-8
    diff = np.linalg.norm(B - B_local, axis=0) / np.linalg.norm(B_local, axis=0)
    assert (diff <= 1e-6).all(), diff
    assert err.kind == err_local.kind and err.rows == err_local.rows
    # observed 4e-6 relative
    assert np.allclose(err.bound, err_local.bound, rtol=5e-5), (err.bound, err_local.bound)


def test_far_field_options_are_checked():
    scene = load_scene("cornell", patches=200)
    with pytest.raises(InputError, match="far_field must be one of"):
        hfrad.factorize(scene, 0.05, far_field="fast")
    with pytest.raises(InputError, match="relative eps"):
        hfrad.factorize(scene, 0.05, relative=False, far_field="sampled")
    with pytest.raises(InputError, match="eta"):
        FarFieldOptions(eta=0.0)
    with pytest.raises(InputError, match="options.far"):
        hfrad.factorize(scene, 0.05, options=hfrad.PrecomputeOptions(far={"eta": 1}))
    # "auto" below AUTO_HIERARCHICAL_FROM patches is the exact pass
    fac = hfrad.factorize(scene, 0.05)
    assert fac.params["far_field"] == "exact"


def test_auto_chooses_the_measured_faster_far_field(monkeypatch):
    """"auto": the H-matrix in this process from AUTO_HIERARCHICAL_FROM patches at a relative eps of at
    least AUTO_HIERARCHICAL_EPS (where it was measured faster), the exact pass everywhere else."""
    import warnings

    from hfrad.errors import AccuracyWarning
    from hfrad.precompute import options as opts

    big, eps = opts.AUTO_HIERARCHICAL_FROM, opts.AUTO_HIERARCHICAL_EPS
    assert opts.far_field_mode("auto", big, True, eps=eps) == "hierarchical"
    assert opts.far_field_mode("auto", big - 1, True, eps=eps) == "exact"
    assert opts.far_field_mode("auto", big, True, eps=0.02) == "exact"        # measured slower at 39,482
    assert opts.far_field_mode("auto", big, False, eps=eps) == "exact"        # an absolute eps
    assert opts.far_field_mode("auto", big, True, eps=eps, local=False) == "exact"   # Dask
    assert opts.far_field_mode("auto", big, True, eps=eps, clustered=True) == "exact"  # Šibenik: not faster
    assert opts.far_field_mode("exact", big, True, eps=eps) == "exact"        # a named mode is kept
    monkeypatch.setattr(opts, "AUTO_HIERARCHICAL_FROM", 200)
    scene = load_scene("cornell", patches=300)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", AccuracyWarning)
        assert hfrad.factorize(scene, 0.05).params["far_field"] == "hierarchical"
        custom = hfrad.factorize(scene, 0.05, order=np.arange(scene.n_patches)[::-1].copy())
    assert custom.params["far_field"] == "exact" and custom.params["order"] == "custom"


def test_sampled_far_field_resumes_from_a_checkpoint(tmp_path):
    """An interrupted sampled run resumes after the saved blocks with the same result and certificate."""
    from hfrad import Checkpoint

    scene = load_scene("cornell", patches=600)
    options = hfrad.PrecomputeOptions(block_size=32, far=FAR)
    kw = dict(eps=EPS, dtype="float64", far_field="sampled", near_field=None, options=options)
    full = hfrad.factorize(scene, **kw)
    ckpt = tmp_path / "run.partial"
    with pytest.raises(Interrupt):
        hfrad.factorize(scene, status=interrupt_at(5), checkpoint=Checkpoint(ckpt, interval=0.0), **kw)
    resumed = hfrad.factorize(scene, checkpoint=ckpt, **kw)
    assert resumed.rank == full.rank
    np.testing.assert_allclose(resumed.solve(scene.emission), full.solve(scene.emission), rtol=1e-10)
    assert resumed.lowrank.info["far_field"]["error_upper"] == pytest.approx(
        full.lowrank.info["far_field"]["error_upper"], rel=1e-12)
