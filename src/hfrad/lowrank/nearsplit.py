"""The near-field / far-field split: near pairs into a sparse N, HF of the smooth rest.

METHOD.md section 8: pairs of patches closer than a few patch sizes (corners,
neighbours on one wall) are what keeps the rank of G = diag(rho_max) F high.
Moving the entries of pairs whose centroids lie within ``radius`` of each
other into a sparse matrix N and factoring only the remainder,

    G = N + (G - N),   G - N ~= Q V^T,

gives the same error at a fraction of the rank; the solver then works around
the sparse ``I - D_c N`` (:mod:`hfrad.solve.nearfield`).

The split is decided per pair from the centroids alone (symmetric and the same
in every column block), so it streams with the blocks: :class:`NearFieldSplit`
takes each column block, moves its near entries into coordinate lists and
zeroes them in the block before HF sees it. The error is measured against the
full ``||G||_F`` (pass the block's norm before the split to ``HFStream.push``),
so ``||G - N - Q V^T||_F <= eps ||G||_F`` keeps the meaning it has without the split.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from ..formfactors.pieces import BlockPieces

__all__ = ["NearFieldSplit", "near_radius", "DEFAULT_NEAR_ENTRIES"]

#: Facing neighbours per row the default radius aims at: patches that can exchange light
#: (each in front of the other), i.e. about the nonzero entries of a row of N. Counting
#: facing patches, not all centroids, keeps nnz(N) - and SuperLU's fill - the same from
#: scene to scene (coplanar neighbours have F = 0 and count for nothing). The split moves
#: the near pairs - F's high-rank part - out of HF: HF's rank falls (most at larger eps),
#: while the sparse LU of ``I - D_c N`` grows with the fill of N, about c log c entries a
#: row for c nonzeros per row; too many entries cost more in the LU than they save in HF.
#: benchmarks/README.md ("Figures moved out of docstrings") has the measurements behind 120.
DEFAULT_NEAR_ENTRIES = 120

_SAMPLE = 2048  # centroids sampled to pick the radius (deterministic: evenly spaced)
_LOOK = 6       # nearest centroids searched per sample, times ``entries``


def near_radius(centroids: np.ndarray, entries: int = DEFAULT_NEAR_ENTRIES,
                normals: np.ndarray | None = None) -> float:
    """Centroid distance within which a patch has about ``entries`` neighbours (median).

    Parameters
    ----------
    centroids : (n, 3) float, metres
    entries : int
        Target neighbours per row of N.
    normals : (n, 3) float, optional
        Unit patch normals: then only *facing* neighbours count (each in front of
        the other: the pairs whose form factor can be nonzero), so ``entries`` is
        about the nonzeros per row of N. Without normals every centroid counts
        (the patch itself included).

    Returns
    -------
    float, metres
    """
    c = np.asarray(centroids, np.float64)
    n = len(c)
    if n < 2 or entries < 2:
        return 0.0
    pick = np.unique(np.linspace(0, n - 1, min(n, _SAMPLE)).astype(np.int64))
    tree = cKDTree(c)
    if normals is None:
        dist, _ = tree.query(c[pick], k=min(int(entries), n))
        return float(np.median(dist[:, -1]))
    nrm = np.asarray(normals, np.float64)
    dist, idx = tree.query(c[pick], k=min(_LOOK * int(entries), n))
    d = c[idx] - c[pick][:, None, :]                                   # (s, k, 3) towards the neighbour
    facing = (np.einsum("skx,sx->sk", d, nrm[pick]) > 0) & (np.einsum("skx,skx->sk", d, nrm[idx]) < 0)
    count = np.cumsum(facing, axis=1)
    # the distance at which the entries-th facing neighbour appears (the farthest searched if fewer)
    at = np.minimum((count < entries).sum(axis=1), dist.shape[1] - 1)
    return float(np.median(dist[np.arange(len(pick)), at]))


class NearFieldSplit:
    """Splits streamed column blocks of G into a sparse near part and the far rest.

    Parameters
    ----------
    centroids : (n, 3) float
        Patch centroids in the internal (row) order of the blocks.
    radius : float, metres
        Pairs with centroid distance <= radius are near.

    Attributes
    ----------
    rows, cols, values : lists of arrays
        Coordinates (internal order) and values of the near entries so far.
    moved2 : float
        Sum of the squares of the entries the last :meth:`split` moved out.
    """

    def __init__(self, centroids: np.ndarray, radius: float) -> None:
        self.centroids = np.ascontiguousarray(centroids, np.float64)
        self.radius = float(radius)
        self.n = len(self.centroids)
        self._tree = cKDTree(self.centroids)
        self.rows: list[np.ndarray] = []
        self.cols: list[np.ndarray] = []
        self.values: list[np.ndarray] = []
        self.moved2 = 0.0

    def split(self, block, start: int):
        """Move the near entries of ``block`` (= G[:, start:start + b]) out; zeroes them in place.

        ``block``: an array, or :class:`~hfrad.formfactors.pieces.BlockPieces` (its rows that
        hold near entries are then made dense first).

        Returns ``block`` (now ``G - N`` on those columns; pieces: new pieces).
        """
        b = block.shape[1]
        lists = self._tree.query_ball_point(self.centroids[start:start + b], self.radius)
        counts = np.fromiter((len(x) for x in lists), np.int64, count=b)
        r = np.fromiter((i for x in lists for i in x), np.int64, count=int(counts.sum()))
        c = np.repeat(np.arange(b, dtype=np.int64), counts)
        if isinstance(block, BlockPieces):
            pieces = block.with_dense_rows(np.unique(r))
            self._move(pieces.dense, np.searchsorted(pieces.rows, r), r, c, start)
            return pieces
        self._move(block, r, r, c, start)
        return block

    def _move(self, dense: np.ndarray, at: np.ndarray, r: np.ndarray, c: np.ndarray, start: int) -> None:
        """Move entries ``dense[at, c]`` (rows ``r`` of G) into the lists and zero them."""
        v = dense[at, c]
        keep = v != 0
        self.rows.append(r[keep])
        self.cols.append(c[keep] + start)
        moved = v[keep].astype(np.float64)
        self.values.append(moved)
        #: the squares of the entries the last :meth:`split` moved out, summed (float64)
        self.moved2 = float(np.dot(moved, moved))
        dense[at, c] = 0

    def state(self) -> dict:
        """The near entries so far as three arrays (for checkpoints)."""
        cat = (lambda xs, dt: np.concatenate(xs) if xs else np.zeros(0, dt))
        return {"near_rows": cat(self.rows, np.int64), "near_cols": cat(self.cols, np.int64),
                "near_values": cat(self.values, np.float64)}

    def restore(self, state: dict) -> None:
        """Continue from :meth:`state` (resuming an interrupted run)."""
        self.rows = [np.asarray(state["near_rows"], np.int64)]
        self.cols = [np.asarray(state["near_cols"], np.int64)]
        self.values = [np.asarray(state["near_values"], np.float64)]

    def matrix(self) -> sp.csr_matrix:
        """N (n x n) in CSR, internal order, float64."""
        s = self.state()
        return sp.csr_matrix((s["near_values"], (s["near_rows"], s["near_cols"])), shape=(self.n, self.n))
