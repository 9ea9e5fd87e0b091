"""Visibility between patches: the fraction of unoccluded rays, cast with Embree.

V_ij is estimated from ``samples`` segments between fixed sample points of the
two patches: the centroids of an m x m split of each triangle (samples = m^2;
stratified and deterministic). Segment k joins point k of the lower-indexed
patch to point ``(k + samples // 2) % samples`` of the other one (a fixed
shift, so that parallel patches are not probed only by parallel rays). The
pair is put in canonical order (lower patch index first) and always cast in
that direction, so V_ij == V_ji bit for bit and reciprocity survives.

Where the first rays disagree (a partly visible pair) or the patches are close
(centroid distance below 2 (D_i + D_j), where four rays can all agree and still
be wrong), and the pair matters (F_ij or F_ji above ``refine_above``), a second
round casts ``refine_samples`` rays between a finer stratified set (4 x 4
split) and replaces the estimate: partial visibility between near patches is
where a coarse estimate's error is largest, and such pairs are few.

Before any of that, each pair that needs rays gets one probe segment, and only
pairs whose neighbouring pairs' probes disagree (shadow boundaries), close or
large pairs get all ``samples`` rays (probing.py): 43% fewer rays at 20K
Cornell patches, the same row sums.

There is no random jitter on purpose: Monte Carlo noise in F is full rank and
destroys the low rank the hierarchical factorization relies on (docs/method.md, section 2).

End points are moved off their surfaces along the patch normals by
``1e-5 x scene size`` so that a ray never hits the face it starts or ends on.
Rays are cast in coordinates relative to the centre of the scene's bounding
box: Embree works in float32, whose resolution far from the origin (site or
georeferenced coordinates: 0.06 m at 1e6 m) would swallow the offset.
Rays are cast only for pairs with a nonzero unoccluded form factor that *can*
be blocked: an occluder triangle can cut a segment only if the segment's end
points lie on opposite sides of its plane and the pair's bounding box meets the
triangle's. Per patch and occluder plane, one bit says "wholly on the front
side" and one "wholly on the back side"; a pair needs rays only if some
occluder is neither wholly in front of both patches nor wholly behind both and
its box overlaps theirs (shaft culling with planes and boxes). In a room most
pairs of wall patches need no ray at all.
"""

from __future__ import annotations

import math
import time

import numpy as np
from numba import njit, prange

from ..errors import InputError
from .kernel import points_on_triangles, split_centroids
from .probing import NEIGHBOURS, PROBE_BELOW, cuttable, full_ray_pairs, nearest_patches
from .raycast import RayCaster

#: Rays per patch pair by default (a 2 x 2 split of each triangle).
DEFAULT_SAMPLES = 4

#: Rays of the second round for partially visible pairs (a 4 x 4 split of each triangle).
REFINE_SAMPLES = 16

#: Pairs whose first rays disagree, or closer than REFINE_NEAR * (D_i + D_j) (centroid
#: distance, longest edges), get the second round if F_ij or F_ji exceeds REFINE_ABOVE.
REFINE_ABOVE = 1e-4
REFINE_NEAR = 2.0

#: Above this many occluder triangles the per-pair culling test costs more than it saves.
MAX_CULL_OCCLUDERS = 2048

#: Rays per Embree call and per temporary buffer (bounds memory: ~28 bytes a ray).
RAY_BATCH = 1 << 21

_OFFSET = 1e-5  # end point offset, times the scene size


def settings() -> dict:
    """The second-round visibility parameters, as recorded with results (.hfr files)."""
    return {"refine_samples": REFINE_SAMPLES, "refine_above": REFINE_ABOVE, "refine_near": REFINE_NEAR,
            "probe_neighbours": NEIGHBOURS, "probe_below": PROBE_BELOW}


def check_samples(samples: int) -> int:
    """Validate ``samples`` (a perfect square >= 1); returns its square root."""
    m = math.isqrt(int(samples)) if int(samples) >= 1 else 0
    if samples != int(samples) or m < 1 or m * m != int(samples):
        raise InputError(f"samples must be a perfect square (1, 4, 9, 16, ...) so the sample points "
                         f"are a stratified split of each triangle, got {samples}")
    return m


