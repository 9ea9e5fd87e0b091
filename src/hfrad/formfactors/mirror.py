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

Which rows a block copies is a function of the block alone (the ``band``
blocks before it by more than ``MIRROR_LAG``), not of the number of processes
or their timing, so a run gives the same F with any process count. Tiles live
in memory: a block keeps its tiles for the ``band`` blocks that will copy them,
and ``band`` is the widest whose peak fits ``budget_bytes`` (every earlier block
when about n^2 s / 4 bytes fit, s the dtype's itemsize: :func:`mirror_bytes`).
A band holds a tile only for ``band`` blocks, so a budget too small for all of
them still copies much: each block copies from ``band`` blocks while the peak
grows with the band more slowly than with all of them (:func:`band_for`).
A pass resumed at block ``first`` copies only from the blocks it computed.
"""

from __future__ import annotations

import numpy as np

__all__ = ["ReciprocityMirror", "MIRROR_LAG", "MIRROR_SHARE", "RUN_FRACTION", "band_for", "mirror_bytes",
           "block_request", "computed_rows", "put_computed_rows", "full_height"]

#: Block b copies rows only from blocks before b - MIRROR_LAG: those are finished when b is
#: handed to a worker (up to workers + 1 blocks are in flight), for any count up to 7 processes.
MIRROR_LAG = 8

#: Share of the available memory that the kept tiles may take (iter_column_blocks' default).
MIRROR_SHARE = 0.25


# -- block requests: the engines compute a column block without the rows a mirror fills -----------

def block_request(item) -> tuple[np.ndarray, slice]:
    """``(cols, skip)`` of an item of an engine's ``col_sets``: columns, or columns and rows to skip."""
    if isinstance(item, tuple):
        cols, skip = item
        return np.asarray(cols, np.int64), skip
    return np.asarray(item, np.int64), slice(0, 0)


def computed_rows(rows: np.ndarray, skip: slice) -> np.ndarray:
    """``rows`` without the positions ``skip`` (a contiguous range)."""
    if skip.stop <= skip.start:
        return rows
    return np.concatenate([rows[:skip.start], rows[skip.stop:]])


def put_computed_rows(out: np.ndarray, F: np.ndarray, skip: slice) -> None:
    """Write the computed rows ``F`` into the all-row block ``out``, around the positions ``skip``."""
    if skip.stop <= skip.start:
        out[:] = F
        return
    out[:skip.start] = F[:skip.start]
    out[skip.stop:] = F[skip.start:]


def full_height(F: np.ndarray, skip: slice, n: int) -> np.ndarray:
    """The block of all n rows from the computed ones (rows ``skip`` left unspecified)."""
    if skip.stop <= skip.start:
        return F
    out = np.empty((n, F.shape[1]), F.dtype)
    put_computed_rows(out, F, skip)
    return out


#: A run is refused above this share of the available memory (:func:`hfrad.memory.require`); the
#: tiles may take what the run's own estimate leaves of it.
RUN_FRACTION = 0.8


def mirror_bytes(n: int, itemsize: int, available: int | None = None, reserved: int = 0) -> int:
    """Most bytes a pass's kept tiles may take.

    MIRROR_SHARE of ``available`` (default: the memory available now), no more
    than ``RUN_FRACTION`` of it minus ``reserved`` (what the rest of the run is
    estimated to need), and never more than all the tiles of a full pass need
    (about n^2/4 values).
    """
    if available is None:
        from ..memory import available_bytes
        available = available_bytes()
    return int(max(0.0, min(1.01 * n * n * itemsize / 4, MIRROR_SHARE * available,
                            RUN_FRACTION * available - reserved)))


def _peak_tiles(blocks: int, lag: int, band: int) -> int:
    """Most tiles held at once when block a keeps tiles for blocks a + lag + 1 .. a + lag + band."""
    source = np.arange(blocks)
    peak = 0
    for a in range(blocks):         # after block a is kept: tiles of blocks <= a for blocks > a
        lo = np.maximum(a + 1, source[:a + 1] + lag + 1)
        hi = np.minimum(blocks - 1, source[:a + 1] + lag + band)
        peak = max(peak, int(np.clip(hi - lo + 1, 0, None).sum()))
    return peak


def band_for(blocks: int, block_size: int, itemsize: int, budget_bytes: int, lag: int = MIRROR_LAG) -> int:
    """The widest band (blocks copied from, per block) whose tiles fit ``budget_bytes`` at their peak."""
    tile = block_size * block_size * itemsize
    lo, hi = 0, max(0, blocks - lag - 1)
    while lo < hi:                  # the peak grows with the band: bisect
        mid = (lo + hi + 1) // 2
        if _peak_tiles(blocks, lag, mid) * tile <= budget_bytes:
            lo = mid
        else:
            hi = mid - 1
    return lo


class ReciprocityMirror:
    """Tiles of finished column blocks, and the rows of later blocks they give.

    Parameters
    ----------
    areas : (n,) float
        Patch areas in the internal (block) order.
    starts : (B + 1,) int
        Block boundaries in the internal order: block b is columns (and rows)
        ``starts[b]:starts[b + 1]``.
    band : int
        Block b copies the rows of blocks ``b - lag - band .. b - lag - 1`` (from ``first`` on);
        :func:`band_for` sizes it for a memory budget.
    first : int
        The first block of this pass (resumed passes start later).
    lag : int
    """

    def __init__(self, areas, starts, *, band: int, first: int = 0, lag: int = MIRROR_LAG) -> None:
        self.areas = np.asarray(areas, dtype=np.float64)
        self.starts = np.asarray(starts, dtype=np.int64)
        self.band, self.first, self.lag = int(band), int(first), int(lag)
        self.tiles: dict[tuple[int, int], np.ndarray] = {}
        self.bytes = 0
        self.peak_bytes = 0
        self.kept = self.first   # blocks first .. kept - 1 have kept their tiles
        self.copied_pairs = 0

    @property
    def n_blocks(self) -> int:
        return len(self.starts) - 1

    def copied_rows(self, b: int) -> slice:
        """The rows (internal order) block b takes from kept tiles: one contiguous range, maybe empty.

        Asked when block b is handed out: the blocks it copies from must have been
        kept by then (true while fewer than ``lag`` blocks are in flight).
        """
        lo = max(self.first, b - self.lag - self.band)
        hi = min(b - self.lag, self.kept)
        if hi <= lo:
            return slice(0, 0)
        return slice(int(self.starts[lo]), int(self.starts[hi]))

    def fill(self, b: int, block: np.ndarray, rows: slice) -> None:
        """Write ``rows`` (as :meth:`copied_rows` gave when b was handed out) of block b from kept tiles."""
        if rows.stop <= rows.start:
            return
        cols = slice(int(self.starts[b]), int(self.starts[b + 1]))
        first = int(np.searchsorted(self.starts, rows.start))
        last = int(np.searchsorted(self.starts, rows.stop))
        for a in range(first, last):
            lo, hi = int(self.starts[a]), int(self.starts[a + 1])
            tile = self.tiles.pop((b, a))                               # F[J_b, J_a]
            self.bytes -= tile.nbytes
            ratio = self.areas[cols][None, :] / self.areas[lo:hi, None]    # A_j / A_i
            block[lo:hi] = ratio * tile.T
            self.copied_pairs += tile.size

    def discard(self, b: int) -> None:
        """Drop the tiles kept for block b (it came from elsewhere, e.g. a block cache)."""
        for key in [key for key in self.tiles if key[0] == b]:
            self.bytes -= self.tiles.pop(key).nbytes

    def keep(self, a: int, block: np.ndarray) -> None:
        """Keep the tiles of block a that the next blocks will copy (``band`` of them)."""
        if a != self.kept:
            raise ValueError(f"blocks must be kept in order: expected block {self.kept}, got {a}")
        for x in range(a + self.lag + 1, min(self.n_blocks, a + self.lag + self.band + 1)):
            tile = block[self.starts[x]:self.starts[x + 1]].copy()
            self.tiles[(x, a)] = tile
            self.bytes += tile.nbytes
        self.peak_bytes = max(self.peak_bytes, self.bytes)
        self.kept += 1
