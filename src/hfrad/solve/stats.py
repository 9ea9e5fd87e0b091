"""What the single pass over F records besides the factors: sums and random probes.

docs/method.md, section 7: the row sums of F bound ``||R_c F||`` (and flag
energy errors), and the sketch ``G Omega'`` of a few Gaussian probes, taken
while each column block streams past, measures the factorization error
``||G - Q V^T||`` after the pass with a stated failure probability.
"""

from __future__ import annotations

import copy
import math

import numpy as np

from ..lowrank.hf import SLAB_ROWS
from .bounds import contraction_bound
from .readonly import read_only

__all__ = ["PassStatistics", "PROBES", "FAILURE_PROBABILITY", "probe_alpha", "probe_vectors"]


#: Gaussian probes of the factorization error accumulated during the single pass over F.
PROBES = 20
#: Probability that the probe-based figure is not an upper bound (Halko et al. 2011, Lemma 4.1).
FAILURE_PROBABILITY = 1e-6
PROBE_SEED = 20161


def probe_alpha(probes: int, failure: float = FAILURE_PROBABILITY) -> float:
    """alpha with alpha^-p = failure: ||M|| <= alpha sqrt(2/pi) max_i ||M omega_i|| but with that probability."""
    return float(failure ** (-1.0 / probes))


def probe_vectors(weights: np.ndarray | None, n: int, probes: int = PROBES, seed: int = PROBE_SEED) -> np.ndarray:
    """(n, p) ``W^{-1/2} Omega`` with Omega standard Gaussian: probes of ``W^{1/2} X W^{-1/2}``."""
    omega = np.random.default_rng(seed).standard_normal((n, probes))
    return omega if weights is None else omega / np.sqrt(weights)[:, None]


class PassStatistics:
    """What the single pass over F records besides the factors, in the internal patch order.

    Row and column sums of F (energy checks, the contraction bound) and the
    sketch ``G Omega'`` of p random probes (the factorization error,
    docs/method.md section 7). Costs 2 n^2 p flops in all, O(n p) memory.

    Parameters
    ----------
    n : int
    weights : (n,) float, optional
        Patch areas in internal order: the norm is the area-weighted one
        (``||x||_A = ||A^{1/2} x||``). None: the plain 2-norm.
    probes : int
    seed : int
    """

    def __init__(self, n: int, weights=None, *, probes: int = PROBES, seed: int = PROBE_SEED) -> None:
        self.n, self.probes, self.seed = int(n), int(probes), int(seed)
        self.weights = None if weights is None else np.asarray(weights, dtype=np.float64).reshape(n)
        self.row_sums = np.zeros(n)
        self.col_sums = np.zeros(n)
        self.sketch = np.zeros((n, probes))
        self._omega = probe_vectors(self.weights, n, probes, seed)

    def add(self, start: int, stop: int, F_block: np.ndarray, rows_rho: np.ndarray) -> None:
        """Record columns ``start:stop`` of F (all rows, internal order); ``rows_rho`` is (n, 1) rho_max.

        In float64, slab by slab of ``SLAB_ROWS`` rows: a float64 copy of a whole block of
        b columns would be ``8 n b`` bytes of fresh memory every block (page faults each
        time), a slab's copy is ``8 SLAB_ROWS b`` bytes and stays in the cache.
        """
        omega = self._omega[start:stop]
        col_sums = np.zeros(stop - start)
        for a in range(0, F_block.shape[0], SLAB_ROWS):
            Fb = np.asarray(F_block[a:a + SLAB_ROWS], dtype=np.float64)
            self.row_sums[a:a + SLAB_ROWS] += Fb.sum(axis=1)
            col_sums += Fb.sum(axis=0)
            self.sketch[a:a + SLAB_ROWS] += rows_rho[a:a + SLAB_ROWS] * (Fb @ omega)   # G Omega', block by block
        self.col_sums[start:stop] = col_sums

    def state(self) -> dict:
        """Arrays and numbers that :meth:`from_state` rebuilds this from (checkpoints, .hfr files)."""
        out = {"row_sums": self.row_sums, "col_sums": self.col_sums, "sketch": self.sketch,
               "probes": self.probes, "seed": self.seed}
        if self.weights is not None:
            out["weights"] = self.weights
        return out

    def frozen(self) -> "PassStatistics":
        """A shallow copy whose arrays are read-only views (what a factorization holds, no copy of data).

        The error figures are computed from these sums and sketch; the copy
        refuses :meth:`add` (``ValueError``), while ``self`` stays writable.
        """
        out = copy.copy(self)
        for name in ("row_sums", "col_sums", "sketch", "weights", "_omega"):
            value = getattr(self, name)
            if value is not None:
                setattr(out, name, read_only(value))
        return out

    @classmethod
    def from_state(cls, state: dict) -> "PassStatistics":
        sketch = np.asarray(state["sketch"], dtype=np.float64)
        stats = cls(sketch.shape[0], state.get("weights"), probes=int(state["probes"]), seed=int(state["seed"]))
        stats.row_sums = np.asarray(state["row_sums"], dtype=np.float64)
        stats.col_sums = np.asarray(state["col_sums"], dtype=np.float64)
        stats.sketch = sketch
        return stats

    def operator_error(self, Q: np.ndarray, V: np.ndarray, D: np.ndarray, *, near=None,
                       low_rank=None) -> np.ndarray:
        """(3,) upper bound on ``||R_c F - Q_c V^T||`` per channel, failing with probability FAILURE_PROBABILITY.

        ``(G - Q V^T) Omega' = sketch - Q (V^T Omega')`` (minus ``near Omega'`` for the
        near-field split's sparse N, internal order); channel c scales rows
        by ``D_c = rho_c / rho_max``, and ``||M|| <= alpha sqrt(2/pi) max_i ||M omega_i||``
        (Halko, Martinsson & Tropp 2011, Lemma 4.1) with ``M`` the weighted error.

        Parameters
        ----------
        Q, V : (n, k)
        D : (n, 3)
        near : (n, n) sparse, optional
        low_rank : callable, optional
            ``low_rank(c, W)``: channel c's low-rank part applied to ``W = V^T Omega'``
            (n, p), where the solve inverts ``D_c N + U_c V^T`` with another ``U_c`` than
            ``D_c Q`` (the near-field solver's stored ``A_c Z_c``).
        """
        W = V.astype(np.float64).T @ self._omega
        base = self.sketch if near is None else self.sketch - near @ self._omega
        QW = None if low_rank is not None else Q.astype(np.float64) @ W
        scale = probe_alpha(self.probes) * math.sqrt(2.0 / math.pi)
        out = np.empty(D.shape[1])
        for c in range(D.shape[1]):
            R = D[:, c:c + 1] * (base - QW) if low_rank is None else D[:, c:c + 1] * base - low_rank(c, W)
            if self.weights is not None:
                R = np.sqrt(self.weights)[:, None] * R
            out[c] = scale * np.linalg.norm(R, axis=0).max()
        return out

    def contraction(self, reflectance_int: np.ndarray) -> np.ndarray:
        """(3,) upper bound on ``||R_c F||`` in this norm (:func:`~hfrad.solve.bounds.contraction_bound`)."""
        return contraction_bound(reflectance_int, self.row_sums, self.col_sums, weighted=self.weights is not None)

    @property
    def norm(self) -> str:
        """``"area"`` when the patch areas weight the norm, else ``"2"``."""
        return "area" if self.weights is not None else "2"
