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

__all__ = ["NearFieldSplit", "near_radius", "DEFAULT_NEAR_ENTRIES"]

#: Neighbours per row the default radius aims at (centroids within the radius, the patch
#: itself and coplanar neighbours, whose F is 0, included: ~100-130 nonzero entries per row
#: on the Cornell box). Measured there (HF rank and area-weighted radiosity error vs the
#: exact solve; plain -> split at 300): 2K patches eps 0.05: 591 -> 60, 0.75% -> 0.86%;
#: eps 0.02: 740 -> 432, 0.24% -> 0.13%; 5K eps 0.05: 1,081 -> 195, 0.83% -> 0.55%;
#: eps 0.02: 1,362 -> 1,307, 0.19% -> 0.10%. 64 entries only halved the rank at eps 0.05,
#: and 1,200 cut it further at eps 0.02 but SuperLU's fill made the sparse LU 170 s at 20K
#: (300: 2.3 s, ~650 LU entries per row from 5K to 20K).
DEFAULT_NEAR_ENTRIES = 300

_SAMPLE = 2048  # centroids sampled to pick the radius (deterministic: evenly spaced)


def near_radius(centroids: np.ndarray, entries: int = DEFAULT_NEAR_ENTRIES) -> float:
    """Centroid distance within which a patch has about ``entries`` neighbours (median).

    Parameters
    ----------
    centroids : (n, 3) float, metres
    entries : int
        Target neighbours per row of N (including the patch itself).

    Returns
    -------
    float, metres
    """
    c = np.asarray(centroids, np.float64)
    n = len(c)
    if n < 2 or entries < 2:
        return 0.0
    k = min(int(entries), n)
    sample = c[np.unique(np.linspace(0, n - 1, min(n, _SAMPLE)).astype(np.int64))]
    dist, _ = cKDTree(c).query(sample, k=k)
    return float(np.median(dist[:, -1]))


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
    """

    def __init__(self, centroids: np.ndarray, radius: float) -> None:
        self.centroids = np.ascontiguousarray(centroids, np.float64)
        self.radius = float(radius)
        self.n = len(self.centroids)
        self._tree = cKDTree(self.centroids)
        self.rows: list[np.ndarray] = []
        self.cols: list[np.ndarray] = []
        self.values: list[np.ndarray] = []

    def split(self, block: np.ndarray, start: int) -> np.ndarray:
        """Move the near entries of ``block`` (= G[:, start:start + b]) out; zeroes them in place.

        Returns ``block`` (now ``G - N`` on those columns).
        """
        b = block.shape[1]
        lists = self._tree.query_ball_point(self.centroids[start:start + b], self.radius)
        counts = np.fromiter((len(x) for x in lists), np.int64, count=b)
        r = np.fromiter((i for x in lists for i in x), np.int64, count=int(counts.sum()))
        c = np.repeat(np.arange(b, dtype=np.int64), counts)
        v = block[r, c]
        keep = v != 0
        self.rows.append(r[keep])
        self.cols.append(c[keep] + start)
        self.values.append(v[keep].astype(np.float64))
        block[r, c] = 0
        return block

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
