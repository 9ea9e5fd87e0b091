"""A column block as exact rows plus a low-rank far part: what the sampled far field hands on.

The sampled far field (:mod:`hfrad.formfactors.farfield`) computes a column block of F
pair by pair only in some rows (near rows, rows whose visibility is mixed) and interpolates
the others from a few skeleton columns of each column group::

    F[:, C] = P_E D + P_R W X

``E`` (m rows, sorted) are the rows held densely (``D``: m x b), ``R`` the rest, whose rows
are ``W X`` (``W``: (n - m) x s, the skeleton columns of every column group side by side;
``X``: s x b, each group's interpolation in its own columns). Everything downstream of the
form factors (the pass statistics, the near-field split, HF's leaf) reads these pieces in
O((m b + n s) ...) instead of the dense n x b block, whose forming would cost more than the
far field saved (issue 43, item 3). The functions at the end take either a dense array or
pieces, so their callers need not care which they were given.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["BlockPieces", "rows_of", "product", "column_squares", "gram64"]

#: Rows taken to float64 at a time where a float64 copy of a whole (n x s) factor is not wanted.
SLAB_ROWS = 8192


@dataclass
class BlockPieces:
    """``B[rows] = dense``, ``B[far] = W @ X``: an n x b column block in pieces.

    Attributes
    ----------
    n : int
        Rows of the block (patches).
    rows : (m,) int64, sorted
        Rows held densely.
    dense : (m, b) array
    far : (n - m,) int64, sorted
        The other rows (the complement of ``rows``).
    W : (n - m, s) array
        Their factor: the skeleton columns' values.
    X : (s, b) float64
        The interpolation.
    """

    n: int
    rows: np.ndarray
    dense: np.ndarray
    far: np.ndarray
    W: np.ndarray
    X: np.ndarray

    @classmethod
    def from_dense(cls, A: np.ndarray) -> "BlockPieces":
        """Pieces holding every row of ``A`` densely (a block that did not compress)."""
        n, b = A.shape
        return cls(n, np.arange(n, dtype=np.int64), A, np.zeros(0, np.int64), np.zeros((0, 0), A.dtype),
                   np.zeros((0, b)))

    @property
    def shape(self) -> tuple[int, int]:
        return self.n, self.X.shape[1]

    @property
    def dtype(self) -> np.dtype:
        return self.dense.dtype

    @property
    def is_dense(self) -> bool:
        """Whether every row is held densely (nothing to gain from the pieces)."""
        return self.far.size == 0

    def astype(self, dtype) -> "BlockPieces":
        """The pieces with ``dense`` and ``W`` in ``dtype`` (X stays float64: it is small)."""
        return BlockPieces(self.n, self.rows, self.dense.astype(dtype, copy=False), self.far,
                           self.W.astype(dtype, copy=False), self.X)

    def to_dense(self, out: np.ndarray | None = None) -> np.ndarray:
        """The n x b block (into ``out`` when given; pieces holding every row densely are their
        ``dense`` already, rows in order: returned as they are, no copy)."""
        if self.is_dense and out is None:
            return self.dense
        out = np.empty(self.shape, self.dtype) if out is None else out
        out[self.rows] = self.dense
        if self.far.size:
            out[self.far] = self.W @ self.X.astype(self.dtype)
        return out

    def scaled(self, rho: np.ndarray, dtype) -> "BlockPieces":
        """``diag(rho) B`` in ``dtype`` (rows scaled: the dense rows and W's)."""
        rho = np.asarray(rho).reshape(self.n)
        dense = np.asarray(self.dense, dtype) * rho[self.rows, None].astype(dtype)
        W = np.asarray(self.W, dtype) * rho[self.far, None].astype(dtype)
        return BlockPieces(self.n, self.rows, dense, self.far, W, self.X)

    def take_rows(self, idx: np.ndarray) -> np.ndarray:
        """(len(idx), b) rows ``idx`` of the block, in its dtype."""
        idx = np.asarray(idx, np.int64)
        pos = np.searchsorted(self.rows, idx)
        held = np.zeros(idx.size, bool)
        inside = pos < self.rows.size
        held[inside] = self.rows[pos[inside]] == idx[inside]
        out = np.empty((idx.size, self.shape[1]), self.dtype)
        out[held] = self.dense[pos[held]]
        if (~held).any():
            where = np.searchsorted(self.far, idx[~held])
            out[~held] = self.W[where] @ self.X.astype(self.dtype)
        return out

    def with_dense_rows(self, idx: np.ndarray) -> "BlockPieces":
        """The same block with rows ``idx`` (and those already held) held densely."""
        idx = np.asarray(idx, np.int64)
        new = np.setdiff1d(idx, self.rows)
        if new.size == 0:
            return self
        rows = np.union1d(self.rows, new)
        dense = np.empty((rows.size, self.shape[1]), self.dtype)
        held = np.isin(rows, self.rows, assume_unique=True)
        dense[held] = self.dense
        dense[~held] = self.take_rows(new)
        keep = ~np.isin(self.far, new, assume_unique=True)
        return BlockPieces(self.n, rows, dense, self.far[keep], self.W[keep], self.X)

    def row_sums(self) -> np.ndarray:
        """(n,) float64 sums of each row."""
        out = np.zeros(self.n)
        out[self.rows] = self.dense.sum(axis=1, dtype=np.float64)
        if self.far.size:
            out[self.far] = _matmul64(self.W, self.X.sum(axis=1))
        return out

    def col_sums(self) -> np.ndarray:
        """(b,) float64 sums of each column."""
        out = self.dense.sum(axis=0, dtype=np.float64)
        if self.far.size:
            out += self.W.sum(axis=0, dtype=np.float64) @ self.X
        return out

    def matmul(self, Y: np.ndarray) -> np.ndarray:
        """(n, q) float64 ``B @ Y`` for Y (b, q)."""
        Y = np.asarray(Y, np.float64)
        out = np.zeros((self.n, Y.shape[1]))
        if self.rows.size:
            out[self.rows] = np.asarray(self.dense, np.float64) @ Y
        if self.far.size:
            out[self.far] = _matmul64(self.W, self.X @ Y)
        return out

    def frobenius2(self) -> float:
        """``||B||_F^2`` in float64."""
        total = float(np.square(self.dense, dtype=np.float64).sum())
        if self.far.size:
            M = gram64(self.W)
            total += float(np.einsum("kp,kl,lp->", self.X, M, self.X))
        return total

    def column_squares(self, scale: np.ndarray) -> np.ndarray:
        """(b, c) ``sum_i scale[i, c] B[i, p]^2`` in float64 (``scale``: (n, c), non-negative)."""
        scale = np.asarray(scale, np.float64)
        out = np.square(self.dense, dtype=np.float64).T @ scale[self.rows]
        for c in range(scale.shape[1]) if self.far.size else ():
            M = gram64(self.W, scale[self.far, c])
            out[:, c] += np.einsum("kp,kl,lp->p", self.X, M, self.X)
        return out


def gram64(W: np.ndarray, weights: np.ndarray | None = None, slab_rows: int = SLAB_ROWS) -> np.ndarray:
    """``W^T diag(weights) W`` (k, k) in float64 for W (m, k) of any float dtype, ``slab_rows`` rows taken
    to float64 at a time: the Gram matrix of a float32 factor to float64 rounding without a float64
    copy of W (a transposed view serves for ``B B^T`` of a wide B)."""
    M = np.zeros((W.shape[1], W.shape[1]))
    for a in range(0, W.shape[0], slab_rows):
        slab = np.asarray(W[a:a + slab_rows], np.float64)
        M += slab.T @ (slab if weights is None else slab * weights[a:a + slab_rows, None])
    return M


def _matmul64(W: np.ndarray, Z: np.ndarray) -> np.ndarray:
    """``W @ Z`` in float64 (Z float64), slab by slab of W's rows."""
    out = np.empty((W.shape[0],) + Z.shape[1:])
    for a in range(0, W.shape[0], SLAB_ROWS):
        out[a:a + SLAB_ROWS] = np.asarray(W[a:a + SLAB_ROWS], np.float64) @ Z
    return out


# -- Dense arrays and pieces alike -----------------------------------------------------------------

def rows_of(B, idx: np.ndarray) -> np.ndarray:
    """Rows ``idx`` of a block (array or :class:`BlockPieces`)."""
    return B.take_rows(idx) if isinstance(B, BlockPieces) else B[idx]


def product(B, Y: np.ndarray) -> np.ndarray:
    """``B @ Y`` of a block (array: in its dtype, as NumPy multiplies; pieces: float64)."""
    return B.matmul(Y) if isinstance(B, BlockPieces) else np.asarray(B) @ np.asarray(Y).astype(B.dtype)


def column_squares(B, scale: np.ndarray) -> np.ndarray:
    """(b, c) ``sum_i scale[i, c] B[i, p]^2`` in float64, for an array (slab by slab of rows: a
    float64 copy of the whole n x b block would cost 8 n b bytes) or :class:`BlockPieces`."""
    if isinstance(B, BlockPieces):
        return B.column_squares(scale)
    out = np.zeros((B.shape[1], scale.shape[1]))
    for lo in range(0, B.shape[0], SLAB_ROWS):
        slab = np.square(np.asarray(B[lo:lo + SLAB_ROWS], np.float64))
        out += slab.T @ scale[lo:lo + SLAB_ROWS]
    return out
