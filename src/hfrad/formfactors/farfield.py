"""The far field from sampled form factors: column blocks of F from a small share of the pairs.

Column block j of F (the Z-order range ``C_j`` of b patches) is split by its rows:

- **near rows**: the row leaves (Z-order ranges of b patches, as the column blocks)
  that are not well separated from ``C_j``, ``dist(box_R, box_C) < eta max(diam_R, diam_C)``
  (or closer than the near-field split's radius): every pair computed, as in the exact pass;
- **far rows**: the rest. Seen from a far patch x, ``F(x, y)`` varies smoothly over the
  compact cluster ``C_j`` (distance, angles and visibility change little across it), so the
  far part has a low rank in its columns: an interpolative decomposition

      F[far, C_j] ~ F[far, S] X        (S: s skeleton columns of C_j, X: s x b)

  whose skeleton comes from a pivoted QR of a few sampled far rows, checked on other,
  held-out far rows. Where the check fails (a shadow edge across the cluster, a contact)
  the sample grows and the skeleton with it; a block that does not compress is computed
  exactly. Only ``F[far, S]`` and the sampled rows are evaluated.

The tolerance of each block's far part is a share (``FarFieldOptions.share``) of the
HF tolerance, relative to the group's norm (its exact rows', and its far rows' estimated
from the sampled rows), so the far field adds about that share of eps to the
factorization's error. What the
sample rows promise is checked afterwards by exact rows of a separate certification
sample (:class:`FarFieldCertificate`): the error figure of the operator without the full pass.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import Iterator

import numpy as np
import scipy.linalg as sla

from ..errors import InputError
from ..progress import ProgressCallback, report
from ..resources import blas_threads
from .certify import upper_margin as _upper_margin
from .clustervis import BLOCKED, CLUSTER_SIZE, MIXED, VISIBLE
from .engine import FormFactorEngine
from .pieces import BlockPieces

__all__ = ["FarFieldOptions", "FarFieldStats", "FarFieldCertificate", "SampledFarField", "patch_boxes",
           "near_leaves", "near_rows", "skeleton", "sampled_column_blocks", "FAR_FIELD_CHOICES",
           "CERTIFICATE_FAILURE"]

#: A column group is halved while its box's diagonal exceeds this many times the square root of its
#: area (a flat square has ~1.4, an L across a corner ~2) ...
GROUP_SPREAD = 3.0
#: ... and it has at least twice this many patches.
MIN_GROUP = 16
#: Rays from a far row's patch to patches of a column cluster where the cluster-pair test is not
#: conclusive (one to each of PROBES patches spread along the cluster).
PROBES = 6
#: The values of ``far_field`` (``hfrad.factorize``, ``hfrad precompute --far-field``).
FAR_FIELD_CHOICES = ("exact", "sampled", "hierarchical", "auto")
#: The certificate's stated failure probability: its upper figure is below ``||G - G~||`` about
#: this often (benchmarks/README.md, "A dependable certificate", counts redraws).
CERTIFICATE_FAILURE = 0.025
#: Share of a certification draw spread evenly over a group's clean rows (the rest follows the
#: predictor): a defensive mixture, so that ``e / pi`` is at most ``N / DEFENSIVE`` times a row's
#: error where the predictor misses it.
DEFENSIVE = 0.3
#: Rows whose view of a column cluster the probe rays decided weigh this much more in the draw.
PROBED_WEIGHT = 4.0


@dataclass(frozen=True)
class FarFieldOptions:
    """How the sampled far field is built (defaults for a first run).

    Attributes
    ----------
    eta : float
        Admissibility: a row leaf is far from a column block when the gap between their
        boxes is at least ``eta`` times the larger box's diagonal.
    share : float in (0, 1)
        Each block's far part may be off by ``share * eps`` of the block's norm (Frobenius).
    rows : int
        Far rows sampled first to choose the skeleton (as many again are held out to check it).
    rounds : int
        Times a block's sample may double after a failed check before the block is computed exactly.
    max_skeleton_share : float
        A block whose skeleton would take more than this share of its columns is computed exactly.
    certify_rows : int or None
        Slots of the certification sample (:class:`FarFieldCertificate`): exact rows, never seen
        by the decomposition, drawn afresh in each column group; a block costs this many exact
        rows. None: ``2 sqrt(n)``, at least 256 (2,000 at a million patches: 0.2% of the pairs).
    holdout_rows : int
        Slots of a second, independent sample that checks the certificate (benchmarks; 0: none).
    seed : int
    """

    eta: float = 1.0
    share: float = 0.2
    rows: int = 96
    rounds: int = 3
    max_skeleton_share: float = 0.4
    certify_rows: int | None = None
    holdout_rows: int = 0
    seed: int = 43

    def __post_init__(self) -> None:
        if not (self.eta > 0 and math.isfinite(self.eta)):
            raise InputError(f"eta must be a positive number; got {self.eta!r}")
        if not (0.0 < self.share < 1.0):
            raise InputError(f"share must be in (0, 1); got {self.share!r}")
        if int(self.rows) != self.rows or self.rows < 8:
            raise InputError(f"rows must be an integer >= 8; got {self.rows!r}")
        if int(self.rounds) != self.rounds or self.rounds < 0:
            raise InputError(f"rounds must be an integer >= 0; got {self.rounds!r}")
        if not (0.0 < self.max_skeleton_share <= 1.0):
            raise InputError(f"max_skeleton_share must be in (0, 1]; got {self.max_skeleton_share!r}")
        if self.certify_rows is not None and (int(self.certify_rows) != self.certify_rows or self.certify_rows < 2):
            raise InputError(f"certify_rows must be an integer >= 2; got {self.certify_rows!r}")
        if int(self.holdout_rows) != self.holdout_rows or self.holdout_rows < 0 or self.holdout_rows == 1:
            raise InputError(f"holdout_rows must be 0 or an integer >= 2; got {self.holdout_rows!r}")


@dataclass
class FarFieldStats:
    """What the sampled far field did (kept in the factorization's ``info['far_field']``)."""

    pairs: int = 0                 # form factors evaluated, with visibility or not
    traced_pairs: int = 0          # ... with visibility (rays where needed)
    kernel_pairs: int = 0          # ... unoccluded only (visibility from the cluster-pair tests)
    mixed_pairs: int = 0           # far pairs computed exactly because their cluster pair is mixed
    probe_rays: int = 0            # rays that decided cluster pairs the conservative test left mixed
    near_pairs: int = 0            # ... of them in near rows
    sample_pairs: int = 0          # ... in the sampled and held-out far rows
    skeleton_pairs: int = 0        # ... in the skeleton columns
    certify_pairs: int = 0         # ... in the certification rows
    blocks: int = 0
    groups: int = 0                # compact column groups (a block has one or more)
    exact_groups: int = 0          # groups computed exactly (few far rows, or did not compress)
    refined_groups: int = 0        # groups whose sample grew after a failed check
    refinements: int = 0           # sample doublings in all
    split_groups: int = 0          # groups halved because their far rows did not compress
    piece_blocks: int = 0          # blocks handed on in pieces (dense rows + W X), not dense
    dense_rows: int = 0            # rows held densely in those blocks, summed
    skeleton: list = field(default_factory=list)   # skeleton columns of each group (0: exact)

    def __add__(self, other: "FarFieldStats") -> "FarFieldStats":
        """The tallies of two sets of blocks together (the Dask leaves', summed on the client)."""
        out = FarFieldStats(**{f.name: getattr(self, f.name) + getattr(other, f.name)
                               for f in fields(self) if f.name != "skeleton"})
        out.skeleton = list(self.skeleton) + list(other.skeleton)
        return out

    def state(self) -> dict:
        """JSON-ready counters (a Dask leaf's record); :meth:`from_state` reads them back."""
        return {f.name: (list(map(int, self.skeleton)) if f.name == "skeleton" else int(getattr(self, f.name)))
                for f in fields(self)}

    @classmethod
    def from_state(cls, state: dict) -> "FarFieldStats":
        return cls(**{f.name: state[f.name] for f in fields(cls) if f.name in state})

    def as_dict(self, n: int) -> dict:
        sk = np.asarray(self.skeleton or [0])
        return {"pairs": int(self.pairs), "pairs_share": self.pairs / max(n * n, 1),
                "traced_pairs": int(self.traced_pairs), "traced_share": self.traced_pairs / max(n * n, 1),
                "kernel_pairs": int(self.kernel_pairs), "mixed_pairs": int(self.mixed_pairs),
                "probe_rays": int(self.probe_rays),
                "near_pairs": int(self.near_pairs), "sample_pairs": int(self.sample_pairs),
                "skeleton_pairs": int(self.skeleton_pairs), "certify_pairs": int(self.certify_pairs),
                "blocks": int(self.blocks), "groups": int(self.groups), "exact_groups": int(self.exact_groups),
                "refined_groups": int(self.refined_groups), "refinements": int(self.refinements),
                "split_groups": int(self.split_groups),
                "piece_blocks": int(self.piece_blocks),
                "dense_row_share": self.dense_rows / max(self.piece_blocks * n, 1),
                "skeleton_mean": float(sk.mean()), "skeleton_max": int(sk.max())}


# -- Which rows of a column block are far ---------------------------------------------------------

def patch_boxes(scene) -> tuple[np.ndarray, np.ndarray]:
    """(n, 3) lower and upper corners of each patch's triangles (metres)."""
    tri = np.asarray(scene.triangles, np.float64)
    owner = scene.patch_of_triangle
    lo = np.full((scene.n_patches, 3), np.inf)
    hi = np.full((scene.n_patches, 3), -np.inf)
    np.minimum.at(lo, owner, tri.min(axis=1))
    np.maximum.at(hi, owner, tri.max(axis=1))
    return lo, hi


def _gap(lo: np.ndarray, hi: np.ndarray, box_lo: np.ndarray, box_hi: np.ndarray) -> np.ndarray:
    """Distance between each box ``(lo[i], hi[i])`` and one box (0 where they overlap)."""
    gap = np.maximum(np.maximum(lo - box_hi, box_lo - hi), 0.0)
    return np.sqrt((gap * gap).sum(axis=1))


def near_leaves(lo: np.ndarray, hi: np.ndarray, box, eta: float, radius: float = 0.0) -> np.ndarray:
    """(m,) bool: leaves that may hold patches near ``box`` (lower, upper corner): closer to it
    than ``eta`` times its diagonal (or ``radius``)."""
    diam = float(np.sqrt(((box[1] - box[0]) ** 2).sum()))
    return _gap(lo, hi, box[0], box[1]) < max(eta * diam, radius)


def near_rows(patch_lo: np.ndarray, patch_hi: np.ndarray, lo: np.ndarray, hi: np.ndarray, box, eta: float,
              block_size: int, radius: float = 0.0) -> np.ndarray:
    """Internal positions of the patches near a group of columns whose patches lie in ``box``, sorted.

    A patch is far when its box is at least ``eta`` times the column block's diagonal
    (and ``radius``) away from the block's box: seen from anywhere in it, the form
    factors vary smoothly across the block. Only the leaves that may hold near patches
    (:func:`near_leaves`) are tested patch by patch. ``patch_lo``/``patch_hi``: internal order.
    """
    n = patch_lo.shape[0]
    candidates = _leaf_rows(near_leaves(lo, hi, box, eta, radius), n, block_size)
    diam = float(np.sqrt(((box[1] - box[0]) ** 2).sum()))
    close = _gap(patch_lo[candidates], patch_hi[candidates], box[0], box[1]) < max(eta * diam, radius)
    return candidates[close]


def _leaf_rows(mask: np.ndarray, n: int, block_size: int) -> np.ndarray:
    """Internal row positions of the leaves in ``mask``."""
    starts = np.flatnonzero(mask) * block_size
    if starts.size == 0:
        return np.zeros(0, np.int64)
    return np.concatenate([np.arange(a, min(a + block_size, n)) for a in starts]).astype(np.int64)


def _compact(values: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(values, return_inverse=True)`` for integers in ``[0, k)``, without a sort."""
    present = np.zeros(k, bool)
    present[values] = True
    unique = np.flatnonzero(present)
    index = np.cumsum(present) - 1
    return unique, index[values]


def _first_of_each(inverse: np.ndarray, k: int) -> np.ndarray:
    """(k,) the first position holding each value 0..k-1 of ``inverse``."""
    first = np.full(k, inverse.size, np.int64)
    np.minimum.at(first, inverse, np.arange(inverse.size))
    return first


def _spread(pool: np.ndarray, m: int, rng: np.random.Generator) -> np.ndarray:
    """``m`` positions of ``pool`` (sorted) spread along it: one from each of m equal strata."""
    if m >= pool.size:
        return pool
    edges = np.linspace(0, pool.size, m + 1)
    pick = np.floor(edges[:-1] + rng.random(m) * np.diff(edges)).astype(np.int64)
    return pool[np.minimum(pick, pool.size - 1)]


# -- The skeleton of a far part ------------------------------------------------------------------

def skeleton(Gs: np.ndarray, scale2: float, tol2: float, max_rank: int):
    """Skeleton columns and interpolation of sampled rows ``Gs`` (t x b).

    The smallest s with ``scale2 * ||R22||_F^2 <= tol2`` (pivoted QR ``Gs P = Q R``; the
    sampled rows stand for ``scale2`` times as many), at most ``max_rank``.

    Returns
    -------
    (S (s,), X (s, b)) with ``Gs ~ Gs[:, S] X``, or None if it needs more than ``max_rank`` columns.
    """
    t, b = Gs.shape
    _, R, piv = sla.qr(Gs, mode="economic", pivoting=True, check_finite=False)
    r = min(t, b)
    # ||R[k:, k:]||_F^2 (the residual of the first k pivoted columns) = sum over rows i >= k of
    # ||R[i, i:]||^2, R being upper triangular
    row2 = np.square(np.triu(R[:r])).sum(axis=1)
    tail = np.zeros(r + 1)
    tail[:r] = np.cumsum(row2[::-1])[::-1]
    ok = np.flatnonzero(scale2 * tail <= tol2)
    s = int(ok[0]) if ok.size else r
    if s > max_rank:
        return None
    X = np.zeros((s, b))
    if s:
        X[:, piv[:s]] = np.eye(s)
        X[:, piv[s:]] = sla.solve_triangular(R[:s, :s], R[:s, s:], lower=False, check_finite=False)
    return piv[:s].copy(), X


# -- The certification sample ----------------------------------------------------------------------

@dataclass
class FarFieldCertificate:
    """Exact rows of F against what HF was given: ``||G - G~||`` estimated, with an upper figure.

    The norm is the area-weighted ``||A^{1/2} (G - G~) A^{-1/2}||_F`` (plain: weights None),
    squared a sum over column groups g and rows i of ``e_ig = A_i sum_{j in g} (G - G~)_ij^2 / A_j``.
    Rows computed pair by pair in a group have ``e_ig = 0`` (what HF was given is exact there);
    the group's other ("clean") rows carry the decomposition's error. Each of the ``m`` slots draws,
    in every group of every block, one clean row ``i`` with probability

        pi_i = DEFENSIVE / N_g + (1 - DEFENSIVE) p_i / sum p,   p_i = rho_i sqrt(A_i) ||F[i, S]||

    (``p_i`` PROBED_WEIGHT times more where probe rays decided the row's visibility: the errors
    sit there and grow with the row's weight on the skeleton columns; the uniform share bounds
    ``e / pi`` where the predictor misses, :func:`_draw_probabilities`), and adds
    ``e_ig / pi_i`` (Horvitz-Thompson): each slot's total ``y_k`` is an unbiased estimate of
    ``||G - G~||^2``, independent of the other slots, and a sum over every group of every block
    (a new draw each), so a row that is bad in many blocks is not missed in all of them at once.
    The draw of a group is seeded by ``(seed, stream, block)`` and made before its exact rows are
    computed, from what the decomposition kept (never from the exact values).

    Attributes
    ----------
    index : (m,) int
        The slots (in files of the systematic certificate, before issue 43's fifth stop: its patches).
    q : (m,) float
        ``y_k / n``: then ``n mean(q)`` estimates ``||G - G~||^2`` both for these slots and for a
        systematic sample's per-row sums of files written before.
    n : int
    seed, stream : int
        The draws' seed (:attr:`FarFieldOptions.seed`) and stream (1: the certificate, 2: the held-out check).
    """

    index: np.ndarray
    q: np.ndarray
    n: int
    seed: int = 43
    stream: int = 1

    @classmethod
    def design(cls, n: int, m: int, seed: int, stream: int = 1) -> "FarFieldCertificate":
        m = max(min(int(m), n), 2)       # slots, not patches: two at least, for a variance
        return cls(np.arange(m, dtype=np.int64), np.zeros(m), n, int(seed), int(stream))

    def draw(self, block: int, parts: list, row_scale: np.ndarray) -> list:
        """``(offset, part, pick (m,), pi (m,))`` for every group of ``parts`` with clean rows:
        ``part.clean[pick]`` the rows drawn (one a slot), ``pi`` their probabilities. ``parts``:
        ``(column offset, _GroupPart)`` of one block, before any certification row is evaluated;
        ``row_scale``: (n,) ``rho^2 A``."""
        rng = np.random.default_rng([self.seed, self.stream, int(block)])
        out = []
        for offset, p in parts:
            if p.X is None or p.clean.size == 0:
                continue
            cdf = np.cumsum(_draw_probabilities(p, row_scale))
            pick = np.minimum(np.searchsorted(cdf, rng.random(self.q.size) * cdf[-1], side="right"), cdf.size - 1)
            out.append((offset, p, pick, np.diff(cdf, prepend=0.0)[pick]))
        return out

    def add_block(self, block: int, start: int, parts: list, exact, rho: np.ndarray,
                  weights: np.ndarray | None) -> None:
        """Record one column block: its groups ``parts`` (``(column offset, _GroupPart)``) and
        ``exact(rows, a, c)``, the exact F at internal rows ``rows`` and the block's columns
        ``a:c`` (offsets), ``(len(rows), c - a)``. ``rho``, ``weights``: (n,) internal order."""
        scale = np.square(rho) * (1.0 if weights is None else weights)
        for offset, p, pick, pi in self.draw(block, parts, scale):
            b = p.X.shape[1]
            unique, inv = np.unique(pick, return_inverse=True)
            rows = p.clean[unique]
            d = (np.asarray(exact(rows, offset, offset + b), np.float64) - p.F_S[unique] @ p.X) * rho[rows, None]
            if weights is not None:
                d = d * np.sqrt(weights[rows, None] / weights[None, start + offset:start + offset + b])
            e = np.einsum("ij,ij->i", d, d)
            self.q += e[inv] / pi / self.n

    def frobenius(self, failure: float | None = None) -> tuple[float, float]:
        """(estimate, upper figure) of ``||G - G~||_F`` (norm as recorded).

        The upper figure is below the error with probability at most ``failure`` (default
        :data:`CERTIFICATE_FAILURE`) by Cantelli's inequality, the slots' variance taken from the
        sample (:func:`_upper_margin`).
        """
        failure = CERTIFICATE_FAILURE if failure is None else failure
        m = self.q.size
        y = self.n * np.asarray(self.q, np.float64)
        mean = float(y.mean()) if m else 0.0
        return math.sqrt(max(mean, 0.0)), math.sqrt(max(mean + _upper_margin(y, failure), 0.0))

    def state(self) -> dict:
        return {"far_index": self.index, "far_q": self.q}

    @classmethod
    def from_state(cls, state: dict, n: int, seed: int = 43, stream: int = 1) -> "FarFieldCertificate":
        return cls(np.asarray(state["far_index"], np.int64), np.asarray(state["far_q"], np.float64), n, seed, stream)


def _draw_probabilities(p: "_GroupPart", row_scale: np.ndarray) -> np.ndarray:
    """(len(p.clean),) the certification draw's probabilities over a group's clean rows: a share
    DEFENSIVE uniform, the rest proportional to the square root of the row's weight on the
    skeleton columns, PROBED_WEIGHT times more where probes decided its visibility (benchmarks/README.md,
    "A dependable certificate": the errors grow about as that root, and sit mostly in probed rows)."""
    N = p.clean.size
    pred = np.sqrt(np.einsum("ij,ij->i", p.F_S, p.F_S) * row_scale[p.clean])
    if p.probed is not None:
        pred = pred * np.where(p.probed, PROBED_WEIGHT, 1.0)
    total = float(pred.sum())
    if not (total > 0 and math.isfinite(total)):
        return np.full(N, 1.0 / N)
    return DEFENSIVE / N + (1.0 - DEFENSIVE) * pred / total


# -- The block producer -------------------------------------------------------------------------

class SampledFarField:
    """Column blocks of F (internal order) from exact near rows and interpolated far rows.

    Parameters
    ----------
    scene : Scene
    engine : FormFactorEngine
        Computes the sub-blocks that are evaluated.
    order : (n,) int
        Internal order (Z-order).
    block_size : int
    rows_rho : (n,) float
        ``rho_max`` in internal order: the far parts' tolerance is on ``G = rho F``.
    eps : float
        HF's relative tolerance; each far part may be off by ``options.share * eps`` of its block.
    weights : (n,) float or None
        Patch areas in internal order (the certificate's norm).
    exact_rows : (r,) int
        Internal positions whose exact rows a caller wants beside each block (the per-solve
        figure's sampled rows).
    near_radius : float
        Pairs closer than this are always in the near rows (the near-field split's radius).
    options : FarFieldOptions
    """

    def __init__(self, scene, engine, order, block_size: int, rows_rho, eps: float, *, weights=None,
                 exact_rows=(), near_radius: float = 0.0, options: FarFieldOptions | None = None) -> None:
        self.options = options or FarFieldOptions()
        self.engine, self.order, self.block_size = engine, np.asarray(order, np.int64), int(block_size)
        self.n = self.order.size
        self.rho = np.asarray(rows_rho, np.float64).reshape(self.n)
        self.eps, self.weights, self.near_radius = float(eps), weights, float(near_radius)
        self.exact_rows = np.asarray(exact_rows, np.int64)
        lo, hi = patch_boxes(scene)
        self.patch_lo, self.patch_hi = lo[self.order], hi[self.order]
        self.areas = np.asarray(scene.areas, np.float64)[self.order]
        starts = np.arange(0, self.n, self.block_size)
        self.lo = np.minimum.reduceat(self.patch_lo, starts, axis=0)
        self.hi = np.maximum.reduceat(self.patch_hi, starts, axis=0)
        self.fresh_tallies()
        #: Keep the last block's groups as ``last_parts`` (benchmarks/bench_far_field.py redraws the certificate)
        self.keep_parts = False
        # far rows see a column group wholly or not at all where their cluster pair says so (no
        # rays): there F is the unoccluded kernel, which the decomposition samples
        self.kernel_engine = FormFactorEngine(scene, samples=0)
        vis = getattr(engine, "visibility", None)
        self.clusters = None if vis is None else vis.cluster_pairs(scene, CLUSTER_SIZE)

    def fresh_tallies(self) -> None:
        """Start the certificate, the held-out check and the counters from zero: a Dask worker's
        producer makes one leaf's share at a time, and the client adds the shares up."""
        rows = self.options.certify_rows
        if rows is None:
            rows = max(256, int(2 * math.sqrt(self.n)))
        self.certificate = FarFieldCertificate.design(self.n, rows, self.options.seed)
        self.holdout = (FarFieldCertificate.design(self.n, self.options.holdout_rows, self.options.seed, 2)
                        if self.options.holdout_rows else None)
        self.stats = FarFieldStats()

    def close(self) -> None:
        """Release both engines (Embree scenes, threads)."""
        self.kernel_engine.close()
        self.engine.close()

    def _kernel(self, rows: np.ndarray, cols: np.ndarray, kind: str) -> np.ndarray:
        """The unoccluded F[order[rows]][:, cols] (no rays), counted under ``kind``."""
        return self._count(self.kernel_engine, rows, cols, kind, "kernel_pairs")

    def _eval(self, rows: np.ndarray, cols: np.ndarray, kind: str) -> np.ndarray:
        """F[order[rows]][:, cols] with visibility (cols already user indices), counted under ``kind``."""
        return self._count(self.engine, rows, cols, kind, "traced_pairs")

    def _count(self, engine, rows: np.ndarray, cols: np.ndarray, kind: str, how: str) -> np.ndarray:
        if rows.size == 0 or cols.size == 0:
            return np.zeros((rows.size, cols.size))
        F = engine.block(self.order[rows], cols)
        for counter in ("pairs", how, kind):
            setattr(self.stats, counter, getattr(self.stats, counter) + F.size)
        return F

    def block(self, j: int) -> tuple[BlockPieces, np.ndarray]:
        """Column block ``j`` of F (n x b, internal order, float64) in pieces (exact rows and the
        far rows' skeleton factors, never the dense block), and the exact rows at ``exact_rows``."""
        n, b0 = self.n, self.block_size
        start, stop = j * b0, min(n, (j + 1) * b0)
        cols = self.order[start:stop]
        rng = np.random.default_rng([self.options.seed, j])
        self.stats.blocks += 1
        # one BLAS thread: the pivoted QRs are small, and OpenBLAS's threads spin against the
        # kernel's and Embree's (a 96 x 256 geqp3 took 0.23 s with two, 4 ms with one)
        with blas_threads(1):
            parts = self._parts(start, stop, rng)
        pieces = _assemble_pieces(n, cols.size, parts)
        if not pieces.is_dense:
            self.stats.piece_blocks += 1
            self.stats.dense_rows += pieces.rows.size
        if self.keep_parts:     # a benchmark redraws the certificate on them (they hold n x s per group)
            self.last_parts = parts
        # the exact rows the certificate draws from the groups (never seen by the decomposition)
        for c in (self.certificate, self.holdout):
            if c is not None:
                c.add_block(j, start, parts, lambda rows, a, c: self._eval(rows, cols[a:c], "certify_pairs"),
                            self.rho, self.weights)
        # the rows a caller wants exact (the per-solve figure's): evaluated beside the block
        return pieces, self._eval(self.exact_rows, cols, "certify_pairs")

    def _parts(self, start: int, stop: int, rng) -> list:
        """``(column offset, _GroupPart)`` of every group of columns ``start:stop``.

        A group whose far rows do not compress (its checks failed ``options.rounds`` times:
        a shadow edge or a contact across it) is halved and each half tried again, down to
        ``2 MIN_GROUP`` columns, below which it is computed pair by pair: halves are smoother
        and have fewer near rows, where a whole group computed exactly costs every row.
        """
        work, parts = self._groups(start, stop), []
        while work:
            a, c, box = work.pop(0)
            part = self._group(self.order[a:c], box, rng, may_split=c - a >= 2 * MIN_GROUP)
            if part is None:
                mid = (a + c) // 2
                work[:0] = [(a, mid, self._box(a, mid)), (mid, c, self._box(mid, c))]
                self.stats.split_groups += 1
                continue
            parts.append((a - start, part))
        return parts

    def _box(self, a: int, c: int) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper corners of the patches at internal positions ``a:c``."""
        return self.patch_lo[a:c].min(axis=0), self.patch_hi[a:c].max(axis=0)

    def _groups(self, a: int, c: int) -> list:
        """Compact pieces ``(a, c, box)`` of columns ``a:c``: a Z-order range can jump across the
        scene (a box far larger than its patches), so it is halved until its diagonal is at most
        ``GROUP_SPREAD`` times the square root of its area, or it has ``MIN_GROUP`` patches."""
        lo, hi = self._box(a, c)
        diam = float(np.sqrt(((hi - lo) ** 2).sum()))
        if c - a <= 2 * MIN_GROUP or diam <= GROUP_SPREAD * math.sqrt(float(self.areas[a:c].sum())):
            return [(a, c, (lo, hi))]
        mid = (a + c) // 2
        return self._groups(a, mid) + self._groups(mid, c)

    def _group(self, cols: np.ndarray, box, rng, may_split: bool = False) -> "_GroupPart | None":
        """One column group: near rows and rows whose visibility is mixed exactly, the other far
        rows by a checked decomposition of the unoccluded kernel times their visibility.

        None where the far rows did not compress and ``may_split`` (the caller halves the group);
        else such a group is computed pair by pair."""
        opt, n = self.options, self.n
        near = near_rows(self.patch_lo, self.patch_hi, self.lo, self.hi, box, opt.eta, self.block_size,
                         self.near_radius)
        is_near = np.zeros(n, bool)
        is_near[near] = True
        far = np.flatnonzero(~is_near)
        self.stats.groups += 1
        state, inv_c, probed = self._visibility(far, cols)        # (len(far), column clusters)
        mixed = (state == MIXED).any(axis=1)
        is_near[far[mixed]] = True
        exact = np.flatnonzero(is_near)                    # near and mixed rows, sorted
        values = self._eval(exact, cols, "near_pairs")
        self.stats.mixed_pairs += int(mixed.sum()) * cols.size
        clean_pos = np.flatnonzero(~mixed)
        clean = far[clean_pos]
        seen = (state[clean_pos] == VISIBLE).astype(np.float64)

        def visible(i: np.ndarray, k: np.ndarray) -> np.ndarray:
            """0/1 visibility of clean rows ``clean[i]`` to columns ``cols[k]``."""
            return seen[np.ix_(i, inv_c[k])]

        if clean.size <= max(2 * opt.rows, cols.size):     # little to gain: every pair
            return self._exact_group(exact, values, clean, cols)
        norm2 = float(np.square(values * self.rho[exact, None]).sum())
        found = self._far_part(clean, visible, norm2, cols, rng)
        if found is None and may_split:
            return None
        if found is None:
            return self._exact_group(exact, values, clean, cols)
        S, X, F_S = found
        return _GroupPart(exact, values, clean, F_S, X, probed[clean_pos])

    def _exact_group(self, exact, values, clean, cols) -> "_GroupPart":
        """A group computed pair by pair: its clean rows evaluated too."""
        rows = np.union1d(exact, clean)
        out = np.empty((rows.size, cols.size))
        out[np.searchsorted(rows, exact)] = values
        out[np.searchsorted(rows, clean)] = self._eval(clean, cols, "near_pairs")
        self._count_exact()
        return _GroupPart(rows, out, np.zeros(0, np.int64), None, None)

    def _visibility(self, far: np.ndarray, cols: np.ndarray):
        """Visibility of each far row to each cluster of ``cols``: VISIBLE, BLOCKED or MIXED.

        The cluster-pair tests (no rays, conservative) decide where a pair of clusters is
        wholly visible or wholly blocked; where they say MIXED, ``PROBES`` rays from the row's
        patch to patches of the column cluster decide for that row (a row cluster can straddle
        a shadow edge: a floor patch under a block and its neighbour beside it). MIXED rows are
        computed exactly.

        Returns ``(state (len(far), column clusters) int8, inv_c (len(cols),), probed (len(far),)
        bool)``: column k of ``cols`` is in column cluster ``inv_c[k]``; ``probed``: rows whose
        view of some cluster the probes decided (where the certificate looks hardest).
        """
        clusters = self.clusters
        if clusters is None:   # no occluders: everything visible
            return np.full((far.size, 1), VISIBLE, np.int8), np.zeros(cols.size, np.int64), np.zeros(far.size, bool)
        cf = clusters.cluster[self.order[far]]
        cc = clusters.cluster[cols]
        ur, inv_r = _compact(cf, clusters.table.shape[0])
        uc, inv_c = _compact(cc, clusters.table.shape[0])
        # one patch of each cluster stands for it: states() works on patch pairs, through its table
        rep_r = self.order[far][_first_of_each(inv_r, ur.size)]
        rep_c = cols[_first_of_each(inv_c, uc.size)]
        state = clusters.states(rep_r, rep_c)[inv_r]              # (far rows, clusters of cols)
        r, c = np.nonzero(state == MIXED)
        probed = np.zeros(far.size, bool)
        probed[r] = True
        if r.size:   # the tests are conservative: probe rays decide, row by row
            state[r, c] = self._probed(self.order[far[r]], uc[c])
        return state, inv_c, probed

    def _probed(self, patches: np.ndarray, clusters: np.ndarray) -> np.ndarray:
        """(m,) VISIBLE, BLOCKED or MIXED: ``PROBES`` rays from each patch to patches of its
        cluster, VISIBLE or BLOCKED where all rays that face agree (VISIBLE where none faces:
        F ~ 0 there)."""
        k = PROBES
        j = self._members(clusters, k).ravel()
        i = np.repeat(patches, k)
        facing, blocked = self.engine.visibility.segments_blocked(i, j)
        facing, blocked = facing.reshape(-1, k), (blocked & facing).reshape(-1, k)
        self.stats.probe_rays += int(facing.sum())
        n_blocked, n_facing = blocked.sum(axis=1), facing.sum(axis=1)
        out = np.full(patches.size, MIXED, np.int8)
        out[n_blocked == 0] = VISIBLE
        out[(n_blocked == n_facing) & (n_facing > 0)] = BLOCKED
        return out

    def _members(self, clusters: np.ndarray, k: int) -> np.ndarray:
        """(len(clusters), k) patches of each cluster, spread along its members (repeats if fewer)."""
        if not hasattr(self, "_cluster_start"):
            self._cluster_members = np.argsort(self.clusters.cluster, kind="stable")
            self._cluster_start = np.r_[0, np.cumsum(np.bincount(self.clusters.cluster))]
        lo, hi = self._cluster_start[clusters], self._cluster_start[clusters + 1]
        pick = lo[:, None] + ((hi - lo)[:, None] * (2 * np.arange(k) + 1)) // (2 * k)
        return self._cluster_members[pick]

    def _far_part(self, rows: np.ndarray, visible, norm2: float, cols: np.ndarray, rng):
        """An interpolative decomposition of ``F[rows, cols]`` checked on held-out rows.

        ``rows``: far rows whose cluster pairs with the columns are all or nothing, so their
        F is the unoccluded kernel times ``visible(i, k)`` (0/1, ``i`` positions in ``rows``):
        no ray is cast. ``norm2``: ``||G||^2`` of the group's exact rows; the tolerance is
        relative to it plus the far rows' norm estimated from the sampled rows.

        Returns
        -------
        (S (s,), X (s, b), F_S (len(rows), s)): ``F[rows, cols] ~ F_S X``, ``F_S = F[rows, cols[S]]``;
        or None where the check failed ``options.rounds`` times (the caller computes the group).
        """
        opt, b = self.options, cols.size
        every = np.arange(b)

        def G(i: np.ndarray) -> np.ndarray:
            return self._kernel(rows[i], cols, "sample_pairs") * visible(i, every) * self.rho[rows[i], None]

        t = min(opt.rows, rows.size // 2)
        picked = np.sort(_spread(np.arange(rows.size), 2 * t, rng))
        sample, check = picked[0::2], picked[1::2]
        G_sample, G_check = G(sample), G(check)
        max_rank = int(opt.max_skeleton_share * b)
        refined = 0
        while True:
            scale = rows.size / sample.size
            # relative to the group's whole norm, as HF's eps: its exact rows' and its far rows'
            # (estimated from the sampled rows, which stand for `scale` times as many)
            tol2 = (opt.share * self.eps) ** 2 * (norm2 + scale * float(np.square(G_sample).sum()))
            found = skeleton(G_sample, scale, 0.25 * tol2, min(max_rank, sample.size // 2))
            if found is not None:
                S, X = found
                err2 = rows.size / check.size * float(np.square(G_check - G_check[:, S] @ X).sum())
                if err2 <= tol2:
                    break
            if refined >= opt.rounds or sample.size + check.size >= rows.size // 2:
                self._count_refined(refined)
                return None
            # the check failed: the held-out rows join the sample, and as many new rows are held out
            refined += 1
            sample = np.concatenate([sample, check])
            rest = np.setdiff1d(np.arange(rows.size), sample)
            check = np.sort(_spread(rest, sample.size, rng))
            G_sample = np.vstack([G_sample, G_check])
            G_check = G(check)
        self._count_refined(refined)
        F_S = self._kernel(rows, cols[S], "skeleton_pairs") * visible(np.arange(rows.size), S)
        self.stats.skeleton.append(int(S.size))
        return S, X, F_S

    def _count_exact(self) -> None:
        self.stats.exact_groups += 1
        self.stats.skeleton.append(0)

    def _count_refined(self, refined: int) -> None:
        if refined:
            self.stats.refined_groups += 1
            self.stats.refinements += refined


@dataclass
class _GroupPart:
    """What one column group gave: ``rows`` computed pair by pair (``values``: len(rows) x b_g),
    the ``clean`` rows (the rest) as ``F_S X`` (None for a group computed wholly); ``probed``
    (len(clean),): clean rows whose visibility of some column cluster the probe rays decided."""

    rows: np.ndarray
    values: np.ndarray
    clean: np.ndarray
    F_S: np.ndarray | None
    X: np.ndarray | None
    probed: np.ndarray | None = None


def _assemble_pieces(n: int, b: int, parts: list) -> BlockPieces:
    """The block's pieces from its groups ``(column offset, _GroupPart)``.

    Rows computed pair by pair in any group are held densely (in the other groups their
    values come from those groups' ``F_S X``); every other row is clean in every group, so
    it is the row of ``W X`` with ``W`` the groups' ``F_S`` side by side and ``X`` their
    interpolations, block diagonal. A group computed wholly makes every row dense.
    """
    dense_rows = np.unique(np.concatenate([p.rows for _, p in parts]))
    far = np.setdiff1d(np.arange(n, dtype=np.int64), dense_rows, assume_unique=True)
    widths = [0 if p.X is None else p.X.shape[0] for _, p in parts]
    D = np.empty((dense_rows.size, b))
    W = np.empty((far.size, sum(widths)))
    X = np.zeros((sum(widths), b))
    k = 0
    for (offset, p), s in zip(parts, widths):
        cols = slice(offset, offset + p.values.shape[1])
        D[np.searchsorted(dense_rows, p.rows), cols] = p.values
        if p.X is None:
            continue
        others = np.setdiff1d(dense_rows, p.rows, assume_unique=True)     # clean here, dense elsewhere
        D[np.searchsorted(dense_rows, others), cols] = p.F_S[np.searchsorted(p.clean, others)] @ p.X
        W[:, k:k + s] = p.F_S[np.searchsorted(p.clean, far)]
        X[k:k + s, cols] = p.X
        k += s
    return BlockPieces(n, dense_rows, D, far, W, X)


def sampled_column_blocks(producer: SampledFarField, dtype=np.float64, first_block: int = 0,
                          progress: ProgressCallback = None) -> Iterator[tuple[int, int, BlockPieces, np.ndarray]]:
    """Yield ``(start, stop, pieces, exact_rows)`` for every column block, as :func:`iter_column_blocks`
    yields ``(start, stop, block)`` (here :class:`BlockPieces`: never the dense block);
    ``exact_rows`` are the exact rows at ``producer.exact_rows``."""
    n, b = producer.n, producer.block_size
    for j in range(first_block, -(-n // b)):
        block, exact = producer.block(j)
        stop = min(n, (j + 1) * b)
        report(progress, stop, n)
        yield j * b, stop, block.astype(dtype), exact
