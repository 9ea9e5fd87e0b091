"""The result of every factorizer: a low-rank pair A ~= Q V^T with its achieved error."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class LowRank:
    """A low-rank approximation ``A ~= Q @ V.T`` of an (n, n') matrix.

    Attributes
    ----------
    Q : (n, k) float
        Left factor, ``Q = U diag(s)`` with orthonormal ``U``.
    V : (n', k) float
        Right factor with orthonormal columns.
    achieved_error : float
        ``||A - Q V^T||_F`` (absolute), as achieved, not as targeted.
    norm : float
        ``||A||_F``.
    eps : float
        The requested tolerance (relative to ``norm`` when ``relative``).
    relative : bool
        Whether ``eps`` is relative to ``||A||_F`` or absolute.
    method : str
        Which factorizer produced it ("hf", "svd", "rsvd", "sketch", "operator").
    info : dict
        Timings (seconds) and rank statistics, method specific.
    """

    Q: np.ndarray
    V: np.ndarray
    achieved_error: float
    norm: float
    eps: float
    relative: bool = True
    method: str = "hf"
    info: dict = field(default_factory=dict)

    @property
    def rank(self) -> int:
        """k, the number of columns of Q and V."""
        return int(self.Q.shape[1])

    @property
    def relative_error(self) -> float:
        """``||A - Q V^T||_F / ||A||_F`` (0 for a zero matrix)."""
        return float(self.achieved_error / self.norm) if self.norm > 0 else 0.0

    @property
    def target_error(self) -> float:
        """The absolute Frobenius error allowed by ``eps``."""
        return float(self.eps * self.norm if self.relative else self.eps)


def truncation_rank(s: np.ndarray, budget2: float) -> tuple[int, float]:
    """Smallest rank whose discarded squared Frobenius part fits in ``budget2``.

    Parameters
    ----------
    s : (p,) float
        Singular values in descending order.
    budget2 : float
        Allowed squared Frobenius norm of the discarded part.

    Returns
    -------
    k : int
        Number of singular values to keep.
    discarded2 : float
        ``sum(s[k:] ** 2)`` accumulated in float64.
    """
    s2 = np.asarray(s, dtype=np.float64) ** 2
    # tail[i] = sum_{j >= i} s_j^2, tail[p] = 0
    tail = np.concatenate([np.cumsum(s2[::-1])[::-1], [0.0]])
    k = int(np.argmax(tail <= budget2))  # tail is non-increasing, tail[p] = 0 always fits
    return k, float(tail[k])


def sign_fix(U: np.ndarray, Wt: np.ndarray | None = None) -> None:
    """Make the largest-magnitude entry of each column of U positive, in place.

    The matching rows of ``Wt`` are flipped too, so ``U S Wt`` is unchanged;
    this makes SVD-based factorizations deterministic.
    """
    if U.shape[1] == 0 or U.shape[0] == 0:
        return
    idx = np.argmax(np.abs(U), axis=0)
    signs = np.sign(U[idx, np.arange(U.shape[1])])
    signs[signs == 0] = 1
    U *= signs.astype(U.dtype)
    if Wt is not None:
        Wt *= signs.astype(Wt.dtype)[:, None]
