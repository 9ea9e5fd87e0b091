"""What the single pass over F records besides the factors: sums and random probes.

docs/method.md, section 7: the row sums of F bound ``||R_c F||`` (and flag
energy errors), and the sketch ``G Omega'`` of a few Gaussian probes, taken
while each column block streams past, measures the factorization error
``||G - Q V^T||`` after the pass with a stated failure probability.
"""

from __future__ import annotations

import copy
import math

import numba
import numpy as np
from numba import njit, prange

from ..formfactors.farfield import FarFieldCertificate
from ..formfactors.pieces import BlockPieces
from .bounds import contraction_bound, reflection_gain_bound
from .readonly import read_only
from .samples import SAMPLE_SHARE, SampledRows

__all__ = ["PassStatistics", "PROBES", "FAILURE_PROBABILITY", "probe_alpha", "probe_vectors"]


#: Gaussian probes of the factorization error accumulated during the single pass over F.
PROBES = 20
#: Probability that the probe-based figure is not an upper bound (Halko et al. 2011, Lemma 4.1).
FAILURE_PROBABILITY = 1e-6
PROBE_SEED = 20161


def probe_alpha(probes: int, failure: float = FAILURE_PROBABILITY) -> float:
    """alpha with alpha^-p = failure: ||M|| <= alpha sqrt(2/pi) max_i ||M omega_i|| but with that probability."""
    return float(failure ** (-1.0 / probes))


