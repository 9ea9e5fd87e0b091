"""Exact rows of F kept from the single pass: the error figure of every solve (docs/method.md, section 7b).

A solve returns ``B~`` with an unknown error ``e = B~ - B = (I - R F)^{-1} r``,
``r = E - (I - R F) B~`` its residual. Two exact identities bound it::

    e = r + R F e,  so  ||e|| <= ||r|| + (1 + gain) ||R F r||

(``R F e = (I - R F)^{-1} R F r``, ``gain >= ||(I - R F)^{-1} R F||``). The residual of a
factorization is rough (its error sits on near pairs), and ``R F`` smooths, so ``||R F r||``
is small and the amplification (4-6 on a closed white box) falls on it alone.
Both norms are sums over patches, estimated from a sample of patches whose rows
are exact:

- **residual rows**: rows ``F[s, :]`` of a systematic sample of patches drawn with
  probability proportional to area along the Z-order (``r_s`` exactly);
- **smoothed rows**: for a second, smaller sample (16 patches), rows ``F[s, :]`` and
  ``(F R_c F)[s, :]`` per channel (``(R F r)_s`` exactly). The latter comes from the
  same pass by reciprocity, ``A_j F_jk = A_k F_kj``: ``(F R_c F)[s, k] = A_k (F y)_k``
  with ``y_j = F_sj rho_jc / A_j``, one small product per column block;
- **adjoint rows**: rows ``F[s, :]`` of a third sample drawn with probability proportional
  to ``1 / A`` (the dual norm's weights: an adjoint's residual piles up on small patches,
  which rows drawn by area rarely see).

Each sum gets an upper confidence figure (the estimate plus ``Z_SAMPLING`` standard
errors from successive differences, the standard variance estimate of a systematic
sample), and the rough term a further ``ROUGH_SAFETY`` factor: a sample of rows can
miss the few patches next to a small light where the residual concentrates. The residual's sum
comes from the area-drawn and the 1/A-drawn rows together (one sample from their mixture:
:meth:`SampledRows._rough_of_both`), in either norm. With at
most ``len(index)`` patches the rows are all of F's and the figure is a bound.

Relative to the reflected light ``||B - E||``, bounded from below by the largest of
``||B~ - E|| - a``, ``||R F B~|| - (1 + gain) ||R F r||`` (``B - E = R F B``; a lower
confidence figure from the residual rows) and, for ``E >= 0``, the exact first bounce
``sqrt(sum_p E_p^2 ||R F e_p||^2)`` from the norms the pass records for every column
(``bounce``), which also give a deterministic upper figure for emissions of few patches
(docs/method.md, section 7b).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from ..formfactors.pieces import SLAB_ROWS, BlockPieces, column_squares, product, rows_of

__all__ = ["SampledRows", "SolutionError", "SAMPLE_SEED", "ROUGH_SAFETY", "Z_SAMPLING",
           "FIGURE_FAILURE_PROBABILITY", "SAMPLE_SHARE", "max_residual_rows", "dual_sampling_weights"]

SAMPLE_SEED = 20162
#: Most residual rows recorded during the pass.
RESIDUAL_ROWS = 128
#: Smoothed rows: R F r is smooth, so a few estimate its norm as well as many away from a few-patch
#: emission (Cornell box, 1,508 patches, 60 draws x 20 emissions: figure / true error 1.2-16 with 32
#: rows, 1.2-16 with 8), but beside one a single row can hold most of the sum: the conference room's
#: near-field solver, 20 emitting patches, the stored draw: 10.6x the truth with 8 rows, 5.9x with 16
#: (5 redrawn samples: at most 7.9x and 7.4x). Each costs 3 n^2 multiply-adds in the pass (the
#: (F R_c F) rows: 48 columns beside the 20 probes; benchmarks/README.md, "fourth stop", for its time).
SMOOTH_ROWS = 16
#: The fewest residual rows a pass records however large n (16 x n float32: 64 MB at a million patches).
PASS_MIN_ROWS = 16
#: The fewest residual rows kept when the storage budget would leave fewer: the stated failure
#: probability is a normal approximation, which needs a sample of some size on clustered scenes (the
#: conference room, 3K patches, near field forced: 32 rows gave one figure at 0.64x the true error
#: in 20 emissions, 64 rows none below 1.2x; the rows then take ~10% of the factors and N, 2.5% of
#: the .hfr).
MIN_RESIDUAL_ROWS = 64
#: Standard errors added to each sampled sum of squares.
Z_SAMPLING = 2.0
#: Factor on the rough term's estimate (see the module's docstring).
ROUGH_SAFETY = 2.0
#: One-sided normal tail of Z_SAMPLING standard errors: the stated chance that a sampled sum is
#: above its upper figure (a normal approximation; the amplification factor itself is exact).
FIGURE_FAILURE_PROBABILITY = 0.5 * math.erfc(Z_SAMPLING / math.sqrt(2.0))
#: The first-bounce lower bound is taken this much smaller: the F it was summed from is float32, as
#: are the rows (a margin far above the rounding of either, far below the figure's own slack).
BOUNCE_ROUNDING = 1.0 - 1e-3
#: The Collatz-Wielandt spectral bound is taken this much larger: x and F x were summed from float32 F.
GAIN_ROUNDING = 1.0 + 1e-3
#: The stored rows may add at most this share to the factors' bytes (2 n k + 3 k^2 words).
SAMPLE_SHARE = 0.1


def max_residual_rows(n: int) -> int:
    """Residual rows recorded during the pass: all of them for small n, else at most
    ``RESIDUAL_ROWS`` and at most ~2e7 / n (a few hundred MB at a million patches)."""
    if n <= RESIDUAL_ROWS:
        return n
    cap = 2 ** int(math.floor(math.log2(max(2e7 / n, PASS_MIN_ROWS))))
    return int(min(RESIDUAL_ROWS, cap))


def dual_sampling_weights(areas: np.ndarray) -> np.ndarray:
    """(n,) the weights the adjoint's residual rows are drawn by, from the patch areas (n,) m^2:
    ``1 / A``, the dual norm's own weights, so that each drawn row counts ``r_p^2`` unscaled, as an
    area-drawn row does in the area norm (docs/method.md, section 7b)."""
    return 1.0 / np.asarray(areas, np.float64)


#: Arrays of files written since the adjoint's own rows (2026-12-06, fourth stop): field -> state key.
_NEWER = {"dual_bounce": "sample_dual_bounce", "gain_vector": "sample_gain_vector",
          "gain_product": "sample_gain_product"}


def _weighted_column_sums(F_block, weights: np.ndarray) -> np.ndarray:
    """(b,) ``sum_i weights_i F[i, p]`` in float64 of an array (slab by slab) or block pieces."""
    if isinstance(F_block, BlockPieces):
        out = np.asarray(F_block.dense, np.float64).T @ weights[F_block.rows]
        if F_block.far.size:
            out += (weights[F_block.far] @ np.asarray(F_block.W, np.float64)) @ np.asarray(F_block.X, np.float64)
        return out
    out = np.zeros(F_block.shape[1])
    for lo in range(0, F_block.shape[0], SLAB_ROWS):
        out += weights[lo:lo + SLAB_ROWS] @ np.asarray(F_block[lo:lo + SLAB_ROWS], np.float64)
    return out


def _systematic(weights: np.ndarray, m: int, rng: np.random.Generator) -> np.ndarray:
    """(m,) indices of a systematic sample with probability proportional to ``weights``, in order."""
    cum = np.cumsum(weights)
    positions = (np.arange(m) + rng.random()) * (cum[-1] / m)
    return np.minimum(np.searchsorted(cum, positions, side="right"), weights.size - 1).astype(np.int64)


@dataclass(frozen=True)
class SolutionError:
    """The error figure of one solve (or a batch), per colour channel; docs/method.md, section 7b.

    Attributes
    ----------
    bound : (3,) or (3, m) float
        ``||B~ - B||_A / ||B - E||_A``: the error relative to the reflected light (what the
        surfaces show); inf where the figure reaches the reflected light itself.
    absolute : (3,) or (3, m) float
        The figure for ``||B~ - B||_A`` (W/m^2 times sqrt(m^2), area norm; the 2-norm without areas).
    reflected : (3,) or (3, m) float
        ``||B~ - E||_A`` of the solution.
    kind : {"exact-rows", "sampled", "sampled-estimate"}
        "exact-rows": every row of F was kept (a bound); "sampled": from a sample of rows, with a stated
        failure probability (an adjoint solve: from its own rows, drawn by 1/A); "sampled-estimate": an
        adjoint solve from a file written before those rows, with none stated (its dual norm weighs small
        patches by 1/A, which the rows drawn by area see rarely: on the clustered conference room, 3K
        patches, 20% of redrawn samples gave a figure below the true error; benchmarks/README.md).
    failure_probability : float or None
        Stated chance that the figure is below the error ("sampled" only; None otherwise).
    rows : int
        Residual rows the figure used.
    norm : str
        ``"reflected"`` (relative to ``||B - E||`` in the area norm; ``"reflected-2"`` without areas).
    """

    bound: np.ndarray
    absolute: np.ndarray
    reflected: np.ndarray
    kind: str
    failure_probability: float | None
    rows: int
    norm: str = "reflected"

    def as_dict(self) -> dict:
        """JSON-ready fields (inf becomes None); a batch's figures are (3, m) nested lists."""
        return {"error_bound": _json_figures(self.bound), "error_norm": self.norm, "error_bound_kind": self.kind,
                "failure_probability": self.failure_probability, "error_absolute": _json_figures(self.absolute),
                "error_rows": self.rows}

    @classmethod
    def from_dict(cls, d: dict) -> "SolutionError":
        """Back from :meth:`as_dict` (a report's JSON): None figures become inf; ``reflected`` is not kept."""
        figures = (lambda v: np.array([np.inf if x is None else x for x in v], np.float64))
        return cls(bound=figures(d["error_bound"]), absolute=figures(d["error_absolute"]),
                   reflected=np.full(len(d["error_bound"]), np.nan), kind=d["error_bound_kind"],
                   failure_probability=d["failure_probability"], rows=int(d["error_rows"]), norm=d["error_norm"])


