"""The reciprocity copy on Dask: group-pair tiles, each computed once and used by both groups.

The leaves of the Dask backend are column blocks ``F[:, J_j]`` of all n rows, so
without the copy every pair (i, j) is computed twice (in the block of column j
and, as (j, i), in the block of column i). Here consecutive blocks form groups
of ``g`` blocks (``gb`` columns, b the block size); for two groups I < J no more
than ``band`` apart, one *tile task* computes

    T_IJ = F[rows of group I, cols of group J]            (gb x gb)

and the *group leaf* of each group takes its rows from it: group J directly
(its rows I), group I by the transposed, area-scaled copy
``F[J, I] = diag(1 / A_J) T_IJ^T diag(A_I)`` (reciprocity, ``A_i F_ij = A_j F_ji``,
:mod:`hfrad.formfactors.mirror`). One output, used twice. A group leaf computes
only its own group's rows and those of groups farther than ``band`` (or of groups
a resumed run does not recompute), then runs the unchanged leaf of each of its
blocks (pass statistics, near-field split, truncated SVD: :func:`hfrad.distributed.tasks.leaf_from_block`).

Tasks: ``G`` group leaves, at most ``G band`` tiles (``G = ceil(m / g)``) and one
small selection task per leaf, so ``tiles / m`` ~ ``band / g`` extra tasks per leaf;
:func:`plan` picks ``g`` so that they stay within ``TILE_TASKS_PER_LEAF`` per leaf.

Pairs computed (:meth:`TilePlan.pairs_computed`): n^2 without the copy; with a
full band (``band = G - 1``) ``(n^2 + n c) / 2`` when ``g b`` divides n, c = b / DIAGONAL_CUTS
the diagonal tiles' cells (a group's own ``g b x g b`` tile copies its lower block pairs too:
:func:`diagonal_tile`), i.e. a share ``(1 + c / n) / 2`` (0.5008 at 163K patches, b = 256).

Bytes moved over the network: each tile travels to at most two group leaves (none
where the leaf runs on the tile's worker): at most ``2 (g b)^2 s`` per tile (s the
factors' itemsize), so at most ``2 band g b^2 s`` per leaf and ``2 s (g b)^2 #tiles``
in all, about ``n^2 s`` with a full band (each computed pair moves at most twice).
Without the copy nothing but the leaves' factors moves.

Memory per worker: a group leaf holds its tiles (at most ``2 band`` of ``(g b)^2 s``
bytes each, never more than the ``n x g b`` strip) plus one leaf
(:func:`hfrad.distributed.sizing.leaf_bytes`); tiles wait on the worker that made them
until both their group leaves ran. Submitted row by row (tiles ``(I, I+1 .. I+band)``,
then group leaf I), at most about ``band (band + 1) / 2 + workers x band`` tiles wait
at once over the cluster (:func:`resident_tiles`), ``1 / workers`` of them per worker
when Dask spreads them. :func:`tile_bytes_per_worker` adds the two; ``band`` is the
widest for which it fits the tile budget (:func:`band_for`: an option, or
``TILE_SHARE`` of the smallest worker memory limit).

Copied entries equal computed ones to rounding (float64: ~1e-16 relative; with
float32 factors one more float32 rounding, the copy scaling a float32 tile).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Tile tasks per leaf that :func:`plan` allows by default: Dask costs 1-6 ms per task at the scheduler,
#: well below a tile of b x b pairs at ~2 us each (0.13 s at b = 256), so the limit is the scheduler's
#: load (m = 645 at 163K: g = 8, 3,240 tiles). Smaller groups copy more: a group's own
#: g b x g b diagonal tile is computed whole, about 1 / G of the pairs more than half.
TILE_TASKS_PER_LEAF = 8
#: Share of the smallest worker memory limit the waiting tiles may take on one worker (as the local
#: path's MIRROR_SHARE of the available memory).
TILE_SHARE = 0.25
#: Largest tile ``(g b)^2 s`` the default group size allows (a tile task holds it in float64 too).
TILE_BYTES = 1 << 28
#: Cells per block on a group's diagonal tile (:func:`diagonal_tile`): the cell pairs below the
#: diagonal are copied. 1: a block's own b x b tile is computed whole (1 / m of the pairs); more cuts
#: copy half of it too, in more, smaller engine calls, which cost a few ms each: measured at 4K
#: patches, the diagonal blocks took ~13% of the form-factor CPU, less than those calls cost.
DIAGONAL_CUTS = 1
#: Fewest columns of a group by default: the engine's fixed cost per call (a few ms) stays small
#: beside a tile of at least 512 x 512 pairs.
MIN_GROUP_COLUMNS = 512


@dataclass(frozen=True)
class TilePlan:
    """Groups of ``group`` blocks; tiles between groups at most ``band`` apart.

    Attributes
    ----------
    n : int
        Patches (rows and columns of F).
    block_size : int
        Columns per leaf (b).
    group : int
        Blocks per group (g); group J is blocks ``J g .. J g + g - 1``.
    band : int
        Groups I < J share a tile when ``J - I <= band`` (0: no copy).
    """

    n: int
    block_size: int
    group: int
    band: int

    @property
    def blocks(self) -> int:
        return -(-self.n // self.block_size)

    @property
    def groups(self) -> int:
        return -(-self.blocks // self.group)

    def rows(self, J: int) -> slice:
        """Rows (= columns), internal order, of group J."""
        w = self.group * self.block_size
        return slice(J * w, min(self.n, (J + 1) * w))

    def group_of(self, j: int) -> int:
        return j // self.group

    def blocks_of(self, J: int) -> range:
        return range(J * self.group, min(self.blocks, (J + 1) * self.group))

    def tiles(self, needed=None) -> list[tuple[int, int]]:
        """The tiles ``(I, J)``, I < J, in submission order (row by row), between groups in ``needed``."""
        ok = (lambda K: True) if needed is None else needed.__contains__
        return [(I, J) for I in range(self.groups) if ok(I)
                for J in range(I + 1, min(self.groups, I + self.band + 1)) if ok(J)]

    def partners(self, J: int, needed=None) -> tuple[list[int], list[int]]:
        """Groups whose rows group J takes from tiles: ``(direct, copied)`` (tiles (I, J), I < J, and (J, K), K > J)."""
        ok = (lambda K: True) if needed is None else needed.__contains__
        if not ok(J):
            return [], []
        direct = [I for I in range(max(0, J - self.band), J) if ok(I)]
        copied = [K for K in range(J + 1, min(self.groups, J + self.band + 1)) if ok(K)]
        return direct, copied

    def own_rows(self, J: int, needed=None) -> np.ndarray:
        """Rows group J computes block by block: all but those of its tile partners and its own
        (the diagonal tile, :func:`diagonal_tile`)."""
        keep = np.ones(self.n, bool)
        for K in sum(self.partners(J, needed), [J]):
            keep[self.rows(K)] = False
        return np.flatnonzero(keep)

    def cells(self, J: int) -> list[tuple[int, int]]:
        """The diagonal tile's cells (positions within group J): each block cut in DIAGONAL_CUTS."""
        rows = self.rows(J)
        w, b = rows.stop - rows.start, self.block_size
        out = []
        for s in range(0, w, b):
            e = min(w, s + b)
            cuts = np.unique(np.linspace(s, e, DIAGONAL_CUTS + 1).round().astype(int))
            out += list(zip(cuts[:-1].tolist(), cuts[1:].tolist()))
        return out

    def diagonal_pairs(self, J: int) -> int:
        """Pairs of group J's diagonal tile computed: cell pairs (p, q), p <= q, i.e. ``(w^2 + sum |p|^2) / 2``."""
        sizes = np.array([hi - lo for lo, hi in self.cells(J)])
        return int((sizes.sum() ** 2 + (sizes ** 2).sum()) // 2)

    def pairs_computed(self, needed=None) -> int:
        """Pairs (i, j) whose form factor is computed (copies excluded) by the group leaves and tiles."""
        total = 0
        for J in range(self.groups):
            if needed is None or J in needed:
                cols = self.rows(J)
                total += self.own_rows(J, needed).size * (cols.stop - cols.start) + self.diagonal_pairs(J)
        for I, J in self.tiles(needed):
            r, c = self.rows(I), self.rows(J)
            total += (r.stop - r.start) * (c.stop - c.start)
        return total


def diagonal_tile(plan: TilePlan, J: int, areas: np.ndarray, compute) -> np.ndarray:
    """Group J's diagonal tile ``F[rows J, cols J]`` with its lower half copied by reciprocity.

    The tile is computed by cells (:meth:`TilePlan.cells`: blocks, each cut in DIAGONAL_CUTS):
    a block pair P < Q whole (one engine call), the cell pairs p <= q within a block; the
    other cell pairs are copied.
    ``compute(rows, cols)``: F of those internal positions (slices); ``areas``: (n,) internal order.
    """
    rows = plan.rows(J)
    g0, w, b = rows.start, rows.stop - rows.start, plan.block_size
    blocks = [(lo, min(w, lo + b)) for lo in range(0, w, b)]
    pieces = [((P, Q), blocks[P], blocks[Q]) for P in range(len(blocks)) for Q in range(P + 1, len(blocks))]
    cells = plan.cells(J)
    for P, (lo, hi) in enumerate(blocks):
        mine = [c for c in cells if lo <= c[0] < hi]
        pieces += [(None, mine[p], mine[q]) for p in range(len(mine)) for q in range(p, len(mine))]
    D = None
    for _, (rlo, rhi), (clo, chi) in pieces:
        T = compute(slice(g0 + rlo, g0 + rhi), slice(g0 + clo, g0 + chi))
        if D is None:
            D = np.empty((w, w), T.dtype)
        D[rlo:rhi, clo:chi] = T
        if (rlo, rhi) != (clo, chi):
            ratio = areas[g0 + rlo:g0 + rhi][None, :] / areas[g0 + clo:g0 + chi][:, None]   # A_i / A_j
            D[clo:chi, rlo:rhi] = ratio * T.T                                               # F_ji = A_i F_ij / A_j
    return D


def resident_tiles(groups: int, band: int, workers: int) -> int:
    """Most tiles waiting at once over the cluster when submitted row by row (see the module's Memory)."""
    band = min(band, max(0, groups - 1))
    return band * (band + 1) // 2 + workers * band


def tile_bytes_per_worker(groups: int, band: int, group_columns: int, itemsize: int, workers: int) -> int:
    """Tile bytes on one worker: its share of the waiting tiles plus one group leaf's ``2 band`` input tiles,
    ``(resident_tiles / workers + 2 band) (g b)^2 s``."""
    tile = group_columns * group_columns * itemsize
    band = min(band, max(0, groups - 1))
    return int((resident_tiles(groups, band, workers) / max(1, workers) + 2 * band) * tile)


def band_for(groups: int, group_columns: int, itemsize: int, workers: int, budget_bytes: int) -> int:
    """The widest band whose :func:`tile_bytes_per_worker` fits ``budget_bytes``."""
    band = 0
    while band < groups - 1 and \
            tile_bytes_per_worker(groups, band + 1, group_columns, itemsize, workers) <= budget_bytes:
        band += 1
    return band


def default_group(m: int, n: int, block_size: int, itemsize: int) -> int:
    """Smallest power-of-two group size of at least MIN_GROUP_COLUMNS columns with at most
    TILE_TASKS_PER_LEAF tile tasks per leaf (full band), unless the tile ``(g b)^2 s`` would then
    pass TILE_BYTES (that limit wins)."""
    g = 1
    while g < m and g * block_size < MIN_GROUP_COLUMNS:
        g *= 2
    while g < m:
        G = -(-m // g)
        if G * (G - 1) / 2 <= TILE_TASKS_PER_LEAF * m or (2 * g * block_size) ** 2 * itemsize > TILE_BYTES:
            return g
        g *= 2
    return g


def plan(n: int, block_size: int, itemsize: int, workers: int, *, group: int | None = None,
         band: int | None = None, budget_bytes: int | None = None) -> TilePlan:
    """The tiles of a run: ``group`` (default :func:`default_group`) and ``band`` (default the widest
    whose waiting tiles fit ``budget_bytes`` per worker, :func:`band_for`; None budget: no limit)."""
    m = -(-n // block_size)
    g = default_group(m, n, block_size, itemsize) if group is None else int(group)
    G = -(-m // g)
    if band is None:
        band = G - 1 if budget_bytes is None else band_for(G, g * block_size, itemsize, workers, budget_bytes)
    return TilePlan(n=int(n), block_size=int(block_size), group=g, band=int(min(max(0, band), max(0, G - 1))))


def fill_block(F: np.ndarray, plan: TilePlan, J: int, j: int, areas: np.ndarray, direct: dict, copied: dict) -> None:
    """Write the rows of block j (group J) that tiles give into the all-row block ``F`` (n x b).

    ``direct[I]`` is the tile (I, J): rows of group I, columns of group J (taken as they are);
    ``copied[K]`` the tile (J, K): rows of group J, columns of group K, giving rows K by
    ``F_ik = A_k F_ki / A_i`` (k in block j, i in group K). ``areas``: (n,) float64, internal order.
    """
    g0 = plan.rows(J).start
    lo = j * plan.block_size - g0
    hi = lo + F.shape[1]
    cols = slice(g0 + lo, g0 + hi)
    for I, T in direct.items():
        F[plan.rows(I)] = T[:, lo:hi]
    for K, T in copied.items():
        rows = plan.rows(K)
        ratio = areas[cols][None, :] / areas[rows][:, None]     # A_k / A_i
        F[rows] = ratio * T[lo:hi].T
