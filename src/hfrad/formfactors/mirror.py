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

Tiles beyond the memory band spill to a scratch file (:class:`TileScratch`):
the ``near`` nearest blocks' tiles stay in memory (each is taken soon after it
is kept), the rest of the ``band`` go to disk, so with room for them every
pair is computed once. The file holds equal slots of ``b^2 s`` bytes, reused
as tiles are taken, so it needs the peak of the spilled tiles: at most about
``n^2 s / 4`` bytes (every pair is still written and read once: about
``n^2 s / 2`` bytes of I/O). Each tile is checksummed (Fletcher-64, :func:`tile_checksum`) when written and
checked when read; a damaged tile is recomputed (or refused), never used. The
file is unlinked as soon as it is created, so it vanishes when it is closed or
the process ends, however it ends. Spilled or not, a copied tile holds the same
bytes, so F is bit for bit the one an all-in-memory band gives.
"""

from __future__ import annotations

import errno
import logging
import mmap
import os
import tempfile
import time
import zlib
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Callable

import numpy as np
from numba import njit

__all__ = ["ReciprocityMirror", "TileScratch", "ScratchDamageError", "MIRROR_LAG", "MIRROR_SHARE",
           "RUN_FRACTION", "SCRATCH_SHARE", "band_for", "band_pairs", "spill_band_for", "scratch_bytes", "slot_bytes", "mirror_bytes",
           "block_request", "computed_rows", "put_computed_rows", "full_height"]

log = logging.getLogger(__name__)

#: Block b copies rows only from blocks before b - MIRROR_LAG. Which rows is decided when b is handed
#: to a worker, but they are filled in when b comes back, in order, after every earlier block was
#: kept: so b can copy from all blocks before it, whatever is in flight. (A lag of 8 left a
#: 3,129-patch scene of 13 blocks computing 9.34M of its 9.79M pairs, both orders of 93%.)
MIRROR_LAG = 0

#: Share of the available memory that the kept tiles may take (iter_column_blocks' default).
MIRROR_SHARE = 0.25

#: Share of the scratch folder's free space the spilled tiles may take: the rest is left for the
#: output (.hfr, checkpoint) and whoever else writes there.
SCRATCH_SHARE = 0.5


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


def _peak_tiles(blocks: int, lag: int, band: int, near: int = 0) -> int:
    """Most tiles held at once when block a keeps tiles for blocks a + lag + near + 1 .. a + lag + band."""
    source = np.arange(blocks)
    peak = 0
    for a in range(blocks):         # after block a is kept: tiles of blocks <= a for blocks > a
        lo = np.maximum(a + 1, source[:a + 1] + lag + near + 1)
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


def slot_bytes(block_size: int, itemsize: int) -> int:
    """Bytes of one scratch slot: a full tile, rounded up to whole pages (each slot is advised alone)."""
    page = mmap.PAGESIZE
    return -(-block_size * block_size * itemsize // page) * page


def scratch_bytes(blocks: int, block_size: int, itemsize: int, near: int, band: int,
                  lag: int = MIRROR_LAG) -> int:
    """Bytes of the scratch file of a pass whose blocks copy from ``band`` blocks, ``near`` of them in memory.

    The peak number of spilled tiles held at once times a slot (``block_size^2 itemsize``
    rounded to pages); 0 when ``band <= near``. With every block copied from
    (``band = blocks - lag - 1``) and no memory band, about ``n^2 s / 4``.
    """
    if band <= near:
        return 0
    return _peak_tiles(blocks, lag, band, near) * slot_bytes(block_size, itemsize)


def spill_band_for(blocks: int, block_size: int, itemsize: int, near: int, disk_bytes: int,
                   lag: int = MIRROR_LAG) -> int:
    """The widest band (``>= near``) whose spilled tiles (those beyond the ``near`` memory band) fit ``disk_bytes``."""
    lo, hi = min(near, max(0, blocks - lag - 1)), max(0, blocks - lag - 1)
    while lo < hi:                  # the spilled peak grows with the band: bisect
        mid = (lo + hi + 1) // 2
        if scratch_bytes(blocks, block_size, itemsize, near, mid, lag) <= disk_bytes:
            lo = mid
        else:
            hi = mid - 1
    return lo


@njit(cache=True, nogil=True)
def _fletcher(words: np.ndarray) -> tuple[int, int]:
    # Fletcher's sums over 32-bit words, mod 2^64: any one changed word changes s1, and a moved
    # or swapped word changes s2. Five to ten times faster than zlib.crc32 on a 256 KiB tile.
    s1 = np.uint64(0)
    s2 = np.uint64(0)
    for i in range(words.size):
        s1 += np.uint64(words[i])
        s2 += s1
    return s1, s2


@njit(cache=True, nogil=True)
def _copy_transposed(out, tile, col_areas, row_areas) -> None:  # pragma: no cover (numba)
    """``out[i, j] = (col_areas[j] / row_areas[i]) tile[j, i]``: reciprocity, ``F_ij = F_ji A_j / A_i``.

    The float64 ratio times the tile's entry, rounded once to ``out``'s dtype: what NumPy's
    ``(col_areas[None, :] / row_areas[:, None]) * tile.T`` stored into ``out`` gives, without
    its two float64 temporaries.
    """
    rows, cols = out.shape
    for i in range(rows):
        area_i = row_areas[i]
        for j in range(cols):
            out[i, j] = (col_areas[j] / area_i) * np.float64(tile[j, i])


def tile_checksum(raw: np.ndarray) -> tuple[int, int]:
    """Checksum of a tile's bytes (``raw``: 1-D uint8): Fletcher-64 sums of its 32-bit words, or CRC-32."""
    if raw.size % 4:
        return (zlib.crc32(raw), 0)
    s1, s2 = _fletcher(raw.view(np.uint32))
    return (int(s1), int(s2))