@njit(cache=True, parallel=True, nogil=True, fastmath={"reassoc", "contract"})
def _block_pass(F, rho, rho64, omega_t, row_sums, sketch, G, want_g, col_parts, g2_parts):  # pragma: no cover (numba)
    """Rows of a column block in ``len(g2_parts)`` chunks: row sums, column sums, ``G Omega'``, ``G`` and ``||G||^2``.

    F (n, b) and rho (n,) in the working dtype (``rho[i] * F[i, c]`` rounds as NumPy's product
    of the two), rho64 the same rho in float64 (the sketch's row scale), omega_t (p, b) float64
    (the block's probe rows, transposed: each probe's dot product with a row of F runs over
    contiguous memory); every sum in float64, in an order of the compiler's choosing
    (``reassoc``: vectorized). ``col_parts`` and ``g2_parts`` get one row / entry per chunk
    (summed by the caller: no two threads write the same place).
    """
    n, b = F.shape
    p = omega_t.shape[0]
    chunks = g2_parts.shape[0]
    for t in prange(chunks):
        lo, hi = t * n // chunks, (t + 1) * n // chunks
        row = np.empty(b)
        g2 = 0.0
        for i in range(lo, hi):
            total = 0.0
            r = rho[i]
            for c in range(b):
                f = F[i, c]
                row[c] = np.float64(f)
                total += row[c]
                col_parts[t, c] += row[c]
                if want_g:
                    g = r * f
                    G[i, c] = g
                    g2 += np.float64(g) * np.float64(g)
            row_sums[i] += total
            for q in range(p):
                dot = 0.0
                for c in range(b):
                    dot += row[c] * omega_t[q, c]
                sketch[i, q] += rho64[i] * dot
        g2_parts[t] = g2


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
    reflectance : (n, 3) float, optional
        Reflectance in internal order: with the areas, the exact sampled rows also record
        ``(F R_c F)`` rows (:class:`~hfrad.solve.samples.SampledRows`), the per-solve error
        figure's smooth term.
    """

    def __init__(self, n: int, weights=None, *, probes: int = PROBES, seed: int = PROBE_SEED,
                 reflectance=None) -> None:
        self.n, self.probes, self.seed = int(n), int(probes), int(seed)
        self.weights = None if weights is None else np.asarray(weights, dtype=np.float64).reshape(n)
        self.row_sums = np.zeros(n)
        self.col_sums = np.zeros(n)
        self.sketch = np.zeros((n, probes))
        self._omega = probe_vectors(self.weights, n, probes, seed)
        self.samples: SampledRows | None = SampledRows.design(self.n, self.weights, reflectance) if n else None
        #: The sampled far field's certificate (``||G - G~||`` from exact rows), None for an exact pass.
        self.far_field: FarFieldCertificate | None = None

    def add(self, start: int, stop: int, F_block: np.ndarray, rows_rho: np.ndarray) -> None:
        """Record columns ``start:stop`` of F (all rows, internal order); ``rows_rho`` is (n, 1) rho_max."""
        self._pass(start, stop, F_block, rows_rho, None)

    def add_scaled(self, start: int, stop: int, F_block: np.ndarray, rows_rho: np.ndarray,
                   out: np.ndarray | None = None, exact_rows: np.ndarray | None = None) -> tuple[np.ndarray, float]:
        """:meth:`add`, and the block of G it reads F for: ``(rows_rho * F_block, ||G_block||_F^2)``.

        ``out``: an array of F_block's shape and dtype to write G into (a buffer reused from
        block to block: fresh pages for every n x b block cost page faults); else a new one.
        ``exact_rows``: the exact rows of F at the sampled rows' patches where ``F_block`` is
        an approximation (:meth:`SampledRows.record`). ``F_block`` may be
        :class:`~hfrad.formfactors.pieces.BlockPieces` (then G is too, and ``out`` is not used).

        Returns
        -------
        G : (n, b) array in F_block's dtype
            ``rows_rho * F_block`` with rho in F's dtype (as NumPy rounds that product).
        norm2 : float
            ``||G||_F^2`` summed in float64 (what :func:`hfrad.lowrank.hf.frobenius2` gives).
        """
        if isinstance(F_block, BlockPieces):
            if not F_block.is_dense:
                return self._pass_pieces(start, stop, F_block, rows_rho, exact_rows)
            F_block = F_block.dense          # every row dense: the one-read pass below
        F_block = np.ascontiguousarray(F_block)
        usable = (isinstance(out, np.ndarray) and out.shape == F_block.shape and out.dtype == F_block.dtype
                  and out.flags.c_contiguous and out.flags.writeable)
        G = out if usable else np.empty_like(F_block)
        return G, self._pass(start, stop, F_block, rows_rho, G, exact_rows)

    def _pass_pieces(self, start: int, stop: int, F: BlockPieces, rows_rho, exact_rows=None):
        """:meth:`add_scaled` of a block in pieces (the sampled far field): the same sums, sketch and
        samples from the pieces, and G in pieces (never the dense n x b block)."""
        self._check_writable()
        if F.shape != (self.n, stop - start):
            raise ValueError(f"a block of columns {start}:{stop} must be ({self.n}, {stop - start}); got {F.shape}")
        rho = np.asarray(rows_rho).reshape(self.n)
        self.row_sums += F.row_sums()
        self.col_sums[start:stop] = F.col_sums()
        self.sketch += rho.astype(np.float64)[:, None] * F.matmul(self._omega[start:stop])
        if self.samples is not None:
            self.samples.record(start, stop, F, exact_rows)
        G = F.scaled(rho, F.dtype)
        return G, G.frobenius2()

    def record_operator(self, matmat, rmatmat, squares, rows_rho, exact_rows: np.ndarray | None = None) -> None:
        """Record all n columns of an F known only by its products (an H-matrix: ``far_field="hierarchical"``).

        What the column blocks' pass records, from products instead: the row sums ``F 1``, the column
        sums ``F^T 1``, the sketch ``rho F Omega'`` and the sampled rows' quantities
        (:meth:`SampledRows.record_operator`), all of the F the factorization was given.

        Parameters
        ----------
        matmat, rmatmat : callable
            ``F @ X`` and ``F.T @ X`` (internal order), X (n, l) float64 -> (n, l) float64.
        squares : callable
            ``squares(scale)`` (n, c) -> (n, c) ``sum_i scale[i, c] F[i, p]^2``.
        rows_rho : (n,) or (n, 1) float
            ``rho_max`` in internal order.
        exact_rows : (m, n), optional
            The exact rows of F at ``self.samples.row_patches`` (required when there are samples).
        """
        self._check_writable()
        rho = np.asarray(rows_rho, np.float64).reshape(self.n)
        Y = matmat(np.column_stack([np.ones(self.n), self._omega]))
        self.row_sums = Y[:, 0].copy()
        self.sketch = rho[:, None] * Y[:, 1:]
        self.col_sums = rmatmat(np.ones((self.n, 1)))[:, 0]
        if self.samples is not None:
            if exact_rows is None:
                raise ValueError("record_operator needs the exact rows at samples.row_patches")
            self.samples.record_operator(matmat, rmatmat, squares, exact_rows)

    def _check_writable(self) -> None:
        if not all(a.flags.writeable for a in (self.row_sums, self.col_sums, self.sketch)):
            raise ValueError("these pass statistics are read-only (a factorization's frozen copy): "
                             "record columns on the PassStatistics they were frozen from")

    def _pass(self, start: int, stop: int, F_block, rows_rho, G, exact_rows=None) -> float:
        """One read of the block for the sums, the sketch and (``G`` given) G and its norm.

        The block is read once, row by row, with float64 accumulators (:func:`_block_pass`):
        separate NumPy passes (the product, float64 slabs for the sums and the probe GEMM,
        the norm) read a 165K x 256 block four times and cost ~0.5 s a block at 163K.
        """
        self._check_writable()
        F_block = np.ascontiguousarray(F_block)
        if F_block.ndim != 2 or F_block.shape != (self.n, stop - start):
            raise ValueError(f"a block of columns {start}:{stop} must be ({self.n}, {stop - start}); got {F_block.shape}")
        rho64 = np.ascontiguousarray(np.asarray(rows_rho).reshape(self.n), dtype=np.float64)
        omega_t = np.ascontiguousarray(self._omega[start:stop].T)
        chunks = max(1, min(numba.get_num_threads(), self.n // 1024))
        col_parts = np.zeros((chunks, stop - start))
        g2_parts = np.zeros(chunks)
        want_g = G is not None
        _block_pass(F_block, rho64.astype(F_block.dtype), rho64, omega_t, self.row_sums, self.sketch, G if want_g else F_block[:0],
                    want_g, col_parts, g2_parts)
        self.col_sums[start:stop] = col_parts.sum(axis=0)
        if self.samples is not None:
            self.samples.record(start, stop, F_block, exact_rows)
        return float(g2_parts.sum())

    def state(self) -> dict:
        """Arrays and numbers that :meth:`from_state` rebuilds this from (checkpoints, .hfr files)."""
        out = {"row_sums": self.row_sums, "col_sums": self.col_sums, "sketch": self.sketch,
               "probes": self.probes, "seed": self.seed}
        if self.weights is not None:
            out["weights"] = self.weights
        if self.samples is not None:
            out.update(self.samples.state())
        if self.far_field is not None:
            out.update(self.far_field.state())
        return out

    def frozen(self, factor_bytes: float | None = None) -> "PassStatistics":
        """A shallow copy whose arrays are read-only views (what a factorization holds, no copy of data).

        The error figures are computed from these sums and sketch; the copy
        refuses :meth:`add` (``ValueError``), while ``self`` stays writable.
        ``factor_bytes``: the factors' size; the sampled rows are then trimmed to at most
        ``SAMPLE_SHARE`` (10%) of it (:meth:`SampledRows.trimmed`).
        """
        out = copy.copy(self)
        for name in ("row_sums", "col_sums", "sketch", "weights", "_omega"):
            value = getattr(self, name)
            if value is not None:
                setattr(out, name, read_only(value))
        if self.samples is not None and factor_bytes is not None:
            out.samples = self.samples.trimmed(SAMPLE_SHARE * factor_bytes)
        return out

    @classmethod
    def from_state(cls, state: dict) -> "PassStatistics":
        sketch = np.asarray(state["sketch"], dtype=np.float64)
        stats = cls(sketch.shape[0], state.get("weights"), probes=int(state["probes"]), seed=int(state["seed"]))
        stats.samples = SampledRows.from_state(state, stats.weights) if "sample_rows" in state else None
        stats.row_sums = np.asarray(state["row_sums"], dtype=np.float64)
        stats.col_sums = np.asarray(state["col_sums"], dtype=np.float64)
        stats.sketch = sketch
        if "far_q" in state:
            stats.far_field = FarFieldCertificate.from_state(state, stats.n)
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
        if self.far_field is not None:
            # the sketch saw the sampled far field's G~, not G: add ||G - G~||_F (its upper figure from
            # exact rows; channel c scales rows by D_c <= 1)
            out += self.far_field.frobenius()[1]
        return out

    def contraction(self, reflectance_int: np.ndarray) -> np.ndarray:
        """(3,) upper bound on ``||R_c F||`` in this norm (:func:`~hfrad.solve.bounds.contraction_bound`)."""
        return contraction_bound(reflectance_int, self.row_sums, self.col_sums, weighted=self.weights is not None)

    def reflection_gain(self, reflectance_int: np.ndarray) -> np.ndarray:
        """(3,) upper bound on ``||(I - R_c F)^{-1} R_c F||`` in this norm
        (:func:`~hfrad.solve.bounds.reflection_gain_bound`; with the sampled rows' power step, the
        sharper spectral bound of :meth:`~hfrad.solve.samples.SampledRows.spectral_bound`)."""
        weighted = self.weights is not None
        spectral = None if (self.samples is None or not weighted) else \
            self.samples.spectral_bound(reflectance_int, self.row_sums)
        return reflection_gain_bound(reflectance_int, self.row_sums, self.col_sums, weighted=weighted,
                                     spectral=spectral)

    @property
    def norm(self) -> str:
        """``"area"`` when the patch areas weight the norm, else ``"2"``."""
        return "area" if self.weights is not None else "2"
