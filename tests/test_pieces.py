"""A column block in pieces (exact rows + W X) reads as the dense block it stands for (issue 43, item 3).

Every consumer of the sampled far field's blocks (the pass statistics, the near-field split,
HF's leaf) is checked against the same consumer given the dense block: the pieces must change
how much work is done, never the answer beyond rounding.
"""

from __future__ import annotations

import numpy as np
import pytest

from hfrad.formfactors.pieces import BlockPieces, column_squares, product, rows_of
from hfrad.lowrank.hf import HFStream
from hfrad.lowrank.nearsplit import NearFieldSplit
from hfrad.solve.stats import PassStatistics

N, B, M, S = 600, 32, 70, 6


def random_pieces(seed: int = 0, dtype=np.float64) -> BlockPieces:
    """Non-negative pieces like a far field's: dense rows, and far rows of rank S."""
    rng = np.random.default_rng(seed)
    rows = np.sort(rng.choice(N, M, replace=False))
    far = np.setdiff1d(np.arange(N), rows)
    W = rng.random((far.size, S)) * 1e-3
    X = rng.random((S, B))
    return BlockPieces(N, rows, rng.random((M, B)).astype(dtype) * 1e-2, far, W.astype(dtype), X)


def test_pieces_read_as_their_dense_block():
    P = random_pieces()
    A = P.to_dense()
    rng = np.random.default_rng(1)
    idx = rng.choice(N, 40, replace=False)
    Y = rng.standard_normal((B, 5))
    scale = rng.random((N, 3))
    np.testing.assert_allclose(rows_of(P, idx), A[idx], rtol=1e-13)
    np.testing.assert_allclose(product(P, Y), A @ Y, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(column_squares(P, scale), column_squares(A, scale), rtol=1e-12)
    np.testing.assert_allclose(P.row_sums(), A.sum(axis=1), rtol=1e-13)
    np.testing.assert_allclose(P.col_sums(), A.sum(axis=0), rtol=1e-13)
    assert P.frobenius2() == pytest.approx(float(np.square(A).sum()), rel=1e-12)
    rho = rng.random(N)
    np.testing.assert_allclose(P.scaled(rho, np.float64).to_dense(), rho[:, None] * A, rtol=1e-13)
    Q = P.with_dense_rows(np.array([P.far[0], P.far[5], P.rows[0]]))
    assert Q.rows.size == M + 2 and Q.far.size == N - M - 2
    np.testing.assert_allclose(Q.to_dense(), A, rtol=1e-13)
    assert BlockPieces.from_dense(A).is_dense and not P.is_dense


def test_pass_statistics_from_pieces_equal_the_dense_pass():
    P = random_pieces(2)
    A = P.to_dense()
    weights = np.random.default_rng(3).random(N) + 0.5
    rho = np.random.default_rng(4).random((N, 1))
    got, want = PassStatistics(N, weights), PassStatistics(N, weights)
    G_p, norm2_p = got.add_scaled(0, B, P, rho)
    G_d, norm2_d = want.add_scaled(0, B, A, rho)
    assert isinstance(G_p, BlockPieces)
    np.testing.assert_allclose(G_p.to_dense(), G_d, rtol=1e-13)
    assert norm2_p == pytest.approx(norm2_d, rel=1e-12)
    for name in ("row_sums", "col_sums", "sketch"):
        np.testing.assert_allclose(getattr(got, name), getattr(want, name), rtol=1e-10, atol=1e-14)


def test_near_split_of_pieces_moves_the_same_entries():
    P = random_pieces(5)
    centroids = np.random.default_rng(6).random((N, 3))
    a, b = NearFieldSplit(centroids, 0.15), NearFieldSplit(centroids, 0.15)
    G_p = a.split(P, 100)
    G_d = b.split(P.to_dense(), 100)
    np.testing.assert_allclose(G_p.to_dense(), G_d, rtol=1e-13)
    sa, sb = a.state(), b.state()
    order_a = np.lexsort((sa["near_cols"], sa["near_rows"]))
    order_b = np.lexsort((sb["near_cols"], sb["near_rows"]))
    for k in ("near_rows", "near_cols", "near_values"):
        np.testing.assert_allclose(sa[k][order_a], sb[k][order_b], rtol=1e-13)
    assert a.moved2 == pytest.approx(b.moved2, rel=1e-12) and a.moved2 > 0


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_hf_leaf_from_pieces_equals_the_dense_leaf(dtype):
    """Two blocks pushed as pieces and as dense arrays: the same singular values, error and product."""
    blocks = [random_pieces(7 + k, dtype) for k in range(2)]
    eps = 0.05
    runs = []
    for dense in (False, True):
        stream = HFStream(N, 2, eps=eps, dtype=dtype)
        for P in blocks:
            stream.push(P.to_dense() if dense else P)
        runs.append(stream.finish())
    pieces, dense = runs
    assert pieces.rank == dense.rank
    # observed: float64 4e-14 (errors) and 1.5e-14 (entries); float32 1e-5 and 3.5e-6
    tol_error, tol_entries = (1e-12, 1e-12) if dtype == np.float64 else (5e-5, 2e-5)
    assert pieces.achieved_error == pytest.approx(dense.achieved_error, rel=tol_error)
    A = np.hstack([P.to_dense() for P in blocks]).astype(np.float64)
    for lr in runs:
        err = np.linalg.norm(A - lr.Q.astype(np.float64) @ lr.V.T.astype(np.float64))
        assert err == pytest.approx(lr.achieved_error, rel=tol_error)
        assert err <= eps * np.linalg.norm(A)
    np.testing.assert_allclose(pieces.Q @ pieces.V.T, dense.Q @ dense.V.T, rtol=0,
                               atol=tol_entries * float(np.abs(A).max()))