def _json_figures(a: np.ndarray) -> list:
    """Nested lists of floats, None where a figure is not finite."""
    a = np.asarray(a, np.float64)
    if a.ndim == 0:
        return float(a) if np.isfinite(a) else None
    return [_json_figures(x) for x in a]


@dataclass
class SampledRows:
    """Exact rows of F for two samples of patches, recorded during the pass (internal order).

    Attributes
    ----------
    index : (m1,) int64
        Residual rows' patches (internal order), a systematic sample proportional to area.
    smooth_index : (m2,) int64
        Smoothed rows' patches.
    dual_index : (m3,) int64
        The adjoint's residual rows: a systematic sample with probability proportional to
        :func:`dual_sampling_weights` (the dual norm's weights ``1 / A``); empty in files written
        before them and without areas (then ``index`` serves both norms).
    rows : (m1 + m2 + m3, n) float32
        ``F[index]``, ``F[smooth_index]`` then ``F[dual_index]``, filled block by block.
    products : (n, m2, 3) float64 or None
        ``U[k, s, c] = sum_j F_kj F_{smooth_s, j} rho_jc / A_j``: ``(F R_c F)[s, k] = A_k U[k, s, c]``
        (None without areas: no reciprocity to form it).
    weights : (n,) float64 or None
        Patch areas (the norm's and the sample's weights); None: plain 2-norm, uniform sample.
    reflectance : (n, 3) float64
        The reflectance ``products`` were formed with.
    exact : bool
        Every patch is a residual row (small scenes): the figure is a bound.
    seed : int
    span : (int, int) or None
        The columns recorded so far (None: none yet): a Dask leaf's state carries only those.
    bounce : (n, 3) float64 or None
        ``||R_c F e_p||^2`` in the norm (weights ``weights``) for every patch p: the first bounce of
        a unit exitance at p, exactly (``sum_i w_i rho_ic^2 F_ip^2``, column p's share of the pass);
        None in files written before them (or without reflectance).
    dual_bounce : (n,) float64 or None
        ``sum_i A_i F_ip^2`` for every patch p (column p's share of the pass): the adjoint's first
        bounce, ``||(R F)^T e_p||^2 = rho_p^2 dual_bounce_p / A_p^2`` in the dual norm (by
        reciprocity ``F_ps = A_s F_sp / A_p``), for any reflectance; None in older files.
    gain_vector, gain_product : (n,) float64 or None
        A positive ``x`` (``x_j = sum_i A_i F_ij / A_j``, the row sums by reciprocity, from column j
        alone) and ``F x``: ``max_i rho_i (F x)_i / x_i`` bounds the spectral radius of ``R F``
        (Collatz-Wielandt), one power step sharper than the largest row sum (:meth:`spectral_bound`);
        None in older files.
    """

    index: np.ndarray
    smooth_index: np.ndarray
    rows: np.ndarray
    products: np.ndarray | None
    weights: np.ndarray | None
    reflectance: np.ndarray
    exact: bool
    seed: int = SAMPLE_SEED
    span: tuple[int, int] | None = None
    bounce: np.ndarray | None = None
    dual_index: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    dual_bounce: np.ndarray | None = None
    gain_vector: np.ndarray | None = None
    gain_product: np.ndarray | None = None
    _smooth_rows: dict = field(default_factory=dict, repr=False, compare=False)

    # -- the design, and recording the pass ------------------------------------
    @classmethod
    def design(cls, n: int, weights, reflectance, *, seed: int = SAMPLE_SEED) -> "SampledRows":
        """The samples of an n-patch pass (deterministic in ``weights`` and ``seed``: both backends agree)."""
        w = None if weights is None else np.asarray(weights, np.float64)
        rho = np.zeros((n, 3)) if reflectance is None else np.asarray(reflectance, np.float64).reshape(n, 3)
        m1 = max_residual_rows(n)
        exact = m1 == n
        rng = np.random.default_rng(seed)
        sw = np.ones(n) if w is None else w
        index = np.arange(n, dtype=np.int64) if exact else _systematic(sw, m1, rng)
        m2 = min(SMOOTH_ROWS, n)
        smooth = np.arange(n, dtype=np.int64) if exact else _systematic(sw, m2, rng)
        # drawn after the others: their draws are those of files written before it
        dual = np.zeros(0, np.int64) if (exact or w is None) else _systematic(dual_sampling_weights(w), m1, rng)
        rows = np.zeros((index.size + smooth.size + dual.size, n), np.float32)
        products = None if (w is None or reflectance is None) else np.zeros((n, smooth.size, 3))
        bounce = None if reflectance is None else np.zeros((n, 3))
        extra = {} if w is None else {"dual_bounce": np.zeros(n), "gain_vector": np.zeros(n), "gain_product": np.zeros(n)}
        return cls(index, smooth, rows, products, w, rho, exact, seed, bounce=bounce, dual_index=dual, **extra)

    @property
    def row_patches(self) -> np.ndarray:
        """(m1 + m2 + m3,) the patches whose rows are recorded: ``index``, ``smooth_index``, ``dual_index``."""
        return np.concatenate([self.index, self.smooth_index, self.dual_index])

    def record(self, start: int, stop: int, F_block, exact: np.ndarray | None = None) -> None:
        """Record columns ``start:stop`` of F (all n rows, internal order; an array or
        :class:`~hfrad.formfactors.pieces.BlockPieces`).

        ``exact`` ((m1 + m2 + m3, b), the rows at :attr:`row_patches`): given where ``F_block`` is an
        approximation (the sampled far field), so the recorded rows stay exact.
        """
        every = self.row_patches
        self.rows[:, start:stop] = rows_of(F_block, every) if exact is None else exact
        self.span = (start, stop) if self.span is None else (min(self.span[0], start), max(self.span[1], stop))
        if self.products is not None:
            m1, m2 = self.index.size, self.smooth_index.size
            Fs = np.asarray(rows_of(F_block, self.smooth_index) if exact is None else exact[m1:m1 + m2],
                            np.float64)                                        # (m2, b), exact rows
            scale = self.reflectance[start:stop] / self.weights[start:stop, None]   # (b, 3) rho_jc / A_j
            Y = Fs.T[:, :, None] * scale[:, None, :]                           # (b, m2, 3)
            b = stop - start
            # in F's dtype (a float64 copy of an n x b block would cost 8 n b bytes), summed in float64
            self.products += product(F_block, Y.reshape(b, -1)).reshape(self.products.shape)
        if self.bounce is not None or self.dual_bounce is not None:
            self._column_bounce(start, stop, F_block)
        if self.gain_vector is not None:
            x = _weighted_column_sums(F_block, self.weights) / self.weights[start:stop]
            self.gain_vector[start:stop] = x
            self.gain_product += product(F_block, x[:, None].astype(np.float64))[:, 0]

    def record_operator(self, matmat, rmatmat, squares, exact: np.ndarray) -> None:
        """Record all n columns of an F known by its products (an H-matrix), as :meth:`record` would
        record them block by block: every quantity is linear in F or a column sum of its squares.

        Parameters
        ----------
        matmat, rmatmat : callable
            ``F @ X`` and ``F.T @ X`` (internal order) for X (n, l) float64, returning (n, l) float64.
        squares : callable
            ``squares(scale)``: (n, c) ``sum_i scale[i, c] F[i, p]^2`` for ``scale`` (n, c) >= 0.
        exact : (m1 + m2 + m3, n)
            The exact rows at :attr:`row_patches`.
        """
        n = self.rows.shape[1]
        self.rows[:] = exact
        self.span = (0, n)
        if self.products is not None:
            m1, m2 = self.index.size, self.smooth_index.size
            Fs = np.asarray(exact[m1:m1 + m2], np.float64)                       # (m2, n)
            Y = Fs.T[:, :, None] * (self.reflectance / self.weights[:, None])[:, None, :]
            self.products = matmat(Y.reshape(n, -1)).reshape(self.products.shape)
        if self.bounce is not None or self.dual_bounce is not None:
            self._column_bounce(0, n, None, squares)
        if self.gain_vector is not None:
            self.gain_vector = rmatmat(self.weights[:, None])[:, 0] / self.weights
            self.gain_product = matmat(self.gain_vector[:, None])[:, 0]

    def _column_bounce(self, start: int, stop: int, F_block, squares=None) -> None:
        """``bounce`` (``sum_i w_i rho_ic^2 F_ip^2``) and ``dual_bounce`` (``sum_i w_i F_ip^2``) of a column
        block, in float64, from one pass of squares over it (``squares(scale)``: the column squares of
        an operator's F instead of ``F_block``'s)."""
        w = np.ones(self.rows.shape[1]) if self.weights is None else self.weights
        scales = ([] if self.bounce is None else [self.reflectance ** 2 * w[:, None]]) + \
            ([] if self.dual_bounce is None else [w[:, None]])
        scale = np.concatenate(scales, axis=1)
        squares = column_squares(F_block, scale) if squares is None else squares(scale)   # (b, 3 or 4 or 1)
        if self.bounce is not None:
            self.bounce[start:stop] = squares[:, :3]
        if self.dual_bounce is not None:
            self.dual_bounce[start:stop] = squares[:, -1]

    # -- state (checkpoints, .hfr files, Dask parts) ----------------------------
    def state(self) -> dict:
        """Arrays for checkpoints, ``.hfr`` files and Dask parts: the rows of the recorded columns only
        (``sample_span``), so a leaf's part carries (m1 + m2 + m3) b numbers of them, not (m1 + m2 + m3) n."""
        n = self.rows.shape[1]
        lo, hi = (0, n) if self.span is None else self.span
        out = {"sample_index": self.index, "smooth_index": self.smooth_index,
               "sample_rows": self.rows if (lo, hi) == (0, n) else self.rows[:, lo:hi],
               "sample_span": np.array([lo, hi], np.int64), "sample_reflectance": self.reflectance,
               "sample_exact": int(self.exact), "sample_seed": self.seed}
        if self.dual_index.size:
            out["sample_dual_index"] = self.dual_index
        if self.products is not None:
            out["smooth_products"] = self.products
        if self.bounce is not None:
            out["sample_bounce"] = self.bounce
        for key, value in (("sample_dual_bounce", self.dual_bounce), ("sample_gain_vector", self.gain_vector),
                           ("sample_gain_product", self.gain_product)):
            if value is not None:
                out[key] = value
        return out

    @classmethod
    def from_state(cls, state: dict, weights) -> "SampledRows":
        rho = np.asarray(state["sample_reflectance"], np.float64)
        rows = np.asarray(state["sample_rows"], np.float32)
        lo, hi = (int(x) for x in state.get("sample_span", (0, rho.shape[0])))
        if rows.shape[1] != rho.shape[0]:            # a part's columns: placed among all n
            full = np.zeros((rows.shape[0], rho.shape[0]), np.float32)
            full[:, lo:hi] = rows
            rows = full
        products, bounce = state.get("smooth_products"), state.get("sample_bounce")
        dual = np.asarray(state.get("sample_dual_index", np.zeros(0)), np.int64)   # none in older files
        extra = {name: np.asarray(state[key], np.float64) for name, key in _NEWER.items() if key in state}
        return cls(np.asarray(state["sample_index"], np.int64), np.asarray(state["smooth_index"], np.int64),
                   rows, None if products is None else np.asarray(products, np.float64),
                   None if weights is None else np.asarray(weights, np.float64), rho,
                   bool(int(state["sample_exact"])), int(state["sample_seed"]), (lo, hi),
                   None if bounce is None else np.asarray(bounce, np.float64), dual, **extra)

    @staticmethod
    def add_states(a: dict, b: dict) -> dict:
        """Samples of two disjoint column ranges together: rows side by side when the ranges touch
        (HF's tree merges neighbours), else placed among all n; products add up."""
        (a_lo, a_hi), (b_lo, b_hi) = a["sample_span"], b["sample_span"]
        if b_lo == a_hi or a_lo == b_hi:
            first, second = (a, b) if b_lo == a_hi else (b, a)
            rows = np.concatenate([first["sample_rows"], second["sample_rows"]], axis=1)
        else:
            n = a["sample_reflectance"].shape[0]
            rows = np.zeros((a["sample_rows"].shape[0], n), np.float32)
            for part in (a, b):
                lo, hi = part["sample_span"]
                rows[:, lo:hi] = part["sample_rows"][:, :hi - lo] if part["sample_rows"].shape[1] != n \
                    else part["sample_rows"][:, lo:hi]
        out = {"sample_rows": rows, "sample_span": np.array([min(a_lo, b_lo), max(a_hi, b_hi)], np.int64)}
        for name in ("smooth_products", "sample_bounce", *_NEWER.values()):   # zero outside each part's columns
            if name in a and name in b:
                out[name] = a[name] + b[name]
        return out

    @property
    def nbytes(self) -> int:
        return int(self.rows.nbytes + (0 if self.products is None else self.products.size * 4)
                   + self.index.nbytes + self.smooth_index.nbytes + self.dual_index.nbytes
                   + sum(0 if x is None else x.size * 4 for x in (self.bounce, self.dual_bounce, self.gain_vector,
                                                                   self.gain_product)))

    def trimmed(self, max_bytes: float) -> "SampledRows":
        """A nested sub-sample of the residual rows within ``max_bytes`` (every 2^j-th row from a seeded
        offset: still a systematic sample), at least ``MIN_RESIDUAL_ROWS`` of them; ``self`` if it fits.
        The adjoint's rows (``dual_index``, as many as the pass's residual rows) are all kept: on the
        conference room's near-field solver (3K patches, the rows at their floor), 20 redrawn samples
        of 4 adjoint emissions gave 2.9% of the figures below the truth with 64 of them, none with 128
        (forward: 2.2% and 2.0%, so its floor stays at ``MIN_RESIDUAL_ROWS``).

        The smoothed rows are all kept (``SMOOTH_ROWS``, 5 n words each): ``R F r`` is smooth away from
        a few-patch emission but not beside it, where one row can hold hundreds of times the whole sum
        (the conference room's near-field solver, 20 emitting patches: one of 4 smoothed rows at 314x,
        the figure 16-22x the truth), and the mean of more rows lowers that row's weight.
        """
        out, j = self, 0
        m1, m2 = self.index.size, self.smooth_index.size
        while out.nbytes > max_bytes and out.index.size // 2 >= MIN_RESIDUAL_ROWS and not self.exact:
            j += 1
            step = 2 ** j
            rng = np.random.default_rng([self.seed, j])
            keep1 = np.arange(int(rng.integers(step)), m1, step)
            rows = np.concatenate([self.rows[keep1], self.rows[m1:]])
            out = replace(self, index=self.index[keep1], rows=rows, _smooth_rows={})
        return out

    # -- the figure of a solve -----------------------------------------------------
    def _smooth_products_rows(self, c: int) -> np.ndarray:
        """(m2, n) float32 ``(F R_c F)[smooth_index]`` (cached)."""
        if c not in self._smooth_rows:
            self._smooth_rows[c] = np.ascontiguousarray((self.products[:, :, c] * self.weights[:, None]).T,
                                                        np.float32)
        return self._smooth_rows[c]

    def _sum_of_squares(self, z: np.ndarray, drawn: np.ndarray, *, bound: int = 0) -> np.ndarray:
        """Estimate of ``sum_i a_i x_i^2`` from ``z_t = x_t^2 a_t / w_t`` (m, ...) of the systematic
        sample drawn with probability proportional to ``w`` (``drawn``, (n,)), plus (``bound`` +1) or
        minus (-1) ``Z_SAMPLING`` standard errors (exact with every row: then ``sum_t z_t w_t``)."""
        if self.exact:
            return np.einsum("t...,t->...", z, drawn)
        weights_total = float(drawn.sum())
        m = z.shape[0]
        total = weights_total * z.mean(axis=0)
        if bound == 0 or m < 2:
            return total if bound >= 0 else np.zeros_like(total)
        var = weights_total ** 2 * (np.diff(z, axis=0) ** 2).sum(axis=0) / (2.0 * m * (m - 1))
        return total + bound * Z_SAMPLING * np.sqrt(var)

    @staticmethod
    def _rows_times(rows: np.ndarray, X: np.ndarray, at: np.ndarray, reflectance, w, adjoint: bool) -> np.ndarray:
        """``R F X`` (forward) or ``F^T R X`` (adjoint) at the patches ``at`` (m, 3, q), from rows F[at]."""
        n, C, q = X.shape
        Y = reflectance[:, :, None] * X / w[:, None, None] if adjoint else X
        FY = (rows @ Y.reshape(n, -1).astype(np.float32)).reshape(at.size, C, q).astype(np.float64)
        return FY * (w[at, None, None] if adjoint else reflectance[at][:, :, None])

    def _smoothed_residual(self, E, B, reflectance, w, adjoint: bool) -> np.ndarray:
        """``(R F r)`` at the smoothed rows' patches (m2, 3, q), exactly:
        ``R F (E - B) + R F R F B`` (adjoint: ``F^T R F^T R = A (F R F) A^{-1} R``)."""
        T, C = self.smooth_index, B.shape[1]
        Y = reflectance[:, :, None] * B / w[:, None, None] if adjoint else B
        FRF = np.stack([self._smooth_products_rows(c) @ Y[:, c, :].astype(np.float32) for c in range(C)],
                       axis=1).astype(np.float64)
        FRF = FRF * (w[T, None, None] if adjoint else reflectance[T][:, :, None])
        m1 = self.index.size
        return self._rows_times(self.rows[m1:m1 + T.size], E - B, T, reflectance, w, adjoint) + FRF

    @staticmethod
    def _first_bounce_lower(E: np.ndarray, bounce: np.ndarray) -> np.ndarray:
        """(3, q) ``sqrt(sum_p E_p^2 ||R F e_p||^2) <= ||R F E|| <= ||B - E||`` for ``E >= 0``: every term
        of ``B - E = R F E + (R F)^2 E + ...`` and every inner product ``<R F e_p, R F e_q>`` is >= 0
        (``bounce`` (n, 3): ``||R F e_p||^2``; the adjoint's ``||(R F)^T e_p||^2`` alike)."""
        return np.sqrt(np.einsum("pcq,pc->cq", E ** 2, bounce)) * BOUNCE_ROUNDING

    def _guarded(self, absolute, E, reflected, gain, bounce) -> np.ndarray:
        """The upper figure, never above the deterministic one ``||e|| = ||(B~ - E) - (B - E)||
        <= ||B~ - E|| + (1 + gain) ||R F E||`` (``||R F E|| <= sum_p |E_p| ||R F e_p||``), and that
        one alone where the sampled figure is below the exact lower bound ``||e|| >= ||B - E|| -
        ||B~ - E||``: the factorization lost light that the sample does not see (a small emitter
        whose light lands on patches the sample missed)."""
        exact_upper = np.einsum("pcq,pc->cq", np.abs(E), np.sqrt(bounce))
        with np.errstate(invalid="ignore"):                      # no emission in a channel: 0, even with gain inf
            deterministic = reflected + np.where(exact_upper > 0, (1.0 + gain) * exact_upper, 0.0)
        contradicted = absolute < self._first_bounce_lower(E, bounce) - reflected
        return np.where(contradicted, deterministic, np.minimum(absolute, deterministic))

    def _bounce_for(self, reflectance: np.ndarray, same: bool, adjoint: bool) -> np.ndarray | None:
        """(n, 3) the exact first-bounce norms of this solve's norm, or None: forward ``||R_c F e_p||_A^2``
        (recorded with the pass's reflectance only); adjoint ``rho_pc^2 dual_bounce_p / A_p^2`` (any)."""
        if adjoint:
            if self.dual_bounce is None:
                return None
            return reflectance ** 2 * (self.dual_bounce / self.weights ** 2)[:, None]
        return self.bounce if same else None

    def spectral_bound(self, reflectance: np.ndarray, row_sums: np.ndarray) -> np.ndarray | None:
        """(3,) upper bound on the spectral radius of ``R_c F``, or None (older files).

        ``max_i rho_ic (F x)_i / x_i`` for the recorded ``x >= 0`` (Collatz-Wielandt, for ``x + delta``
        with ``delta -> 0``: where ``x_i = 0`` the ratio tends to ``rho_ic`` times the row sum, given as
        ``row_sums`` (n,)). ``reflectance`` (n, 3), internal order.

        Where ``F x > 0`` at an ``x_i = 0`` (an F without reciprocity, as an H-matrix's rows and
        columns decided apart: a column of zeros whose row is not), the limit does not hold; then
        ``x + delta`` for a few ``delta > 0`` (``F (x + delta) = F x + delta F 1`` exactly), the least.
        """
        if self.gain_vector is None or self.gain_product is None:
            return None
        x, fx = self.gain_vector, self.gain_product
        rho, rs = np.asarray(reflectance, np.float64), np.asarray(row_sums, np.float64)
        seen = x > 0
        if not (fx[~seen] > 0).any():
            ratio = rs.copy()
            ratio[seen] = fx[seen] / x[seen]
            return (rho * ratio[:, None]).max(axis=0) * GAIN_ROUNDING
        scale = float(np.median(x[seen])) if seen.any() else 1.0
        bounds = [(rho * ((fx + d * rs) / (x + d))[:, None]).max(axis=0) for d in scale * np.logspace(-6, 2, 33)]
        return np.min(bounds, axis=0) * GAIN_ROUNDING

    def _rough_of_both(self, E, B, reflectance, w, a, adjoint: bool) -> tuple[np.ndarray, int]:
        """(3, q) upper figure for ``||r||`` in the norm of weights ``a`` from the residual rows drawn by
        area and by :func:`dual_sampling_weights` together, and how many rows that is.

        The two systematic samples as one sample of ``m = m1 + m3`` draws from their mixture (the
        balance heuristic of multiple importance sampling): a draw at patch i counts ``a_i r_i^2 m /
        (m1 p1_i + m3 p3_i)`` with ``p1 = w / sum w`` and ``p3`` likewise; the estimate is their mean,
        plus ``Z_SAMPLING`` standard errors of it (their sample variance over m: the draws taken as
        independent). Each norm then sees the patches the other's weights favour: an adjoint's residual
        on small patches (1/A), a forward one's on tiny neighbours of a tiny emitter (the conference
        room's near-field solver: below the truth in 3.0% of redrawn forward figures with the area-drawn
        rows alone, 2.0% with both).
        """
        m1, m3 = self.index.size, self.dual_index.size
        m12 = m1 + self.smooth_index.size
        U = np.concatenate([self.index, self.dual_index])
        rows = np.concatenate([self.rows[:m1], self.rows[m12:]])
        r = E[U] - B[U] + self._rows_times(rows, B, U, reflectance, w, adjoint)       # exact, (m, 3, q)
        q = dual_sampling_weights(w)
        expected = m1 * w[U] / w.sum() + m3 * q[U] / q.sum()      # draws expected at each patch
        y = r ** 2 * (a[U] * (m1 + m3) / expected)[:, None, None]
        m = m1 + m3
        upper = y.mean(axis=0) + Z_SAMPLING * np.sqrt(y.var(axis=0, ddof=1) / m)
        return np.sqrt(np.maximum(upper, 0.0)), m

    def figure(self, E: np.ndarray, B: np.ndarray, reflectance: np.ndarray, gain: np.ndarray,
               *, adjoint: bool = False) -> SolutionError:
        """The error figure of solutions ``B`` (n, 3, q) of exitances ``E`` (n, 3, q), internal order.

        ``reflectance`` (n, 3), internal order: the solver's (the smoothed rows and first-bounce
        norms count only if it is the one they were formed with); ``gain`` (3,): bound on
        ``||(I - R_c F)^{-1} R_c F||`` in the norm (:func:`~hfrad.solve.bounds.reflection_gain_bound`).
        ``adjoint``: B solves ``(I - R F)^T B = E``; by reciprocity ``F^T = A F A^{-1}``, rows of
        ``F^T R x`` are ``A_s F_s (rho x / A)``, and the norm is the dual one (weights ``1 / A``),
        in which ``||(R F)^T|| = ||R F||_A``.

        Upper figure ``a >= ||e||``: ``safety * ||r|| + (1 + gain) ||R F r||`` (see the module's
        docstring). The reflected light ``||B - E||`` from below, the largest of
        ``||B~ - E|| - a``; ``||R F B~|| - (1 + gain) ||R F r||`` (``B - E = R F B`` exactly, and
        ``R F B~`` is smooth: the sample sees it well); and, for ``E >= 0``, the first bounce
        ``sqrt(sum_p E_p^2 ||R F e_p||^2)`` from the exact norms recorded in the pass (the light
        of a small emitter that the factorization lost, where the sample sees nothing).
        """
        E = np.asarray(E, np.float64)
        B = np.asarray(B, np.float64)
        n, C, q = B.shape
        w = np.ones(n) if self.weights is None else self.weights
        a = (1.0 / w) if adjoint else w                        # the norm's weights
        gain = np.asarray(gain, np.float64)[:, None]
        same = np.array_equal(reflectance, self.reflectance)
        both = self.dual_index.size > 0 and not self.exact      # rows drawn by area and by 1/A
        S, S_rows = self.index, self.rows[:self.index.size]

        def norm_of(rows_values, at, upper):
            z = rows_values ** 2 * (a[at] / w[at])[:, None, None]
            return np.sqrt(np.maximum(self._sum_of_squares(z, w, bound=upper), 0.0))

        rfb = self._rows_times(S_rows, B, S, reflectance, w, adjoint)     # R F B~ at S, exactly
        if both:
            rough, rough_rows = self._rough_of_both(E, B, reflectance, w, a, adjoint)
        else:
            rough, rough_rows = norm_of(E[S] - B[S] + rfb, S, +1), S.size   # the residual's exact rows
        with np.errstate(invalid="ignore"):
            if self.products is not None and same:
                tail = (1.0 + gain) * norm_of(self._smoothed_residual(E, B, reflectance, w, adjoint), self.smooth_index, +1)
                absolute = (1.0 if self.exact else ROUGH_SAFETY) * rough + tail
            else:                                                  # ||e|| <= (1 + gain) ||r||
                tail = gain * rough
                absolute = rough + tail
        absolute = np.where(np.isnan(absolute), np.inf, absolute)
        reflected = np.sqrt(np.einsum("i,icq->cq", a, (B - E) ** 2))
        lower = norm_of(rfb, S, -1) - tail                         # ||R F B~|| - ||R F e|| <= ||R F B||
        bounce = self._bounce_for(reflectance, same, adjoint)
        if bounce is not None:
            absolute = self._guarded(absolute, E, reflected, gain, bounce)
            lower = np.maximum(lower, self._first_bounce_lower(E, bounce))
        lower = np.maximum(lower, reflected - absolute)
        with np.errstate(divide="ignore", invalid="ignore"):
            bound = np.where(lower > 0, absolute / np.where(lower > 0, lower, 1.0), np.inf)
        bound = np.where(absolute == 0.0, 0.0, bound)
        kind = "exact-rows" if self.exact else ("sampled-estimate" if adjoint and self.weights is not None
                                                and not both else "sampled")
        return SolutionError(bound=bound, absolute=absolute, reflected=reflected, kind=kind,
                             failure_probability=FIGURE_FAILURE_PROBABILITY if kind == "sampled" else None,
                             rows=int(rough_rows), norm=("reflected" if self.weights is not None else "reflected-2"))