#: Tiles a scratch file may have waiting for its writer thread (64 tiles of 256 x 256 float32: 16 MiB).
MAX_PENDING_WRITES = 64


class ScratchDamageError(OSError):
    """A scratch tile failed its checksum and could not be recomputed: it is never used as data."""


class TileScratch:
    """Tiles written once and read once, in equal slots of a memory-mapped scratch file.

    Parameters
    ----------
    folder : str or Path
        Where the file goes (the output's folder, ``scratch=``, or TMPDIR).
    slots : int
        Slots of the file: the peak of tiles held at once (:func:`scratch_bytes`).
    slot_bytes : int
        Bytes of a slot (a multiple of the page size).

    Raises
    ------
    hfrad.errors.WriteError
        ``folder`` is missing or not writable, or its disk has no room for the
        file (checked with statvfs, then reserved with ``posix_fallocate`` so a
        full disk cannot fault a mapped page later).

    Notes
    -----
    The file is unlinked as soon as it is open: the space comes back when
    :meth:`close` runs or the process ends (an error, Ctrl-C, a kill). Every
    tile carries its checksum (:func:`tile_checksum`). Tiles are written with
    ``pwrite`` and read through the map, which is advised away after each read,
    so they weigh on the page cache, not on this process's resident set.
    """

    def __init__(self, folder, slots: int, slot_bytes: int) -> None:
        from ..atomic import free_bytes
        from ..errors import WriteError
        from ..memory import human

        self.folder = Path(folder)
        self.slot_bytes, self.slots = int(slot_bytes), int(slots)
        size = self.slot_bytes * self.slots
        if not self.folder.is_dir():
            raise WriteError(f"scratch folder {self.folder} does not exist; create it or choose another "
                             "(scratch=, or TMPDIR)")
        free = free_bytes(self.folder)
        if size > free:
            raise WriteError(f"the reciprocity scratch file needs {human(size)} in {self.folder}, which has "
                             f"{human(free)} free; choose a folder with more room (scratch=, or TMPDIR) or "
                             "turn spilling off (scratch=False: fewer pairs copied)")
        try:
            fd, name = tempfile.mkstemp(prefix="hfrad-tiles-", suffix=".scratch", dir=self.folder)
        except OSError as exc:
            raise WriteError(f"cannot create a scratch file in {self.folder}: {exc.strerror}; choose another "
                             "folder (scratch=, or TMPDIR)") from exc
        self.path = Path(name)
        try:
            os.unlink(name)       # anonymous from now on: nothing is left behind, however the run ends
            try:
                os.posix_fallocate(fd, 0, size)
            except OSError as exc:
                if exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG):
                    raise WriteError(f"the reciprocity scratch file needs {human(size)} in {self.folder}: "
                                     f"{exc.strerror}; choose a folder with more room (scratch=, or TMPDIR)") from exc
                os.ftruncate(fd, size)     # a file system without fallocate: the statvfs check must do
            self._map = mmap.mmap(fd, size) if size else None
        except BaseException:
            os.close(fd)
            raise
        self._fd = fd
        self._free = list(range(self.slots - 1, -1, -1))      # slot 0 first: the file is used from its start
        self._index: dict = {}                                 # key -> (slot, shape, dtype, future checksum)
        # one writer thread: the pass does not wait on the disk (pwrite and the checksum release
        # the GIL); FIFO, so a slot freed and taken again is written in order
        self._writer = ThreadPoolExecutor(1, thread_name_prefix="hfrad-scratch")
        self._pending: deque = deque()
        self.written = self.read = 0                           # bytes
        self.seconds = 0.0                                     # this thread: copying, reading, checking, waiting
        self.write_seconds = 0.0                               # the writer thread: checksums and pwrite

    def _write(self, raw: np.ndarray, off: int) -> tuple[int, int]:
        t0 = time.perf_counter()
        # written with pwrite, read through the map (one page cache): a first write through the
        # map costs a page fault per page of the reserved extent, about three times pwrite's cost
        done = os.pwrite(self._fd, raw, off)
        if done != raw.size:
            from ..errors import WriteError
            raise WriteError(f"short write ({done} of {raw.size} bytes) to the reciprocity scratch file "
                             f"in {self.folder}")
        crc = tile_checksum(raw)
        self.write_seconds += time.perf_counter() - t0
        return crc

    def put(self, key, tile: np.ndarray) -> None:
        """Write a copy of ``tile`` into a free slot under ``key`` (in the background)."""
        t0 = time.perf_counter()
        while self._pending and self._pending[0].done():
            self._pending.popleft()
        if len(self._pending) >= MAX_PENDING_WRITES:          # a slow disk: wait, do not pile up copies
            self._pending.popleft().result()
        slot = self._free.pop()
        data = np.array(tile, order="C", copy=True)            # ours: the caller's block moves on
        raw = data.view(np.uint8).reshape(-1)
        future = self._writer.submit(self._write, raw, slot * self.slot_bytes)
        self._pending.append(future)
        self._index[key] = (slot, data.shape, data.dtype, future)
        self.written += raw.size
        self.seconds += time.perf_counter() - t0

    def take(self, key) -> np.ndarray | None:
        """The tile kept under ``key``, its slot freed; None when its checksum fails (damaged)."""
        t0 = time.perf_counter()
        slot, shape, dtype, future = self._index.pop(key)
        crc = future.result()                                  # written (a write error is raised here)
        off = slot * self.slot_bytes
        nbytes = int(np.prod(shape)) * dtype.itemsize
        raw = np.frombuffer(self._map, np.uint8, nbytes, off).copy()
        self._drop(off)
        self._free.append(slot)
        self.read += nbytes
        ok = tile_checksum(raw) == crc
        self.seconds += time.perf_counter() - t0
        if not ok:
            log.warning("reciprocity scratch tile %s failed its checksum", key)
            return None
        return raw.view(dtype).reshape(shape)

    def drop(self, key) -> None:
        """Free the slot of ``key`` unread."""
        self._free.append(self._index.pop(key)[0])

    def keys(self):
        return list(self._index)

    def _drop(self, off: int) -> None:
        # a slot read through the map leaves our resident set; its pages stay in the page cache
        if hasattr(self._map, "madvise"):
            self._map.madvise(mmap.MADV_DONTNEED, off, self.slot_bytes)

    def damage(self, key) -> None:
        """Flip a byte of the tile under ``key`` (tests: a disk that lies)."""
        slot, _, _, future = self._index[key]
        future.result()
        off = slot * self.slot_bytes
        os.pwrite(self._fd, bytes([os.pread(self._fd, 1, off)[0] ^ 0xFF]), off)

    def close(self) -> None:
        """Unmap and close the file: its space goes back to the disk. Safe to call twice."""
        if getattr(self, "_fd", None) is None:
            return
        self._writer.shutdown(wait=True, cancel_futures=True)
        if self._map is not None:
            self._map.close()
        os.close(self._fd)
        self._fd = None
        self._index.clear()

    def __del__(self):
        try:
            self.close()
        except Exception:    # interpreter shutdown: the process's end frees the file anyway
            pass


