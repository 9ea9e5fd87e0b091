"""Rows of a column block that reciprocity already gives: ``F_ij = A_j F_ji / A_i``.

F is streamed in column blocks ``F[:, J_b]`` of every row (blocks.py), so each
pair (i, j) is computed twice: once in the block of column j and once, as
(j, i), in the block of column i. Both the kernel (symmetric quadrature) and
the visibility (rays cast in canonical order, every decision symmetric in the
pair) satisfy reciprocity ``A_i F_ij = A_j F_ji`` to rounding, so the second
computation can be a copy: block a keeps its rows of later blocks,
``F[J_x, J_a]`` (the tile (x, a)), and block x takes its rows ``J_a`` from it,

    F[J_a, J_x] = diag(1 / A_{J_a}) F[J_x, J_a]^T diag(A_{J_x}),

computing only the other rows. About half of F's pairs are then copies.

Which rows a block copies is a function of the block alone (the blocks before
it by at least ``MIRROR_LAG`` whose tiles are kept), not of the number of
processes or their timing, so a run gives the same F with any process count.
Tiles live in memory (about ``n^2 / 4`` entries at the peak of a full pass);
they are kept only while they fit ``budget_bytes``: beyond it, blocks compute
every row as before. A pass resumed at block ``first`` copies only from blocks
it computed itself.
"""

from __future__ import annotations

import numpy as np

__all__ = ["ReciprocityMirror", "MIRROR_LAG", "MIRROR_SHARE"]

#: Block b copies rows only from blocks before b - MIRROR_LAG: those are finished when b is
#: handed to a worker (up to workers + 1 blocks are in flight), for any count up to 7 processes.
MIRROR_LAG = 8

#: Share of the available memory that the kept tiles may take (iter_column_blocks' default).
MIRROR_SHARE = 0.25


class ReciprocityMirror:
    """Tiles of finished column blocks, and the rows of later blocks they give.

    Parameters
    ----------
    areas : (n,) float
        Patch areas in the internal (block) order.
    starts : (B + 1,) int
        Block boundaries in the internal order: block b is columns (and rows)
        ``starts[b]:starts[b + 1]``.
    first : int
        The first block of this pass (resumed passes start later).
    budget_bytes : int
        Most bytes the kept tiles may hold at once.
    lag : int
        Block b copies from blocks ``first .. b - lag - 1`` only.
    """

    def __init__(self, areas, starts, *, first: int = 0, budget_bytes: int, lag: int = MIRROR_LAG) -> None:
        self.areas = np.asarray(areas, dtype=np.float64)
        self.starts = np.asarray(starts, dtype=np.int64)
        self.first, self.lag = int(first), int(lag)
        self.budget_bytes = int(budget_bytes)
        self.tiles: dict[tuple[int, int], np.ndarray] = {}
        self.bytes = 0
        self.kept = self.first   # blocks first .. kept - 1 have kept all their tiles
        self.copied_pairs = 0

    @property
    def n_blocks(self) -> int:
        return len(self.starts) - 1

    def _source_blocks(self, b: int) -> range:
        return range(self.first, max(self.first, min(b - self.lag, self.kept)))

    def copied_rows(self, b: int) -> slice:
        """The rows (internal order) block b takes from kept tiles: one contiguous range, maybe empty."""
        src = self._source_blocks(b)
        if not len(src):
            return slice(0, 0)
        return slice(int(self.starts[src.start]), int(self.starts[src.stop]))

    def fill(self, b: int, block: np.ndarray, rows: slice) -> None:
        """Write ``rows`` (as :meth:`copied_rows` gave when b was handed out) of block b from kept tiles."""
        if rows.stop <= rows.start:
            return
        cols = slice(int(self.starts[b]), int(self.starts[b + 1]))
        for a in range(self.n_blocks):
            lo, hi = int(self.starts[a]), int(self.starts[a + 1])
            if hi <= rows.start or lo >= rows.stop:
                continue
            tile = self.tiles.pop((b, a))                               # F[J_b, J_a]
            self.bytes -= tile.nbytes
            ratio = self.areas[cols][None, :] / self.areas[lo:hi, None]    # A_j / A_i
            block[lo:hi] = ratio * tile.T
            self.copied_pairs += tile.size

    def keep(self, a: int, block: np.ndarray) -> None:
        """Keep the tiles of block a that later blocks will copy, if they fit the budget."""
        if a != self.kept:                 # only an unbroken run of kept blocks is usable
            return
        later = range(a + self.lag + 1, self.n_blocks)
        if not len(later):
            self.kept += 1
            return
        lo = int(self.starts[later.start])
        need = (block.shape[0] - lo) * block.shape[1] * block.itemsize
        if self.bytes + need > self.budget_bytes:
            return
        for x in later:
            self.tiles[(x, a)] = block[self.starts[x]:self.starts[x + 1]].copy()
        self.bytes += need
        self.kept += 1
