"""Read-only views of the arrays a factorization holds.

A factorization's arrays (the permutation, Q, V, the reflectances, the k x k
inverses, the near field and its solutions) are computed together: writing
into one of them would leave the others stale and every later solve wrong
without a sign. The solver objects therefore hold them through views whose
``flags.writeable`` is False, so ``fac.Q[0, 0] = 1`` raises ``ValueError``.
A view costs no copy: the caller's array keeps its own flags (code that holds
the original can still write to it, as it could to any array it passed in).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

__all__ = ["read_only", "read_only_csr"]


def read_only(a) -> np.ndarray:
    """A view of ``a`` (converted by :func:`numpy.asarray`) that refuses writes."""
    view = np.asarray(a).view()
    view.flags.writeable = False
    return view


def read_only_csr(M: sp.csr_matrix) -> sp.csr_matrix:
    """A CSR matrix over read-only views of ``M``'s ``data``, ``indices`` and ``indptr`` (no copy)."""
    out = sp.csr_matrix(M.shape, dtype=M.dtype)
    out.data, out.indices, out.indptr = read_only(M.data), read_only(M.indices), read_only(M.indptr)
    return out