def band_pairs(starts, band: int, first: int = 0, lag: int = MIRROR_LAG) -> int:
    """Pairs a pass from block ``first`` copies with a band of ``band`` blocks (block boundaries ``starts``)."""
    starts = np.asarray(starts, np.int64)
    b = np.arange(first + lag + 1, len(starts) - 1)
    lo = np.maximum(first, b - lag - band)
    return int(((starts[b - lag] - starts[lo]).clip(0) * (starts[b + 1] - starts[b])).sum())


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
        :func:`band_for` sizes it for a memory budget, :func:`spill_band_for` for memory and disk.
    first : int
        The first block of this pass (resumed passes start later).
    lag : int
    near : int, optional
        Of the ``band``, the nearest blocks whose tiles stay in memory (default: all of
        them); the tiles of blocks farther than ``lag + near`` go to ``scratch``.
    scratch : TileScratch, optional
        Where the far tiles go; required when ``near < band``. The mirror closes it.
    recompute : callable (rows, cols) -> array, optional
        ``F[rows, cols]`` (slices in the internal order, float64) for a scratch tile
        that fails its checksum; without it such a tile raises :class:`ScratchDamageError`.
    """

    def __init__(self, areas, starts, *, band: int, first: int = 0, lag: int = MIRROR_LAG,
                 near: int | None = None, scratch: TileScratch | None = None,
                 recompute: Callable[[slice, slice], np.ndarray] | None = None) -> None:
        self.areas = np.asarray(areas, dtype=np.float64)
        self.starts = np.asarray(starts, dtype=np.int64)
        self.band, self.first, self.lag = int(band), int(first), int(lag)
        self.near = self.band if near is None else min(int(near), self.band)
        if self.near < self.band and scratch is None:
            raise ValueError(f"a band of {self.band} blocks with {self.near} in memory needs a scratch file")
        self.scratch, self.recompute = scratch, recompute
        self.tiles: dict[tuple[int, int], np.ndarray] = {}
        self.bytes = 0
        self.peak_bytes = 0
        self.kept = self.first   # blocks first .. kept - 1 have kept their tiles
        self.copied_pairs = 0
        self.spilled_pairs = 0   # of the copied pairs, those read back from the scratch file
        self.repaired_tiles = 0  # scratch tiles that failed their checksum and were computed again

    @property
    def n_blocks(self) -> int:
        return len(self.starts) - 1

    def copied_rows(self, b: int) -> slice:
        """The rows (internal order) block b takes from kept tiles: one contiguous range, maybe empty.

        A function of b alone (the same F with any number of processes), asked when block b
        is handed out; the blocks it copies from need only be kept by the time b is filled
        (:meth:`fill`, when b comes back: blocks come back in order).
        """
        lo = max(self.first, b - self.lag - self.band)
        hi = b - self.lag
        if hi <= lo:
            return slice(0, 0)
        return slice(int(self.starts[lo]), int(self.starts[hi]))

    def possible_pairs(self) -> int:
        """Pairs a full band would copy in this pass (blocks ``first`` on): the denominator of the share."""
        return band_pairs(self.starts, self.n_blocks, self.first, self.lag)

    def fill(self, b: int, block: np.ndarray, rows: slice) -> None:
        """Write ``rows`` (as :meth:`copied_rows` gave when b was handed out) of block b from kept tiles."""
        if rows.stop <= rows.start:
            return
        cols = slice(int(self.starts[b]), int(self.starts[b + 1]))
        first = int(np.searchsorted(self.starts, rows.start))
        last = int(np.searchsorted(self.starts, rows.stop))
        for a in range(first, last):
            lo, hi = int(self.starts[a]), int(self.starts[a + 1])
            tile = self.tiles.pop((b, a), None)                          # F[J_b, J_a]
            if tile is not None:
                self.bytes -= tile.nbytes
            else:
                tile = self.scratch.take((b, a))
                if tile is None:                  # damaged on disk: compute these rows instead
                    if self.recompute is None:
                        raise ScratchDamageError(
                            f"reciprocity scratch tile (block {b}, rows of block {a}) failed its checksum "
                            f"(file in {self.scratch.folder}); the disk returned other bytes than were "
                            "written. Rerun (a checkpoint resumes), or choose another scratch folder")
                    block[lo:hi] = self.recompute(slice(lo, hi), cols)
                    self.repaired_tiles += 1
                    continue
                self.spilled_pairs += tile.size
            _copy_transposed(block[lo:hi], tile, self.areas[cols], self.areas[lo:hi])    # F_ij = F_ji A_j / A_i
            self.copied_pairs += tile.size

    def discard(self, b: int) -> None:
        """Drop the tiles kept for block b (it came from elsewhere, e.g. a block cache)."""
        for key in [key for key in self.tiles if key[0] == b]:
            self.bytes -= self.tiles.pop(key).nbytes
        if self.scratch is not None:
            for key in [key for key in self.scratch.keys() if key[0] == b]:
                self.scratch.drop(key)

    def keep(self, a: int, block: np.ndarray) -> None:
        """Keep the tiles of block a that the next blocks will copy (``band`` of them; beyond ``near``, on disk)."""
        if a != self.kept:
            raise ValueError(f"blocks must be kept in order: expected block {self.kept}, got {a}")
        for x in range(a + self.lag + 1, min(self.n_blocks, a + self.lag + self.band + 1)):
            tile = block[self.starts[x]:self.starts[x + 1]]
            if x - a <= self.lag + self.near:
                tile = tile.copy()
                self.tiles[(x, a)] = tile
                self.bytes += tile.nbytes
            else:
                self.scratch.put((x, a), tile)
        self.peak_bytes = max(self.peak_bytes, self.bytes)
        self.kept += 1

    def close(self) -> None:
        """Drop every tile and close the scratch file (its space goes back). Safe to call twice."""
        self.tiles.clear()
        self.bytes = 0
        if self.scratch is not None:
            self.scratch.close()