class Visibility:
    """Ray casting state for one scene: sample points, culling masks, Embree scene.

    Parameters
    ----------
    scene : Scene
        Rays are cast against ``scene.occluder_vertices`` / ``occluder_faces``.
    samples : int
        Rays per pair, a perfect square; 1 = centroid to centroid.
    cull : bool
        Skip pairs that no occluder can block (exact test, see module docstring).
    refine_samples, refine_above : int, float
        The second round for partly visible pairs (see module docstring).
    probe : bool
        One probe ray per pair first, every ray only where neighbouring pairs
        disagree (see :mod:`hfrad.formfactors.probing`); off = every ray everywhere.
    """

    def __init__(self, scene, *, samples: int = DEFAULT_SAMPLES, cull: bool = True,
                 refine_samples: int = REFINE_SAMPLES, refine_above: float = REFINE_ABOVE,
                 probe: bool = True) -> None:
        m = check_samples(samples)
        self.samples = int(samples)
        # everything below is relative to the scene's centre (float32 rays, see module docstring)
        self.centre = 0.5 * (scene.bounds[0] + scene.bounds[1]) if scene.n_patches else np.zeros(3)
        tri = np.asarray(scene.triangles, dtype=np.float64) - self.centre
        size = float(np.ptp(scene.bounds, axis=0).max()) if len(tri) else 1.0
        self.scale = size if size > 0 else 1.0
        self.offset = _OFFSET * self.scale
        pts, pts_normals = sample_points(scene, m)
        nrm = np.asarray(scene.normals, np.float64)
        self.points = np.ascontiguousarray(pts - self.centre + self.offset * pts_normals)
        # patch planes n . x = n . v0, or through the centroid of a clustered patch
        # (sample points are `offset` in front of their own triangles)
        on_plane = scene.centroids - self.centre if scene.is_clustered else tri[:, 0]
        self.plane = np.ascontiguousarray(np.column_stack([nrm, np.einsum("nd,nd->n", nrm, on_plane)
                                                           if len(tri) else np.zeros(0)]))
        self.partner = np.ascontiguousarray((np.arange(self.samples) + self.samples // 2) % self.samples,
                                            dtype=np.int64)
        # second round: a finer stratified set, only for pairs the first rays disagree on
        self.refine_samples = int(refine_samples) if refine_samples > samples else 0
        self.refine_above = float(refine_above)
        if self.refine_samples:
            fine, fine_normals = sample_points(scene, check_samples(self.refine_samples))
            self.fine_points = np.ascontiguousarray(fine - self.centre + self.offset * fine_normals)
            self.fine_partner = np.ascontiguousarray(
                (np.arange(self.refine_samples) + self.refine_samples // 2) % self.refine_samples, dtype=np.int64)
        self.rays_refined = 0
        self.refine_near = REFINE_NEAR
        self.centroids = np.ascontiguousarray(np.asarray(scene.centroids, np.float64) - self.centre)
        edges = np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).max(axis=1) if len(tri) else np.zeros(0)
        self.diameters = np.ascontiguousarray(edges)
        self.caster = RayCaster(np.asarray(scene.occluder_vertices, np.float64) - self.centre,
                                scene.occluder_faces, threads=1)
        self._setup_culling(scene, tri, cull)
        self.areas = np.ascontiguousarray(scene.areas, dtype=np.float64)
        #: Pairs with A_i F_ij (symmetric, so V_ij == V_ji still) below this get one ray, not
        #: ``samples`` (see hfrad.formfactors.parallel.one_ray_threshold); 0 = off.
        self.one_ray_below = 0.0
        self.rays_cast = 0
        self.embree_seconds = 0.0
        # one probe ray per pair first, every ray only where neighbouring pairs disagree (probing.py)
        self.rays_probe = 0
        self.probe_below = PROBE_BELOW
        self.neighbours = None
        if probe and self.samples > 1 and scene.n_patches > 1:
            self.neighbours = nearest_patches(self.centroids)  # centred: see module docstring

    def _setup_culling(self, scene, tri: np.ndarray, cull: bool) -> None:
        occ = (np.asarray(scene.occluder_vertices, np.float64) - self.centre)[np.asarray(scene.occluder_faces)]
        m = len(occ)
        self.n_occluders = m
        n = scene.n_patches
        self.cull = bool(cull) and 0 < m <= MAX_CULL_OCCLUDERS
        if not self.cull:
            self.front_bits = np.zeros((n, 1), np.uint64)
            self.back_bits = np.zeros((n, 1), np.uint64)
            self.below_bits = np.zeros((n, 3, 1), np.uint64)
            self.above_bits = np.zeros((n, 3, 1), np.uint64)
            return
        cr = np.cross(occ[:, 1] - occ[:, 0], occ[:, 2] - occ[:, 0])
        length = np.linalg.norm(cr, axis=1)
        live = length > 1e-12 * self.scale ** 2  # zero-area occluders block nothing
        nrm = np.divide(cr, length[:, None], out=np.zeros_like(cr), where=live[:, None])
        d0 = np.einsum("td,td->t", nrm, occ[:, 0])
        tol = 4 * self.offset  # sample points sit within `offset` of their patch
        words = (m + 63) // 64
        front = np.zeros((n, words), np.uint64)
        back = np.zeros((n, words), np.uint64)
        step = max(1, (1 << 22) // max(1, 3 * m))
        if scene.is_clustered:  # per triangle first, then all of a patch's triangles must agree
            front = np.zeros((len(tri), words), np.uint64)
            back = np.zeros((len(tri), words), np.uint64)
        for s in range(0, len(tri), step):
            d = np.einsum("pkd,td->ptk", tri[s:s + step], nrm) - d0[None, :, None]  # (p, m, 3)
            f = (d >= -tol).all(axis=2) | ~live[None]
            b = (d <= tol).all(axis=2) | ~live[None]
            front[s:s + step] = _pack_bits(f, words)
            back[s:s + step] = _pack_bits(b, words)
        if scene.is_clustered:
            start, index = scene.patch_triangles
            front = np.bitwise_and.reduceat(front[index], start[:-1], axis=0)
            back = np.bitwise_and.reduceat(back[index], start[:-1], axis=0)
        self.front_bits, self.back_bits = front, back
        # Box overlap of the pair's box (union of the two patch boxes) with an
        # occluder box, per axis: occ.lo <= max(hi_i, hi_j) and occ.hi >= min(lo_i, lo_j),
        # i.e. (below_i | below_j) & (above_i | above_j) with per-patch bit masks.
        pad = 2 * self.offset
        lo = tri.min(axis=1) - pad
        hi = tri.max(axis=1) + pad
        if scene.is_clustered:
            start, index = scene.patch_triangles
            lo = np.minimum.reduceat(lo[index], start[:-1], axis=0)
            hi = np.maximum.reduceat(hi[index], start[:-1], axis=0)
        olo, ohi = occ.min(axis=1), occ.max(axis=1)
        below = np.zeros((n, 3, words), np.uint64)
        above = np.zeros((n, 3, words), np.uint64)
        for axis in range(3):
            for s in range(0, n, step):
                below[s:s + step, axis] = _pack_bits(olo[None, :, axis] <= hi[s:s + step, None, axis], words)
                above[s:s + step, axis] = _pack_bits(ohi[None, :, axis] >= lo[s:s + step, None, axis], words)
        self.below_bits, self.above_bits = below, above

    # ------------------------------------------------------------------
    def apply(self, F: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> None:
        """Multiply the unoccluded block ``F`` (len(rows), len(cols)) by V in place."""
        for job in self.jobs(F, rows, cols):
            self.finish(F, job, self.cast(job))

    def jobs(self, F: np.ndarray, rows: np.ndarray, cols: np.ndarray, buffers=None):
        """Ray jobs (at most RAY_BATCH rays each) for the pairs of ``F`` that need rays.

        A generator: each job is prepared (numba) when asked for, into buffers
        taken from ``buffers`` (a ``RayBuffers`` pool; a private one by default).
        """
        rows = np.ascontiguousarray(rows, np.int64)
        cols = np.ascontiguousarray(cols, np.int64)
        need = np.empty(F.shape, np.bool_)
        _needs_rays(F, rows, cols, self.front_bits, self.back_bits, self.below_bits, self.above_bits,
                    self.cull, need)
        if self.neighbours is not None:
            need = full_ray_pairs(self, F, rows, cols, need)  # the others keep their probe
        flat = np.flatnonzero(need.ravel())
        s = self.samples
        per = max(1, RAY_BATCH // s)
        nc = len(cols)
        pool = buffers if buffers is not None else RayBuffers()
        for start in range(0, len(flat), per):
            pairs = flat[start:start + per]
            r_idx = rows[pairs // nc]
            c_idx = cols[pairs % nc]
            valid = np.empty((len(pairs), s), np.bool_)
            counts = np.empty(len(pairs), np.int64)
            _valid_rays(self.points, self.plane, self.partner, r_idx, c_idx, valid, counts)
            if self.one_ray_below > 0.0 and s > 1:
                weak = np.flatnonzero(self.areas[r_idx] * F.ravel()[pairs] < self.one_ray_below)
                first_valid = valid[weak].argmax(axis=1)
                valid[weak] = False
                valid[weak, first_valid] = True
                counts[weak] = 1
            first = np.zeros(len(pairs) + 1, np.int64)
            np.cumsum(counts, out=first[1:])
            r = int(first[-1])
            buf = pool.get(r)
            o, d, t = buf[0][:r], buf[1][:r], buf[2][:r]
            _fill_rays(self.points, self.partner, r_idx, c_idx, valid, first, o, d, t)
            yield RayJob(pairs, first, o, d, t, buf, pool, r_idx, c_idx)

    def cast(self, job: "RayJob") -> np.ndarray:
        """(r,) bool: blocked segments of a job (Embree; holds the GIL, so one call at a time)."""
        return self.cast_segments(job.o, job.d, job.t)

    def cast_segments(self, o: np.ndarray, d: np.ndarray, t: np.ndarray) -> np.ndarray:
        """(r,) bool: which segments (origins, unit directions, lengths; float32) are blocked."""
        t0 = time.perf_counter()
        hit = self.caster.occluded(o, d, t)
        self.embree_seconds += time.perf_counter() - t0
        return hit

    def finish(self, F: np.ndarray, job: "RayJob", hit: np.ndarray) -> None:
        """Scale F's pairs by their visible fractions and hand the buffers back.

        Pairs whose rays disagree (partly visible) and whose F_ij or F_ji exceeds
        ``refine_above`` are re-cast with ``refine_samples`` rays between a finer
        stratified set of points, and that fraction is used instead: the
        deterministic analogue of "more samples where the first ones disagree".
        """
        flat = F.reshape(-1)
        again = np.zeros(len(job.pairs), np.bool_)
        if self.refine_samples:
            _partial_and_large(flat, job.pairs, job.first, hit, job.r_idx, job.c_idx, self.areas,
                               self.centroids, self.diameters, self.refine_near, self.refine_above, again)
        _scale_by_visibility(flat, job.pairs, job.first, hit, again)
        self.rays_cast += len(job.t)
        job.pool.put(job.buf)
        if again.any():
            self._refine(flat, job.pairs[again], job.r_idx[again], job.c_idx[again])

    def _refine(self, flat: np.ndarray, pairs: np.ndarray, r_idx: np.ndarray, c_idx: np.ndarray) -> None:
        """Second round of rays for ``pairs`` (flat indices into F), cast here and applied."""
        s = self.refine_samples
        per = max(1, RAY_BATCH // s)
        for start in range(0, len(pairs), per):
            sl = slice(start, start + per)
            valid = np.empty((len(pairs[sl]), s), np.bool_)
            counts = np.empty(len(pairs[sl]), np.int64)
            _valid_rays(self.fine_points, self.plane, self.fine_partner, r_idx[sl], c_idx[sl], valid, counts)
            first = np.zeros(len(counts) + 1, np.int64)
            np.cumsum(counts, out=first[1:])
            r = int(first[-1])
            o = np.empty((r, 3), np.float32)
            d = np.empty((r, 3), np.float32)
            t = np.empty(r, np.float32)
            _fill_rays(self.fine_points, self.fine_partner, r_idx[sl], c_idx[sl], valid, first, o, d, t)
            hit = self.cast_segments(o, d, t)
            _scale_by_visibility(flat, pairs[sl], first, hit, np.zeros(len(counts), np.bool_))
            self.rays_cast += r
            self.rays_refined += r

    def close(self) -> None:
        self.caster.close()


class RayJob:
    """One batch of segments: origins o, unit directions d, lengths t (float32)."""

    __slots__ = ("pairs", "first", "o", "d", "t", "buf", "pool", "r_idx", "c_idx")

    def __init__(self, pairs, first, o, d, t, buf, pool, r_idx, c_idx) -> None:
        self.pairs, self.first, self.o, self.d, self.t, self.buf, self.pool = pairs, first, o, d, t, buf, pool
        self.r_idx, self.c_idx = r_idx, c_idx  # patch indices of each pair


class RayBuffers:
    """A free list of ray buffers: fresh pages are slow to fault in, so reuse them."""

    def __init__(self) -> None:
        self._free: list = []

    def get(self, r: int):
        for k, buf in enumerate(self._free):
            if len(buf[2]) >= r:
                return self._free.pop(k)
        r = max(r, 1)
        return (np.empty((r, 3), np.float32), np.empty((r, 3), np.float32), np.empty(r, np.float32))

    def put(self, buf) -> None:
        self._free.append(buf)


def sample_points(scene, m: int) -> tuple[np.ndarray, np.ndarray]:
    """Visibility sample points of each patch and the normals of the triangles they lie on.

    A one-triangle patch gets the centroids of an m x m split. A clustered
    patch gets m^2 points spread over its area: point k lies in the triangle
    where the patch's cumulative area reaches (k + 1/2) / m^2 of the total,
    at one of the 4 centroids of a 2 x 2 split of it (which one follows the
    position within that triangle), so points in one triangle do not coincide.

    Returns
    -------
    points, normals : (n, m^2, 3) float
    """
    tri = np.asarray(scene.triangles, dtype=np.float64)
    s = m * m
    if not scene.is_clustered:
        nrm = np.asarray(scene.normals, np.float64)
        return points_on_triangles(tri, split_centroids(m)), np.repeat(nrm[:, None, :], s, axis=1)
    start, index = scene.patch_triangles
    ta = scene.triangle_areas[index]
    cum = np.cumsum(ta)
    before = np.r_[0.0, cum][start[:-1]]  # cumulative area before each patch
    target = before[:, None] + (np.arange(s) + 0.5)[None, :] / s * scene.areas[:, None]  # (n, s)
    k = np.searchsorted(cum, target, side="right")
    k = np.clip(k, start[:-1, None], start[1:, None] - 1)  # stay inside the patch (rounding)
    within = (target - (cum[k] - ta[k])) / ta[k]
    quarter = np.clip((within * 4).astype(np.int64), 0, 3)
    corners = tri[index[k]]  # (n, s, 3, 3)
    w = split_centroids(2)[quarter]  # (n, s, 3)
    pts = np.einsum("nsk,nskd->nsd", w, corners)
    return pts, scene.triangle_normals[index[k]]


def _pack_bits(flags: np.ndarray, words: int) -> np.ndarray:
    """(p, m) bool -> (p, words) uint64, bit t % 64 of word t // 64."""
    p, m = flags.shape
    padded = np.zeros((p, words * 64), np.bool_)
    padded[:, :m] = flags
    by = np.packbits(padded.reshape(p, words, 64), axis=2, bitorder="little")  # (p, words, 8)
    return np.ascontiguousarray(by).view(np.uint64).reshape(p, words)


@njit(parallel=True, cache=True)
def _needs_rays(F, rows, cols, front, back, below, above, cull, need):
    """need[r, c]: F > 0 and some occluder can cut the pair's segments (bitwise test)."""
    for r in prange(rows.shape[0]):
        i = rows[r]
        for c in range(cols.shape[0]):
            need[r, c] = F[r, c] > 0.0 and (not cull or cuttable(i, cols[c], front, back, below, above))


@njit(parallel=True, cache=True)
def _valid_rays(P, plane, partner, r_idx, c_idx, valid, counts):
    """A ray is valid if each end point is in front of the other patch's plane.

    The kernel already gives zero weight to points behind the other patch, so
    rays from them must not count as blocked a second time. A pair with no
    valid ray (a sliver only the near-field rule sees) keeps all of its rays.
    """
    s = P.shape[1]
    for p in prange(r_idx.shape[0]):
        a = min(r_idx[p], c_idx[p])
        b = max(r_idx[p], c_idx[p])
        m = 0
        for k in range(s):
            q = partner[k]
            fa = (plane[b, 0] * P[a, k, 0] + plane[b, 1] * P[a, k, 1] + plane[b, 2] * P[a, k, 2]) > plane[b, 3]
            fb = (plane[a, 0] * P[b, q, 0] + plane[a, 1] * P[b, q, 1] + plane[a, 2] * P[b, q, 2]) > plane[a, 3]
            valid[p, k] = fa and fb
            if fa and fb:
                m += 1
        if m == 0:
            for k in range(s):
                valid[p, k] = True
            m = s
        counts[p] = m


@njit(parallel=True, cache=True)
def _partial_and_large(F, pairs, first, hit, r_idx, c_idx, areas, C, D, near, above, out):
    """out[p]: the rays of pair p disagree, or the patches are close, and max(F_ij, F_ji) > above.

    Close: centroid distance below near * (D_i + D_j); four rays between near
    patches can all agree and still be wrong. Every test is symmetric in (i, j).

    A_i F_ij is the same number for (i, j) and (j, i), so max(F_ij, F_ji) =
    A_i F_ij / min(A_i, A_j) decides alike from either side: V_ij == V_ji holds.
    """
    for p in prange(pairs.shape[0]):
        blocked = 0
        for k in range(first[p], first[p + 1]):
            if hit[k]:
                blocked += 1
        total = first[p + 1] - first[p]
        i = r_idx[p]
        j = c_idx[p]
        dx = C[i, 0] - C[j, 0]
        dy = C[i, 1] - C[j, 1]
        dz = C[i, 2] - C[j, 2]
        close = dx * dx + dy * dy + dz * dz < (near * (D[i] + D[j])) ** 2
        if (0 < blocked < total) or close:
            out[p] = F[pairs[p]] * areas[i] > above * min(areas[i], areas[j])


@njit(parallel=True, cache=True)
def _scale_by_visibility(F, pairs, first, hit, skip):
    """F[pairs[p]] *= fraction of the rays first[p]:first[p+1] that are not blocked (unless skip[p])."""
    for p in prange(pairs.shape[0]):
        if skip[p]:
            continue
        blocked = 0
        for k in range(first[p], first[p + 1]):
            if hit[k]:
                blocked += 1
        total = first[p + 1] - first[p]
        if blocked:
            F[pairs[p]] *= 1.0 - blocked / total


@njit(parallel=True, cache=True)
def _fill_rays(P, partner, r_idx, c_idx, valid, first, o, d, t):
    s = P.shape[1]
    for p in prange(r_idx.shape[0]):
        a = min(r_idx[p], c_idx[p])  # canonical direction: V_ij == V_ji exactly
        b = max(r_idx[p], c_idx[p])
        row = first[p]
        for k in range(s):
            if not valid[p, k]:
                continue
            q = partner[k]
            dx = P[b, q, 0] - P[a, k, 0]
            dy = P[b, q, 1] - P[a, k, 1]
            dz = P[b, q, 2] - P[a, k, 2]
            L = math.sqrt(dx * dx + dy * dy + dz * dz)
            inv = 1.0 / L if L > 0.0 else 0.0
            o[row, 0] = P[a, k, 0]
            o[row, 1] = P[a, k, 1]
            o[row, 2] = P[a, k, 2]
            d[row, 0] = dx * inv
            d[row, 1] = dy * inv
            d[row, 2] = dz * inv
            t[row] = L
            row += 1
