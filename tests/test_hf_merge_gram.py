"""HF merges from the core's Gram matrix: same truncation as gesdd to within the rank margin,
the reported discard is the measured ||children - merged||_F^2, and gesdd where the budget is tiny."""

import dataclasses

import numpy as np
import pytest

from hfrad.lowrank import hf


def decaying(n, decay, seed=0, dtype=np.float32):
    rng = np.random.default_rng(seed)
    U, _ = np.linalg.qr(rng.standard_normal((n, n)))
    W, _ = np.linalg.qr(rng.standard_normal((n, n)))
    s = np.exp(-np.arange(n) / decay)
    return ((U * s) @ W.T).astype(dtype)


def dense(node):
    return (node.U.astype(np.float64) * node.s) @ node.V.T.astype(np.float64)


@pytest.fixture(scope="module")
def children():
    """Two float32 leaves of ranks ~230 (a core of ~460 columns: the Gram path's size)."""
    A = decaying(1200, 60.0)
    budget = hf.ErrorBudget(0.02, True, 2, 0.5)
    return A, hf.compress_leaf(A[:, :600], budget, 0), hf.compress_leaf(A[:, 600:], budget, 1), budget


def _spy(monkeypatch):
    calls = {"gram": 0, "fallback": 0, "gesdd_core": 0}
    core, real_svd = hf._merge_core_gram, hf._svd

    def gram(M, ka, budget2):
        out = core(M, ka, budget2)
        calls["fallback" if out is None else "gram"] += 1
        return out

    def svd(M, where):
        calls["gesdd_core"] += "merge" in where
        return real_svd(M, where)

    monkeypatch.setattr(hf, "_merge_core_gram", gram)
    monkeypatch.setattr(hf, "_svd", svd)
    return calls


def test_gram_merge_keeps_the_gesdd_rank_and_measures_its_discard(monkeypatch, children):
    A, left, right, budget = children
    assert hf._gram_merge_applies(left.s.size, right.s.size, np.float32)
    calls = _spy(monkeypatch)
    node = hf.merge_nodes(left, right, budget, "merge test")
    assert calls == {"gram": 1, "fallback": 0, "gesdd_core": 0}
    monkeypatch.setattr(hf, "_GRAM_MERGE_MIN_WIDTH", 10 ** 9)
    ref = hf.merge_nodes(left, right, budget, "merge test")
    assert calls["gesdd_core"] == 1
    # both spend the whole budget on float64-accurate singular values: the same rank
    print(f"\nrank gram {node.s.size} gesdd {ref.s.size}")
    assert node.s.size == ref.s.size
    children_dense = np.hstack([dense(left), dense(right)])
    own2 = node.discarded2 - left.discarded2 - right.discarded2
    true2 = float(np.sum((children_dense - dense(node)) ** 2))
    norm2 = left.norm2 + right.norm2
    print(f"discard reported {own2 / norm2:.6e} measured {true2 / norm2:.6e}")
    # observed: equal to 3e-9 ||A||^2 (float32 factors); the budget is 3e-4 ||A||^2
    assert abs(own2 - true2) <= 1e-7 * norm2
    assert true2 <= budget.merge(norm2) + left.slack2 + right.slack2
    k = node.s.size
    # observed 4.7e-7 and 7.8e-7 (float32 rounding of orthonormal float64 factors)
    np.testing.assert_allclose(node.U.T.astype(np.float64) @ node.U, np.eye(k), atol=2e-6)
    np.testing.assert_allclose(node.V.T.astype(np.float64) @ node.V, np.eye(k), atol=2e-6)
    assert np.all(np.diff(node.s) <= 0)
    # the singular values agree with gesdd's where both keep them
    # observed 6e-7 of s[0] at most (8.5e-7 relative)
    np.testing.assert_allclose(node.s[:ref.s.size], ref.s, rtol=1e-5, atol=1e-6 * ref.s[0])


def test_hf_with_gram_merges_reports_the_measured_error(monkeypatch):
    A = decaying(1200, 60.0, seed=1)
    calls = _spy(monkeypatch)
    lr = hf.hierarchical_factorization([A[:, i:i + 150] for i in range(0, 1200, 150)], 1200, eps=0.02)
    assert calls["gram"] >= 2 and calls["fallback"] == 0
    err = np.linalg.norm(A.astype(np.float64) - lr.Q.astype(np.float64) @ lr.V.T)
    print(f"\nrank {lr.rank} achieved {lr.achieved_error:.6e} measured {err:.6e}")
    # observed relative difference 2e-5 (float32 factors)
    assert abs(err - lr.achieved_error) <= 2e-4 * lr.achieved_error
    assert err <= 0.02 * np.linalg.norm(A)


def test_tiny_budget_or_float64_falls_back_to_gesdd(monkeypatch, children):
    """A budget under _GRAM_MIN_EPS eps64 ||M||^2 is inside the Gram's rounding: gesdd decides."""
    A, left, right, _ = children
    tiny = hf.ErrorBudget(1e-7, True, 2, 0.5)
    # the children's unused budget would be the merge's too: none here
    left, right = dataclasses.replace(left, slack2=0.0), dataclasses.replace(right, slack2=0.0)
    calls = _spy(monkeypatch)
    node = hf.merge_nodes(left, right, tiny, "merge tiny")
    assert calls == {"gram": 0, "fallback": 1, "gesdd_core": 1}
    assert node.s.size == left.s.size + right.s.size      # nothing of the children fits 1e-14
    # float64 working precision: the Gram squares the condition, so no Gram merge at all
    assert not hf._gram_merge_applies(300, 300, np.float64)
    assert hf._gram_merge_applies(128, 128, np.float32)
    assert not hf._gram_merge_applies(100, 100, np.float32)
