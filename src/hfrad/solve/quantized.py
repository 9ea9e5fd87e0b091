"""Tall matrices stored as 16-bit integers with one float32 scale per row.

A relighting solve with the near-field split reads one n x k matrix
``Z_c = A_c^{-1} D_c Q`` per distinct colour channel (three for a coloured
scene) besides V: that reading is most of the solve's time. Stored as
``Z[i, j] ~= scale[i] * codes[i, j]`` with int16 codes, they take half the
bytes of float32 and a solve reads half as much. Each entry is off by at
most ``scale[i] / 2 = max_j |Z[i, j]| / 65534`` (1.5e-5 of its row's largest
entry), which :meth:`QuantizedRows.error_bound` turns into a bound on the
whole matrix's error; the near-field solver stores Z this way only where that
error is a negligible share of the factorization's own
(:data:`hfrad.solve.nearfield.QUANTIZE_SHARE`).

The product with a few columns streams each row once (int16 -> float32 in
registers), as :mod:`hfrad.solve.thin` does for float factors.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from ..errors import InputError
from .readonly import read_only
from .thin import THIN_MAX

__all__ = ["QuantizedRows", "CODE_MAX"]

#: Largest code: a row's largest entry in magnitude is stored as +-CODE_MAX.
CODE_MAX = 32767
#: Rows decoded at a time for products with many columns (BLAS on float32 slabs).
DECODE_ROWS = 4096


@njit(parallel=True, fastmath=True, cache=True)
def _add_stack_dot(codes, scale, which, ST, out):  # pragma: no cover - compiled
    """``out[i, c, j] += scale[w, i] * sum_l codes[w, i, l] ST[c, j, l]`` with ``w = which[c]``.

    One matrix of the stack at a time, so the rows are read as one sequential
    stream (not the d matrices' rows side by side); the column groups sharing a
    matrix are done while its row is in L1.
    """
    d, n, k = codes.shape
    C, m = ST.shape[0], ST.shape[1]
    for w in range(d):
        rows, steps = codes[w], scale[w]
        for i in prange(n):
            row = rows[i]
            for c in range(C):
                if which[c] != w:
                    continue
                for j in range(m):
                    s = ST[c, j]
                    acc = np.float32(0)
                    for l in range(k):
                        acc += np.float32(row[l]) * s[l]
                    out[i, c, j] += steps[i] * acc


class QuantizedRows:
    """An (n, k) matrix as int16 ``codes`` and a float32 ``scale`` per row (or a stack of them).

    Parameters
    ----------
    codes : (..., n, k) int16
    scale : (..., n) float32
        ``A[..., i, j] ~= scale[..., i] * codes[..., i, j]``.

    Notes
    -----
    ``codes`` and ``scale`` are held read-only (views; writing raises
    ``ValueError``): a factorization's K_c was computed from these values.
    Memory: ``2 n k + 4 n`` bytes per matrix of the stack.

    Raises
    ------
    InputError
        ``codes`` is not at least 2-D or ``scale``'s shape is not ``codes.shape[:-1]``.
    """

    dtype = np.dtype(np.float32)

    def __init__(self, codes: np.ndarray, scale: np.ndarray) -> None:
        codes = np.ascontiguousarray(codes, dtype=np.int16)
        scale = np.ascontiguousarray(scale, dtype=np.float32)
        if codes.ndim < 2 or scale.shape != codes.shape[:-1]:
            raise InputError(f"codes (..., n, k) and scale (..., n) do not match: codes {codes.shape}, "
                             f"scale {scale.shape} (scale must have codes' shape without its last axis)")
        self.codes, self.scale = read_only(codes), read_only(scale)

    @classmethod
    def encode(cls, A: np.ndarray) -> "QuantizedRows":
        """Round each row of ``A`` (n, k) to ``CODE_MAX`` steps of its largest magnitude."""
        A = np.asarray(A)
        scale = cls.row_scale(np.abs(A).max(axis=-1)) if A.shape[-1] else np.zeros(A.shape[:-1], np.float32)
        return cls(cls.encode_with(A, scale), scale)

    @classmethod
    def stack(cls, parts: list["QuantizedRows"]) -> "QuantizedRows":
        """One stack (d, n, k) of d matrices of the same shape."""
        return cls(np.stack([p.codes for p in parts]), np.stack([p.scale for p in parts]))

    @property
    def shape(self) -> tuple[int, ...]:
        return self.codes.shape

    @property
    def nbytes(self) -> int:
        return self.codes.nbytes + self.scale.nbytes

    def __getitem__(self, index: int) -> "QuantizedRows":
        """Matrix ``index`` of a stack."""
        return QuantizedRows(self.codes[index], self.scale[index])

    def decode(self, rows: slice = slice(None)) -> np.ndarray:
        """float32 ``scale * codes`` (of ``rows``; a stack's last two axes)."""
        return self.codes[..., rows, :].astype(np.float32) * self.scale[..., rows, None]

    def error_bound(self) -> float:
        """Upper bound on ``||A - decode()||_F``: each entry is off by at most half its row's step."""
        return self.scale_error(self.scale, self.codes.shape[-1])

    @staticmethod
    def row_scale(row_max: np.ndarray) -> np.ndarray:
        """(n,) float32 scales of rows whose largest magnitudes are ``row_max``: as :meth:`encode` sets them."""
        return (np.asarray(row_max) / CODE_MAX).astype(np.float32)

    @staticmethod
    def encode_with(A: np.ndarray, scale: np.ndarray) -> np.ndarray:
        """(n, w) int16 codes of ``A`` (n, w), some columns of rows whose scales are ``scale`` (n,).

        The codes :meth:`encode` gives those columns when ``scale`` comes from the whole
        rows (:meth:`row_scale` of the row maxima): a column panel is coded on its own.
        """
        safe = np.where(scale > 0, scale, 1).astype(A.dtype)
        return np.clip(np.rint(A / safe[..., None]), -CODE_MAX, CODE_MAX).astype(np.int16)

    @staticmethod
    def scale_error(scale: np.ndarray, k: int) -> float:
        """:meth:`error_bound` of a matrix with k columns and row scales ``scale``."""
        return 0.5 * math.sqrt(k) * float(np.linalg.norm(np.asarray(scale, np.float32).astype(np.float64)))

    def matmul(self, S: np.ndarray) -> np.ndarray:
        """``decode() @ S`` for S (k, r), float32 (n, r), without decoding the matrix at once."""
        n, k = self.codes.shape
        r = S.shape[1]
        if r <= THIN_MAX:           # the streaming kernel, on a stack of one
            out = np.zeros((n, 1, r))
            QuantizedRows(self.codes[None], self.scale[None]).add_products(out, S[:, None, :], [0])
            return out[:, 0, :].astype(np.float32)
        out = np.empty((n, r), np.float32)
        S32 = S.astype(np.float32)
        for a in range(0, n, DECODE_ROWS):
            rows = slice(a, min(a + DECODE_ROWS, n))
            out[rows] = self.decode(rows) @ S32
        return out

    def add_products(self, out: np.ndarray, S: np.ndarray, which) -> None:
        """``out[:, c, :] += decode()[which[c]] @ S[:, c, :]`` for a stack (d, n, k), in place.

        Parameters
        ----------
        out : (n, C, m) float64
        S : (k, C, m)
        which : (C,) int
            The matrix of the stack that column group c multiplies.

        One pass over the stack's rows for all C m columns: a row of codes is
        read once (again from L1 for column groups sharing a matrix).
        """
        which = np.asarray(which, dtype=np.int64)
        d, n, k = self.codes.shape
        C, m = out.shape[1], out.shape[2]
        if k == 0:
            return
        if C * m <= THIN_MAX and out.flags.c_contiguous:
            ST = np.ascontiguousarray(np.moveaxis(S, 0, -1), dtype=np.float32)       # (C, m, k)
            _add_stack_dot(self.codes, self.scale, which, ST, out)
            return
        for w in np.unique(which):
            cols = np.flatnonzero(which == w)
            out[:, cols, :] += self[w].matmul(S[:, cols, :].reshape(k, -1)).reshape(n, len(cols), m)

    def __repr__(self) -> str:
        return f"QuantizedRows(shape={self.shape}, {self.nbytes / 1e6:.1f} MB)"
