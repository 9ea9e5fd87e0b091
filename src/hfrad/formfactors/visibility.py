"""Visibility between patches: the kernel-weighted fraction of unoccluded rays, cast with Embree.

V_ij is estimated from segments between fixed sample points of the two
patches: the centroids of an m x m split of each triangle (stratified and
deterministic). Segment k joins point k of the lower-indexed patch to point
``pairing(s)[k]`` of the other one (a half shift for s <= 4, a fixed scramble
above, so that the segments spread over the 4-d space of point pairs). The pair
is put in canonical order (lower patch index first) and always cast in that
direction, so V_ij == V_ji bit for bit and reciprocity survives. Each segment
is weighted by the point-to-point kernel cos_i cos_j / r^2 (patch normals):
V_ij = sum of the weights of the free segments / sum of all weights. Unweighted
fractions are biased wherever visibility correlates with the kernel (a block
hides the near part of a patch, say): on two of the built-in Cornell box's
worst rows 64 x 64 plain rays per pair left the row sums 1.6% and 2.1% off,
weighted ones 0.07% and 0.04%.

Rounds (probing on, the default; probing.py):

1. every pair that needs rays gets one *probe* segment, centroid to centroid;
   a pair whose neighbouring pairs' probes agree with its own keeps it (0 or 1);
2. the others (shadow boundaries, contact shadows, close or large pairs) get
   ``BOUNDARY_SAMPLES`` = 16 weighted segments (4 x 4 split), or ``samples`` (4)
   and no round 3 if the pair is too weak to matter at the factorization's error
   budget (``RayBudget.few_rays_below``; off unless a budget is given);
3. where those disagree (a partly visible pair) or the patches are close
   (centroid distance below REFINE_NEAR (D_i + D_j): such a pair skips round 2,
   whose rays could not change this), and the pair matters
   (F_ij or F_ji above ``refine_above``, 1e-4), ``REFINE_SAMPLES`` = 64 segments
   (8 x 8 split), ``REFINE_LARGE_SAMPLES`` = 256 (16 x 16) when F_ij or F_ji
   exceeds REFINE_LARGE_ABOVE, replace the estimate. With a ray budget, pairs too weak to
   matter at the factorization's error budget skip this round (``RayBudget.refine_below``)
   or get 64 segments instead of 256 (``RayBudget.large_below``). On Sponza at 3K the
   256-segment round of bent pairs was 41% of all rays (benchmarks/README.md).

   By default (``IMPORTANCE``) this round casts no fixed pairing: among all the segments between
   the points of an 8 x 8 design of each patch (64 x 64 candidates; 6 x 6 where the fixed pairing
   would cast 64: ``IMPORTANCE_DESIGN``) it picks ``IMPORTANCE_PICKS`` = 32 where the fixed pairing
   would cast 64 and 64 where it would cast 256, in proportion to their kernel weight (no rays: a
   low-discrepancy set pushed through the weight's distribution,
   :func:`~hfrad.formfactors.segments.importance_picks`), casts each distinct one once, and V is the
   share of free picks (pairs of flat patches: only in clustered scenes, ``IMPORTANCE_FLAT``).
   The fixed pairing's weighted estimate rests on the few short segments that
   carry most of a close pair's weight; each pick counts alike. On a floor and a wall meeting
   behind a fence (tests/test_importance_visibility.py) the mean error against the closed form
   fell 0.117 -> 0.069 (64 fixed -> 32 picks) and 0.068 -> 0.026 (256 -> 64); 200 rows of each public
   scene at 3K came nearer cosine-weighted shooting with a third fewer rays (benchmarks/README.md,
   "Importance picks for the second round"). ``IMPORTANCE = False`` (or ``importance=False``)
   restores the fixed pairing.

With probing off every pair that needs rays gets ``samples`` segments, then round 3.

The rounds are tuned so that every row of a closed scene closes within about
0.2% (``|sum_j F_ij - 1|``); tests/test_probing.py checks it on the built-in
Cornell box and benchmarks/README.md ("Form-factor accuracy and its cost")
records the cost of each round and the figures measured.

There is no random jitter on purpose: Monte Carlo noise in F is full rank and
destroys the low rank the hierarchical factorization relies on (docs/method.md, section 2).

Clustered patches that are not flat (*bent*: a corner of their triangles farther than
``BENT_DEPTH`` times their diameter from their mean plane: curved vaults, folds, saw teeth) get
other segments in every round, paired alike: their end points are spread over the patch's own
triangles (:func:`bent_points`), and a segment counts where it leaves the front of the triangle at
each end, weighted by those triangles' cosines, as the clustered kernel weighs it (clustered.py,
eq. 3); one that passes through the patch's own other triangles is blocked by Embree (a cluster
shading itself). The patch planes' test threw exactly those away: between a wall and a touching
vault cluster of Sponza it gave a visibility of 0.97 against 0.71 from random segments, and two
interleaved clusters of saw teeth, which see each other across every groove, a form factor of 0.
Pairs of flat patches keep the segments above, bit for bit.

End points are moved off their surfaces along the patch normals by
``1e-5 x scene size`` so that a ray never hits the face it starts or ends on.
Rays are cast in the scene's own frame: coordinates relative to the centre of
its bounding box, in units of its size. Embree works in float32, whose
resolution far from the origin (site or georeferenced coordinates: 0.06 m at
1e6 m) would swallow the offset, and which misses every hit at sizes of 1e13
and more or 1e-20 and less (see :mod:`hfrad.formfactors.raycast`); in this
frame every scene is about 1 across, so its form factors do not depend on
where it lies or on its unit (tests/test_robust_inputs.py checks 1e-25 and 1e13 m).
Rays are cast only for pairs with a nonzero unoccluded form factor that *can*
be blocked: an occluder triangle can cut a segment only if the segment's end
points lie on opposite sides of its plane and the pair's bounding box meets the
triangle's. Per patch and occluder plane, one bit says "wholly on the front
side" and one "wholly on the back side"; a pair needs rays only if some
occluder is neither wholly in front of both patches nor wholly behind both and
its box overlaps theirs (shaft culling with planes and boxes). In a room most
pairs of wall patches need no ray at all.

Optionally (``cluster_size``, off by default: ``CLUSTER_VISIBILITY``), pairs of
patch clusters that no occluder can cut, or that one occluder triangle hides
wholly, are decided without rays by an exact, conservative hull test, and so are
the costly patch pairs of the other cluster pairs (:mod:`hfrad.formfactors.clustervis`);
F is the same as with per-pair rays.
"""

from __future__ import annotations

import math
import time

import numpy as np
from numba import njit, prange

from ..errors import InputError
from .budget import FEW_RAYS_FACTOR, LARGE_FACTOR, REFINE_FACTOR, RayBudget
from .clustervis import (MIXED, ClusterVisibility, costly_pairs,
                         full_ray_pairs_clustered)
from .kernel import points_on_triangles, split_centroids
from .probing import (NEIGHBOURS, PROBE_BELOW, PROBE_NEAR, cuttable, cuttable_one_word, full_ray_pairs,
                      nearest_patches, one_word_bits)
from .raycast import RayCaster
from .segments import (RAY_BATCH, RayBuffers, RayJob, fill_picked, fill_rays, fill_rays_on_triangles,
                       importance_picks, probe_segments, valid_rays, valid_rays_on_triangles)

#: Rays per patch pair by default (a 2 x 2 split of each triangle) with probing off; with
#: probing on (the default) the flagged pairs get max(samples, BOUNDARY_SAMPLES).
DEFAULT_SAMPLES = 4

#: Kernel-weighted rays for the pairs the probes flag (neighbouring probes disagree, close or
#: large pairs): a 4 x 4 split of each triangle, paired by a fixed scramble (see ``pairing``).
BOUNDARY_SAMPLES = 16

#: Second round, kernel-weighted: where the first rays disagree or the patches are close
#: (an 8 x 8 split), and a 16 x 16 split for large pairs (max(F_ij, F_ji) > REFINE_LARGE_ABOVE).
REFINE_SAMPLES = 64
REFINE_LARGE_SAMPLES = 256
REFINE_LARGE_ABOVE = 3e-3

#: The second round's estimator: True, IMPORTANCE_PICKS[s] segments (where the fixed pairing would
#: cast s) picked in proportion to their kernel weight among all pairs of points of an
#: IMPORTANCE_DESIGN[s]^2 design of each patch (:func:`~hfrad.formfactors.segments.importance_picks`);
#: False, the fixed pairing of ``s`` weighted segments. The 6 x 6 design of the 64 level costs a third
#: of the 8 x 8's weights (about 3 ns a candidate) and left Sponza's 200 rows where 8 x 8 did (0.1397).
#: IMPORTANCE_FLAT: pairs of flat patches too, in clustered scenes only: on the unclustered built-in
#: Cornell box (1,508 patches) the picks left the worst row sum at 2.8e-3 against 1.8e-3 (2.1e-3 with
#: as many picks as fixed segments), where on the public scenes' rows they cost nothing
#: (benchmarks/README.md).
IMPORTANCE = True
IMPORTANCE_FLAT = True
IMPORTANCE_DESIGN = {64: 6, 256: 8}
IMPORTANCE_PICKS = {64: 32, 256: 64}

#: Pairs whose first rays disagree, or closer than REFINE_NEAR * (D_i + D_j) (centroid
#: distance, longest edges), get the second round if F_ij or F_ji exceeds REFINE_ABOVE.
REFINE_ABOVE = 1e-4
REFINE_NEAR = 2.0
#: Probe rays (:meth:`Visibility.segments_blocked` with points) join points of a PROBE_DESIGN x
#: PROBE_DESIGN design on each patch: a clustered patch's centre can lie in the open while most of
#: it is shaded (Šibenik, 10,181 patches: a floor cluster's centre rays passed to columns it saw
#: 24% of on average).
PROBE_DESIGN = 3

#: Patches per cluster for cluster-pair visibility (:mod:`hfrad.formfactors.clustervis`) by
#: default; 0 = off. Off by default: the F is the same, and on the built-in scenes its tests cost
#: about as much time as the rays they save (see tests/test_cluster_visibility.py);
#: ``CLUSTER_SIZE`` turns it on.
CLUSTER_VISIBILITY = 0

#: Whether the cluster test is repeated per patch pair where the cluster pair is mixed.
PAIR_TEST = True

#: A clustered patch is *bent* when a corner of its triangles lies farther than this times its
#: diameter from its mean plane (curved, folded or saw-toothed: its own triangles can shade it);
#: pairs with a bent patch get the segments of :meth:`Visibility._bent_jobs`.
BENT_DEPTH = 1e-3

#: Above this many occluder triangles the per-pair culling test costs more than it saves.
MAX_CULL_OCCLUDERS = 2048

_OFFSET = 1e-5  # end point offset, times the scene size


def settings() -> dict:
    """The second-round visibility parameters, as recorded with results (.hfr files), and the ray
    budget's factors (budget.py: a checkpoint made with other rules is not resumed)."""
    return {"boundary_samples": BOUNDARY_SAMPLES, "refine_samples": REFINE_SAMPLES,
            "refine_large_samples": REFINE_LARGE_SAMPLES, "refine_large_above": REFINE_LARGE_ABOVE,
            "refine_above": REFINE_ABOVE, "refine_near": REFINE_NEAR, "weighted": True,
            "probe_neighbours": NEIGHBOURS, "probe_below": PROBE_BELOW, "probe_near": PROBE_NEAR,
            "budget_factors": {"few_rays": FEW_RAYS_FACTOR, "refine": REFINE_FACTOR, "large": LARGE_FACTOR},
            "importance": IMPORTANCE, "importance_flat": IMPORTANCE_FLAT,
            "importance_design": {str(k): v for k, v in IMPORTANCE_DESIGN.items()},
            "importance_picks": {str(k): v for k, v in IMPORTANCE_PICKS.items()}}


def check_samples(samples: int) -> int:
    """Validate ``samples`` (a perfect square >= 1); returns its square root."""
    m = math.isqrt(int(samples)) if int(samples) >= 1 else 0
    if samples != int(samples) or m < 1 or m * m != int(samples):
        raise InputError(f"samples must be a perfect square (1, 4, 9, 16, ...) so the sample points "
                         f"are a stratified split of each triangle, got {samples}")
    return m


def pairing(samples: int) -> np.ndarray:
    """(samples,) int64: segment k joins point k of the lower-indexed patch to point pairing[k]
    of the other one.

    Up to 4 points, a fixed shift by half (so that parallel patches are not probed
    only by parallel rays). From 9 on, a fixed scramble (Fisher-Yates driven by
    a 64-bit linear congruential generator with a fixed seed: the same on every
    platform), so that the segments spread over the 4-d space of pairs of points
    instead of lying on a few parallel families: on the built-in Cornell box's
    worst rows 64 scrambled kernel-weighted rays give a worst row sum of 1.9e-3
    where the shift gives 2.0e-3, and 256 give 1.35e-3 vs 2.35e-3.
    """
    s = int(samples)
    if s <= 4:
        return np.ascontiguousarray((np.arange(s) + s // 2) % s, dtype=np.int64)
    perm = list(range(s))
    state = 0x2545F4914F6CDD1D
    for k in range(s - 1, 0, -1):
        state = (6364136223846793005 * state + 1442695040888963407) % (1 << 64)
        j = (state >> 33) % (k + 1)
        perm[k], perm[j] = perm[j], perm[k]
    return np.asarray(perm, dtype=np.int64)


class Visibility:
    """Ray casting state for one scene: sample points, culling masks, Embree scene.

    Parameters
    ----------
    scene : Scene
        Rays are cast against ``scene.occluder_vertices`` / ``occluder_faces``.
    samples : int
        Rays per pair, a perfect square; 1 = centroid to centroid (and no probing).
        With probing the flagged pairs get max(samples, BOUNDARY_SAMPLES).
    cull : bool
        Skip pairs that no occluder can block (exact test, see module docstring).
    refine_samples, refine_above : int, float
        The second round for partly visible or close pairs (see module docstring;
        REFINE_LARGE_SAMPLES above REFINE_LARGE_ABOVE); 0 = none.
    probe : bool
        One probe ray per pair first, more only where neighbouring pairs
        disagree (see :mod:`hfrad.formfactors.probing`); off = ``samples`` rays everywhere.
    ray_budget : RayBudget, optional
        Fewer rays for weak pairs (default: off, every pair gets all its rays).
    cluster_size : int
        Patches per cluster for visibility decided once per cluster pair where it is
        all or nothing (:mod:`hfrad.formfactors.clustervis`); 0 = off, every pair is
        decided by its own rays. Default ``CLUSTER_VISIBILITY``.
    pair_test : bool, optional
        Where a cluster pair is mixed, run the same all-or-nothing test on each of its
        patch pairs that needs rays and would get every ray whatever its probe says
        (close or large pairs, probing.py), each patch's box as its cluster; only with
        ``cluster_size`` > 0. Default ``PAIR_TEST``.
    ray_threads : int or None
        Threads casting each batch of rays: 1 (default) where the caller runs Embree in a
        thread of its own beside the kernel (the engine's pipeline); None: every core, for a
        caller that waits for each batch (the sampled far field).
    importance, importance_flat : bool, optional
        The second round's segments of pairs with a bent patch, and of pairs of flat patches,
        picked by kernel weight (module docstring); default ``IMPORTANCE``, and ``IMPORTANCE_FLAT``
        for a clustered scene (False for one of single triangles); False: the fixed pairing.
    """

    def __init__(self, scene, *, samples: int = DEFAULT_SAMPLES, cull: bool = True,
                 refine_samples: int = REFINE_SAMPLES, refine_above: float = REFINE_ABOVE,
                 probe: bool = True, ray_budget: RayBudget | None = None,
                 cluster_size: int | None = None, pair_test: bool | None = None, ray_threads: int | None = 1,
                 importance: bool | None = None, importance_flat: bool | None = None) -> None:
        m = check_samples(samples)
        self.samples = int(samples)
        # everything below is in the scene's frame: centred, in units of its size (module docstring);
        # only `areas` stays in m^2 (it weighs form factors, which have no unit)
        self.centre = 0.5 * (scene.bounds[0] + scene.bounds[1]) if scene.n_patches else np.zeros(3)
        size = float(np.ptp(scene.bounds, axis=0).max()) if scene.n_patches else 1.0
        self.unit = size if size > 0 else 1.0  # metres per unit of the frame
        tri = self._frame(scene.triangles)
        self.scale = 1.0  # the scene's size in the frame
        self.offset = _OFFSET * self.scale
        self._scene = scene
        self._tri = tri
        self._design_cache: dict = {}
        nrm = np.asarray(scene.normals, np.float64)
        # patch planes n . x = n . v0, or through the centroid of a clustered patch
        # (sample points are `offset` in front of their own triangles)
        on_plane = self._frame(scene.centroids) if scene.is_clustered else tri[:, 0]
        self.plane = np.ascontiguousarray(np.column_stack([nrm, np.einsum("nd,nd->n", nrm, on_plane)
                                                           if len(tri) else np.zeros(0)]))
        self.points = self._points(m, None)
        self.bent = bent_patches(scene, self.plane, tri, self.offset) if scene.is_clustered else None
        self.partner = pairing(self.samples)
        # the flagged pairs' first round, and the second round (module docstring)
        self.refine_samples = int(refine_samples) if refine_samples > samples else 0
        self.refine_above = float(refine_above)
        self.refine_large_samples = REFINE_LARGE_SAMPLES if self.refine_samples else 0
        self.refine_large_above = REFINE_LARGE_ABOVE
        self.rays_refined = 0
        self.importance = bool(IMPORTANCE if importance is None else importance)
        self.importance_flat = bool(IMPORTANCE_FLAT and scene.is_clustered if importance_flat is None
                                    else importance_flat)
        self.refine_near = REFINE_NEAR
        self.probe_near = PROBE_NEAR
        self.centroids = np.ascontiguousarray(self._frame(scene.centroids))
        edges = np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).max(axis=1) if len(tri) else np.zeros(0)
        self.diameters = np.ascontiguousarray(edges)
        self.caster = RayCaster(self._frame(scene.occluder_vertices), scene.occluder_faces, threads=ray_threads,
                                normalise=False)  # already in the frame
        self._setup_culling(scene, tri, cull)
        self.areas = np.ascontiguousarray(scene.areas, dtype=np.float64)
        self.budget = ray_budget if ray_budget is not None else RayBudget()
        self.rays_cast = 0
        self.embree_seconds = 0.0
        #: per round ("probe", "4", "16", "64", "256"; " bent" for pairs with a bent patch): pairs,
        #: rays and Embree seconds (the cost of each round, benchmarks/bench_visibility_rounds.py)
        self.rounds: dict[str, list] = {}
        # ray buffers reused from block to block (fresh pages cost page faults: ~10% of the time)
        self.buffers = RayBuffers()
        # one probe ray per pair first, every ray only where neighbouring pairs disagree (probing.py)
        self.rays_probe = 0
        self.probe_below = PROBE_BELOW
        self.neighbours = None
        self.boundary_samples = self.samples
        if probe and self.samples > 1 and scene.n_patches > 1:
            self.neighbours = nearest_patches(self.centroids)  # centred: see module docstring
            self.probe_points = self._points(1, None)
            self.boundary_samples = max(self.samples, BOUNDARY_SAMPLES)
        self.boundary_points = (self.points if self.boundary_samples == self.samples
                                else self._points(check_samples(self.boundary_samples), None))
        self.boundary_partner = pairing(self.boundary_samples)
        size = CLUSTER_VISIBILITY if cluster_size is None else int(cluster_size)
        if size < 0:
            raise InputError(f"cluster_size must be 0 (off) or a positive number of patches, got {cluster_size}")
        self.clusters = None
        self.pair_test = bool(PAIR_TEST if pair_test is None else pair_test)
        if size and scene.n_patches > 1 and self.n_occluders:
            occ = self._frame(scene.occluder_vertices)[np.asarray(scene.occluder_faces)]
            self.clusters = ClusterVisibility(self.centroids, self.patch_lo, self.patch_hi, occ,
                                              4 * self.offset, size)

    def _frame(self, x) -> np.ndarray:
        """Points in metres -> the visibility frame (centred, in units of the scene's size), float64."""
        return (np.asarray(x, dtype=np.float64) - self.centre) / self.unit

    def _points(self, m: int, patches) -> np.ndarray:
        """(len(patches), m^2, 3) ray end points of an m x m design (all patches if None), centred
        and moved ``offset`` off their surfaces."""
        scene = self._scene
        if patches is None or scene.is_clustered:
            key = ("all", m)
            if key not in self._design_cache:
                pts, nrm = sample_points(scene, m)
                self._design_cache[key] = np.ascontiguousarray(self._frame(pts) + self.offset * nrm)
                if patches is None:
                    return self._design_cache.pop(key)
            allp = self._design_cache[key]
            return np.ascontiguousarray(allp[patches])
        nrm = np.asarray(scene.normals, np.float64)[patches]
        pts = points_on_triangles(self._tri[patches], split_centroids(m)) + self.offset * nrm[:, None, :]
        return np.ascontiguousarray(pts)

    def _setup_culling(self, scene, tri: np.ndarray, cull: bool) -> None:
        occ = self._frame(scene.occluder_vertices)[np.asarray(scene.occluder_faces)]
        m = len(occ)
        self.n_occluders = m
        self.patch_lo, self.patch_hi = _patch_boxes(scene, tri, 2 * self.offset)
        n = scene.n_patches
        self.cull = bool(cull) and 0 < m <= MAX_CULL_OCCLUDERS
        if not self.cull:
            self.front_bits = np.zeros((n, 1), np.uint64)
            self.back_bits = np.zeros((n, 1), np.uint64)
            self.below_bits = np.zeros((n, 3, 1), np.uint64)
            self.above_bits = np.zeros((n, 3, 1), np.uint64)
            self.word_bits = None
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
        lo, hi = self.patch_lo, self.patch_hi
        olo, ohi = occ.min(axis=1), occ.max(axis=1)
        below = np.zeros((n, 3, words), np.uint64)
        above = np.zeros((n, 3, words), np.uint64)
        for axis in range(3):
            for s in range(0, n, step):
                below[s:s + step, axis] = _pack_bits(olo[None, :, axis] <= hi[s:s + step, None, axis], words)
                above[s:s + step, axis] = _pack_bits(ohi[None, :, axis] >= lo[s:s + step, None, axis], words)
        self.below_bits, self.above_bits = below, above
        # the masks in one (n, 8) array when one word holds them: made once, read by every block
        self.word_bits = one_word_bits(front, back, below, above) if words == 1 else None

    def cluster_pairs(self, scene, size: int) -> ClusterVisibility | None:
        """This visibility's cluster-pair tests (:mod:`hfrad.formfactors.clustervis`), made with
        ``size`` patches a cluster if it has none; None without occluders."""
        if self.clusters is None and scene.n_patches > 1 and self.n_occluders:
            occ = self._frame(scene.occluder_vertices)[np.asarray(scene.occluder_faces)]
            self.clusters = ClusterVisibility(self.centroids, self.patch_lo, self.patch_hi, occ,
                                              4 * self.offset, size)
        return self.clusters

    def segments_blocked(self, i: np.ndarray, j: np.ndarray, ki: np.ndarray | None = None,
                         kj: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Whether the segment between patches ``i[k]`` and ``j[k]`` is blocked: between their centre
        points, or (``ki``, ``kj`` given) between points ``ki[k]`` and ``kj[k]`` of the
        ``PROBE_DESIGN`` x ``PROBE_DESIGN`` design on each (:attr:`probe_design_points` points a patch).

        Returns ``(facing, blocked)`` (len(i),) bool: ``facing`` where each patch faces the
        other (elsewhere F is 0 and the segment says nothing), ``blocked`` where an occluder
        cuts it. One ray a pair: a probe, not a visibility estimate.
        """
        i, j = np.asarray(i, np.int64), np.asarray(j, np.int64)
        if ki is None:
            P, ki, kj = self._probe_design(1), np.zeros_like(i), np.zeros_like(j)
        else:
            P, ki, kj = self._probe_design(PROBE_DESIGN), np.asarray(ki, np.int64), np.asarray(kj, np.int64)
        r = len(i)
        o, d = np.empty((r, 3), np.float32), np.empty((r, 3), np.float32)
        t, facing = np.empty(r, np.float32), np.empty(r, bool)
        probe_segments(P, self._normals, i, ki, j, kj, o, d, t, facing)
        blocked = self.cast_segments(o, d, t) & facing
        self.rays_cast += int(facing.sum())
        return facing, blocked

    def hashed_ray_points(self) -> tuple[np.ndarray, np.ndarray]:
        """``(P, normals)``: the probes' design points (n, :attr:`probe_design_points`, 3) float32 and the
        patches' unit normals (n, 3), in this object's frame: what :meth:`segments_blocked` joins
        (:mod:`hfrad.formfactors.hashed_rays` makes its segments from them)."""
        return self._probe_design(PROBE_DESIGN), self._normals

    @property
    def probe_design_points(self) -> int:
        """Points a patch that :meth:`segments_blocked` picks from (``ki``, ``kj`` below this)."""
        return PROBE_DESIGN * PROBE_DESIGN

    def _probe_design(self, m: int) -> np.ndarray:
        """(n, m^2, 3) float32 the probes' points (kept: 12 m^2 bytes a patch).

        Threads building parts of one H-matrix share this object: ``_normals`` is set before any design
        can be seen, and the designs' dict and entries come from ``setdefault`` (one call under the GIL),
        so a thread never meets the dict without the normals or loses its entry to another thread's
        (before: an AttributeError on ``_normals``, seen once in the distributed tests)."""
        if "_normals" not in self.__dict__:
            self._normals = np.ascontiguousarray(self.plane[:, :3])
        designs = self.__dict__.setdefault("_probe_designs", {})
        design = designs.get(m)
        if design is None:
            design = designs.setdefault(m, np.ascontiguousarray(self._points(m, None), dtype=np.float32))
        return design

    # ------------------------------------------------------------------
    def apply(self, F: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> None:
        """Multiply the unoccluded block ``F`` (len(rows), len(cols)) by V in place."""
        for job in self.jobs(F, rows, cols):
            todo = [job]
            while todo:
                j = todo.pop()
                todo.extend(self.finish(F, j, self.cast(j)))

    def jobs(self, F: np.ndarray, rows: np.ndarray, cols: np.ndarray, buffers=None):
        """Ray jobs (at most RAY_BATCH rays each) for the pairs of ``F`` that need rays.

        A generator: each job is prepared (numba) when asked for, into buffers
        taken from ``buffers`` (a ``RayBuffers`` pool; by default this object's own).
        """
        rows = np.ascontiguousarray(rows, np.int64)
        cols = np.ascontiguousarray(cols, np.int64)
        need = np.empty(F.shape, np.bool_)
        _needs_rays(F, rows, cols, self.front_bits, self.back_bits, self.below_bits, self.above_bits,
                    self.cull, need, self.word_bits)
        if self.clusters is not None:
            # pairs of clusters that are wholly visible or wholly blocked need no ray (clustervis.py)
            cs = self.clusters.states(rows, cols)
            if self.pair_test:  # the same test per patch pair where the cluster pair is mixed and
                # the pair would get every ray (close or large; a probe costs less than the test)
                mixed = costly_pairs(self, F, rows, cols, need & (cs == MIXED))
                cs[mixed] = self.clusters.pair_states(rows, cols, mixed)
            self.clusters.settle(F, need, cs)
        if self.neighbours is not None:
            if self.clusters is not None:
                need = full_ray_pairs_clustered(self, self.clusters, F, rows, cols, need, cs)
            else:
                need = full_ray_pairs(self, F, rows, cols, need)  # the others keep their probe
        flat = np.flatnonzero(need.ravel())
        pool = buffers if buffers is not None else self.buffers
        if self.neighbours is None or self.boundary_samples == self.samples:
            yield from self._jobs(F, rows, cols, flat, self.points, self.partner, pool)
            return
        # with probing the pairs left here are the flagged ones: the boundary design, except for
        # those too weak to matter at the error budget (RayBudget.few_rays_below): ``samples``
        # rays and no second round
        few = self.areas[rows[flat // len(cols)]] * F.ravel()[flat] < self.budget.few_rays_below
        if few.any():
            yield from self._jobs(F, rows, cols, flat[few], self.points, self.partner, pool, final=True)
            flat = flat[~few]
        if self.refine_samples:   # close pairs get the second round whatever their first rays say: only it
            flat = yield from self._close_jobs(F, rows, cols, flat, pool)
        yield from self._jobs(F, rows, cols, flat, self.boundary_points, self.boundary_partner, pool)

    def _close_jobs(self, F, rows, cols, flat, pool):
        """Second-round jobs for the pairs of ``flat`` (flat indices into F) that :meth:`finish` would
        send there for being close, whatever their first rays said (the same F, without those rays);
        returns the others."""
        nc = len(cols)
        r_idx, c_idx = rows[flat // nc], cols[flat % nc]
        level = np.empty(len(flat), np.int8)
        _close_level(F.reshape(-1), flat, r_idx, c_idx, self.areas, self.centroids, self.diameters, self.refine_near,
                     self.refine_above, self.refine_large_above, self.budget.refine_below, self.budget.large_below,
                     level)
        for lv, samples in ((1, self.refine_samples), (2, self.refine_large_samples)):
            sel = level == lv
            if sel.any():
                yield from self._refine_jobs(flat[sel], r_idx[sel], c_idx[sel], samples, pool)
        return flat[level == 0]

    def _jobs(self, F, rows, cols, flat, P, partner, pool, final=False):
        s = partner.shape[0]
        nc = len(cols)
        if self.bent is not None:  # pairs with a bent patch: segments between its triangles' points
            bent = self.bent[rows[flat // nc]] | self.bent[cols[flat % nc]]
            if bent.any():
                pairs = flat[bent]
                weak = self.areas[rows[pairs // nc]] * F.ravel()[pairs] < self.budget.one_ray_below
                yield from self._bent_jobs(pairs, rows[pairs // nc], cols[pairs % nc], s, pool, final, weak)
                flat = flat[~bent]
        per = max(1, RAY_BATCH // s)
        for start in range(0, len(flat), per):
            pairs = flat[start:start + per]
            r_idx = rows[pairs // nc]
            c_idx = cols[pairs % nc]
            valid = np.empty((len(pairs), s), np.bool_)
            counts = np.empty(len(pairs), np.int64)
            valid_rays(P, self.plane, partner, r_idx, c_idx, valid, counts)
            if self.budget.one_ray_below > 0.0 and s > 1:
                weak = self.areas[r_idx] * F.ravel()[pairs] < self.budget.one_ray_below
                _keep_one(valid, counts, np.flatnonzero(weak))
            first = np.zeros(len(pairs) + 1, np.int64)
            np.cumsum(counts, out=first[1:])
            r = int(first[-1])
            buf = pool.get(r)
            o, d, t, w = buf[0][:r], buf[1][:r], buf[2][:r], buf[3][:r]
            fill_rays(P, self.plane, partner, r_idx, c_idx, valid, first, o, d, t, w)
            yield RayJob(pairs, first, o, d, t, w, buf, pool, r_idx, c_idx, final, str(s))

    def cast(self, job: "RayJob") -> np.ndarray:
        """(r,) bool: blocked segments of a job (Embree, in the widest packets this CPU runs; holds no GIL)."""
        return self.cast_segments(job.o, job.d, job.t, job.round, len(job.pairs))

    def cast_segments(self, o: np.ndarray, d: np.ndarray, t: np.ndarray, round: str = "",
                      pairs: int | None = None) -> np.ndarray:
        """(r,) bool: which segments (origins, unit directions, lengths; float32) are blocked.
        ``round`` and ``pairs`` (default: one a segment) go to the counters of :attr:`rounds`."""
        t0 = time.perf_counter()
        hit = self.caster.occluded(o, d, t)
        seconds = time.perf_counter() - t0
        self.embree_seconds += seconds
        if round:
            count = self.rounds.setdefault(round, [0, 0, 0.0])
            count[0] += len(t) if pairs is None else pairs
            count[1] += len(t)
            count[2] += seconds
        return hit

    def finish(self, F: np.ndarray, job: "RayJob", hit: np.ndarray) -> list:
        """Scale F's pairs by their kernel-weighted visible fractions and hand the buffers back.

        Pairs whose rays disagree (partly visible) or whose patches are close, and
        whose F_ij or F_ji exceeds ``refine_above``, are left unscaled and
        returned as second-round jobs: ``refine_samples`` rays
        (``refine_large_samples`` above ``refine_large_above``) between finer
        stratified sets of points, whose fraction is used instead (the
        deterministic analogue of "more samples where the first ones disagree").
        Cast each returned job and ``finish`` it too (it returns nothing more).
        """
        flat = F.reshape(-1)
        self.rays_cast += len(job.t)
        if job.final:
            _scale_by_visibility(flat, job.pairs, job.first, hit, job.w, np.zeros(len(job.pairs), np.bool_))
            job.pool.put(job.buf)
            return []
        again = np.zeros(len(job.pairs), np.int8)
        if self.refine_samples:
            _partial_and_large(flat, job.pairs, job.first, hit, job.r_idx, job.c_idx, self.areas,
                               self.centroids, self.diameters, self.refine_near, self.refine_above,
                               self.refine_large_above, self.budget.refine_below, self.budget.large_below, again)
        _scale_by_visibility(flat, job.pairs, job.first, hit, job.w, again != 0)
        job.pool.put(job.buf)
        more = []
        for level, samples in ((1, self.refine_samples), (2, self.refine_large_samples)):
            sel = again == level
            if sel.any():
                more.extend(self._refine_jobs(job.pairs[sel], job.r_idx[sel], job.c_idx[sel], samples, job.pool))
        return more

    def _refine_jobs(self, pairs: np.ndarray, r_idx: np.ndarray, c_idx: np.ndarray, s: int,
                     pool: "RayBuffers") -> list:
        """Second-round jobs of ``s`` rays for ``pairs`` (flat indices into F), in buffers from ``pool``;
        with :attr:`importance`, the picked segments of :meth:`_importance_jobs` instead."""
        out = []
        bent = self.bent[r_idx] | self.bent[c_idx] if self.bent is not None else np.zeros(len(pairs), np.bool_)
        if self.importance:  # pairs with a bent patch, and flat ones with importance_flat
            picked = bent | self.importance_flat
            for sel, is_bent in ((picked & bent, True), (picked & ~bent, False)):
                if sel.any():
                    out.extend(self._importance_jobs(pairs[sel], r_idx[sel], c_idx[sel], s, pool, is_bent))
            pairs, r_idx, c_idx, bent = pairs[~picked], r_idx[~picked], c_idx[~picked], bent[~picked]
        if bent.any():
            out.extend(self._bent_jobs(pairs[bent], r_idx[bent], c_idx[bent], s, pool, True))
            pairs, r_idx, c_idx = pairs[~bent], r_idx[~bent], c_idx[~bent]
        self.rays_refined += sum(len(job.t) for job in out)
        m = check_samples(s)
        partner = pairing(s)
        per = max(1, RAY_BATCH // s)
        for start in range(0, len(pairs), per):
            sl = slice(start, start + per)
            # the points of the patches involved only (sorted, so canonical order is kept)
            patches, inverse = np.unique(np.concatenate([r_idx[sl], c_idx[sl]]), return_inverse=True)
            k = len(r_idx[sl])
            ri, ci = inverse[:k].astype(np.int64), inverse[k:].astype(np.int64)
            P = self._points(m, patches)
            plane = np.ascontiguousarray(self.plane[patches])
            valid = np.empty((k, s), np.bool_)
            counts = np.empty(k, np.int64)
            valid_rays(P, plane, partner, ri, ci, valid, counts)
            first = np.zeros(k + 1, np.int64)
            np.cumsum(counts, out=first[1:])
            r = int(first[-1])
            buf = pool.get(r)
            o, d, t, w = buf[0][:r], buf[1][:r], buf[2][:r], buf[3][:r]
            fill_rays(P, plane, partner, ri, ci, valid, first, o, d, t, w)
            self.rays_refined += r
            out.append(RayJob(pairs[sl], first, o, d, t, w, buf, pool, r_idx[sl], c_idx[sl], True, str(s)))
        return out

    def _importance_jobs(self, pairs, r_idx, c_idx, s: int, pool: "RayBuffers", bent: bool):
        """Second-round jobs standing for ``s`` fixed segments: ``IMPORTANCE_PICKS[s]`` picks among
        the segments between the IMPORTANCE_DESIGN[s]^2 points of each patch (bent pairs: :func:`bent_points`
        and their triangles' normals; flat ones: :func:`sample_points` and the patch planes), in
        proportion to their kernel weight (segments.importance_picks); V = share of free picks."""
        md = IMPORTANCE_DESIGN[s]
        m = IMPORTANCE_PICKS[s]
        per = max(1, RAY_BATCH // m)
        name = f"{m} picked" + (" bent" if bent else "")
        for start in range(0, len(pairs), per):
            sl = slice(start, start + per)
            patches, inverse = np.unique(np.concatenate([r_idx[sl], c_idx[sl]]), return_inverse=True)
            k = len(r_idx[sl])
            ri, ci = inverse[:k].astype(np.int64), inverse[k:].astype(np.int64)
            plane = np.ascontiguousarray(self.plane[patches])
            if bent:
                P, N = self._bent_points(md, patches)
            else:
                P = self._points(md, patches)
                N = np.ascontiguousarray(np.repeat(plane[:, None, :3], md * md, axis=1))
            picks = np.empty((k, m), np.int64)
            counts = np.empty(k, np.int64)
            modes = np.empty(k, np.int8)
            importance_picks(P, N, plane, ri, ci, picks, counts, modes)
            first = np.zeros(k + 1, np.int64)
            np.cumsum(counts, out=first[1:])
            r = int(first[-1])
            buf = pool.get(r)
            o, d, t, w = buf[0][:r], buf[1][:r], buf[2][:r], buf[3][:r]
            fill_picked(P, N, plane, ri, ci, picks, modes, first, o, d, t, w)
            yield RayJob(pairs[sl], first, o, d, t, w, buf, pool, r_idx[sl], c_idx[sl], True, name)

    def _bent_points(self, m: int, patches: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Points of the m x m bent design (:func:`bent_points`) of ``patches``, offset off their
        triangles, and those triangles' normals."""
        key = ("bent", m)
        if key not in self._design_cache:
            pts, nrm = bent_points(self._scene, m)
            self._design_cache[key] = (np.ascontiguousarray(self._frame(pts) + self.offset * nrm),
                                       np.ascontiguousarray(nrm))
        P, N = self._design_cache[key]
        return np.ascontiguousarray(P[patches]), np.ascontiguousarray(N[patches])

    def _bent_jobs(self, pairs, r_idx, c_idx, s: int, pool: "RayBuffers", final: bool, weak=None):
        """Jobs for pairs with a bent patch: ``s`` segments between the points of :func:`bent_points`
        (paired as :func:`pairing`), valid where both ends leave the front of their own triangles and
        weighted by those triangles' cosines (segments.py). ``weak`` (bool per pair): one segment
        only (``RayBudget.one_ray_below``)."""
        m = check_samples(s)
        ka, kb = np.arange(s, dtype=np.int64), pairing(s)
        per = max(1, RAY_BATCH // len(ka))
        for start in range(0, len(pairs), per):
            sl = slice(start, start + per)
            patches, inverse = np.unique(np.concatenate([r_idx[sl], c_idx[sl]]), return_inverse=True)
            k = len(r_idx[sl])
            ri, ci = inverse[:k].astype(np.int64), inverse[k:].astype(np.int64)
            P, N = self._bent_points(m, patches)
            plane = np.ascontiguousarray(self.plane[patches])
            valid = np.empty((k, len(ka)), np.bool_)
            counts = np.empty(k, np.int64)
            flat_pair = np.empty(k, np.bool_)
            valid_rays_on_triangles(P, N, plane, ka, kb, ri, ci, valid, counts, flat_pair)
            if weak is not None and s > 1:
                _keep_one(valid, counts, np.flatnonzero(weak[sl]))
            first = np.zeros(k + 1, np.int64)
            np.cumsum(counts, out=first[1:])
            r = int(first[-1])
            buf = pool.get(r)
            o, d, t, w = buf[0][:r], buf[1][:r], buf[2][:r], buf[3][:r]
            fill_rays_on_triangles(P, N, plane, ka, kb, ri, ci, valid, first, flat_pair, o, d, t, w)
            yield RayJob(pairs[sl], first, o, d, t, w, buf, pool, r_idx[sl], c_idx[sl], final, f"{s} bent")

    def close(self) -> None:
        self.caster.close()


def _keep_one(valid: np.ndarray, counts: np.ndarray, pairs: np.ndarray) -> None:
    """Pairs ``pairs`` (rows of ``valid``) keep only their first valid segment (too weak to matter)."""
    first_valid = valid[pairs].argmax(axis=1)
    valid[pairs] = False
    valid[pairs, first_valid] = True
    counts[pairs] = 1


def bent_points(scene, m: int) -> tuple[np.ndarray, np.ndarray]:
    """(n, m^2, 3) points of each clustered patch for the segments of bent pairs, and the normals of
    their triangles.

    Point k lies in the triangle where the patch's cumulative area reaches (k + 1/2) / m^2 of the
    total (as :func:`sample_points`), at (u, g_k) of the unit square mapped onto that triangle by the
    area-preserving warp (sqrt(u) on the edge from its first corner): u the position of (k + 1/2) / m^2
    within that triangle's share of the area, g_k = frac(1/2 + k / golden ratio). Points so reach
    into a fold's corners and up to its edges, where the centroids of :func:`sample_points` do not:
    with those, 24 rows of Sponza at 3,129 patches (its 10 worst and 14 others) reached 1.093 against
    1.00 from ray shooting, 7 of them more than 0.02 over; with these, 1.023 and one.
    """
    tri = np.asarray(scene.triangles, np.float64)
    s = m * m
    start, index = scene.patch_triangles
    ta = scene.triangle_areas[index]
    cum = np.cumsum(ta)
    before = np.r_[0.0, cum][start[:-1]]
    target = before[:, None] + (np.arange(s) + 0.5)[None, :] / s * scene.areas[:, None]
    k = np.clip(np.searchsorted(cum, target, side="right"), start[:-1, None], start[1:, None] - 1)
    u = np.sqrt(np.clip((target - (cum[k] - ta[k])) / ta[k], 0.0, 1.0))
    g = np.mod(0.5 + np.arange(s) * 0.6180339887498949, 1.0)[None, :]
    w = np.stack([1.0 - u, u * (1.0 - g), u * g], axis=-1)
    return np.einsum("nsk,nskd->nsd", w, tri[index[k]]), scene.triangle_normals[index[k]]


def bent_patches(scene, plane: np.ndarray, tri: np.ndarray, offset: float) -> np.ndarray:
    """(n,) bool: clustered patches with a triangle corner farther than ``BENT_DEPTH`` times the
    patch's diameter (and the points' offset) from its mean plane ``plane`` (frame units)."""
    start, index = scene.patch_triangles
    if not len(index):
        return np.zeros(scene.n_patches, np.bool_)
    t = tri[index]  # (m, 3, 3), each patch's triangles contiguous
    owner = np.repeat(np.arange(scene.n_patches), np.diff(start))
    depth = np.abs(np.einsum("tkd,td->tk", t, plane[owner, :3]) - plane[owner, 3, None]).max(axis=1)
    depth = np.maximum.reduceat(depth, start[:-1])
    lo = np.minimum.reduceat(t.min(axis=1), start[:-1], axis=0)
    hi = np.maximum.reduceat(t.max(axis=1), start[:-1], axis=0)
    return depth > BENT_DEPTH * np.linalg.norm(hi - lo, axis=1) + 2 * offset


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


def _patch_boxes(scene, tri: np.ndarray, pad: float) -> tuple[np.ndarray, np.ndarray]:
    """(n, 3) lower and upper corners of each patch's bounding box (frame units), padded by ``pad``."""
    lo = tri.min(axis=1) - pad if len(tri) else np.zeros((0, 3))
    hi = tri.max(axis=1) + pad if len(tri) else np.zeros((0, 3))
    if scene.is_clustered and len(tri):
        start, index = scene.patch_triangles
        lo = np.minimum.reduceat(lo[index], start[:-1], axis=0)
        hi = np.maximum.reduceat(hi[index], start[:-1], axis=0)
    return np.ascontiguousarray(lo), np.ascontiguousarray(hi)


def _pack_bits(flags: np.ndarray, words: int) -> np.ndarray:
    """(p, m) bool -> (p, words) uint64, bit t % 64 of word t // 64."""
    p, m = flags.shape
    padded = np.zeros((p, words * 64), np.bool_)
    padded[:, :m] = flags
    by = np.packbits(padded.reshape(p, words, 64), axis=2, bitorder="little")  # (p, words, 8)
    return np.ascontiguousarray(by).view(np.uint64).reshape(p, words)


def _needs_rays(F, rows, cols, front, back, below, above, cull, need, bits=None):
    """need[r, c]: F > 0 and some occluder can cut the pair's segments (bitwise test).
    ``bits``: :func:`~hfrad.formfactors.probing.one_word_bits` of the masks when the caller keeps them."""
    if cull and front.shape[1] == 1:  # at most 64 occluders: one word per mask
        bits = one_word_bits(front, back, below, above) if bits is None else bits
        _needs_rays_one_word(F, rows, cols, bits, np.ascontiguousarray(bits[cols].T), need)
    else:
        _needs_rays_words(F, rows, cols, front, back, below, above, cull, need)


@njit(parallel=True, cache=True, nogil=True)
def _needs_rays_one_word(F, rows, cols, bits, col_bits, need):
    """:func:`_needs_rays` with one 64-bit word per mask: ``bits`` (n, 8) = front, back, below (3
    axes), above (3 axes) of each patch, ``col_bits`` the columns' rows of it, transposed (8, nc)
    (the same test as :func:`~hfrad.formfactors.probing.cuttable`, the row's words loaded once)."""
    for r in prange(rows.shape[0]):
        i = rows[r]
        f, b = bits[i, 0], bits[i, 1]
        lx, ly, lz, ax, ay, az = bits[i, 2], bits[i, 3], bits[i, 4], bits[i, 5], bits[i, 6], bits[i, 7]
        for c in range(cols.shape[0]):
            if not F[r, c] > 0.0:
                need[r, c] = False
                continue
            need[r, c] = cuttable_one_word(f, b, lx, ly, lz, ax, ay, az, col_bits, c)


@njit(parallel=True, cache=True, nogil=True)
def _needs_rays_words(F, rows, cols, front, back, below, above, cull, need):
    """:func:`_needs_rays`, any number of words per mask (or no culling)."""
    for r in prange(rows.shape[0]):
        i = rows[r]
        for c in range(cols.shape[0]):
            need[r, c] = F[r, c] > 0.0 and (not cull or cuttable(i, cols[c], front, back, below, above))


@njit(parallel=True, cache=True, nogil=True)
def _partial_and_large(F, pairs, first, hit, r_idx, c_idx, areas, C, D, near, above, large, refine_below,
                       large_below, out):
    """out[p]: 1 if the rays of pair p disagree, or the patches are close, and max(F_ij, F_ji) > above;
    2 if moreover max(F_ij, F_ji) > large; else 0. The ray budget's thresholds on A_i F_ij lower
    that: 0 below ``refine_below``, at most 1 below ``large_below`` (RayBudget; 0 = off).

    Close: centroid distance below near * (D_i + D_j); rays between near
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
        out[p] = 0
        if (0 < blocked < total) or _close(C, D, near, i, j):
            out[p] = _refine_level(F[pairs[p]] * areas[i], min(areas[i], areas[j]), above, large, refine_below,
                                   large_below)


@njit(parallel=True, cache=True, nogil=True)
def _close_level(F, pairs, r_idx, c_idx, areas, C, D, near, above, large, refine_below, large_below, out):
    """out[p]: the second round :func:`_partial_and_large` gives pair p whatever its first rays say
    (its patches are close), else 0."""
    for p in prange(pairs.shape[0]):
        i = r_idx[p]
        j = c_idx[p]
        out[p] = 0
        if _close(C, D, near, i, j):
            out[p] = _refine_level(F[pairs[p]] * areas[i], min(areas[i], areas[j]), above, large, refine_below,
                                   large_below)


@njit(cache=True, inline="always")
def _close(C, D, near, i, j):
    """Centroid distance below near * (D_i + D_j) (symmetric)."""
    dx = C[i, 0] - C[j, 0]
    dy = C[i, 1] - C[j, 1]
    dz = C[i, 2] - C[j, 2]
    return dx * dx + dy * dy + dz * dz < (near * (D[i] + D[j])) ** 2


@njit(cache=True, inline="always")
def _refine_level(a, m, above, large, refine_below, large_below):
    """0, 1 or 2 (no second round, REFINE_SAMPLES, REFINE_LARGE_SAMPLES) for a pair that asks for one,
    from a = A_i F_ij and m = min(A_i, A_j): see :func:`_partial_and_large`."""
    if a < refine_below:
        return 0
    if a > large * m and a >= large_below:
        return 2
    if a > above * m:
        return 1
    return 0


@njit(parallel=True, cache=True, nogil=True)
def _scale_by_visibility(F, pairs, first, hit, w, skip):
    """F[pairs[p]] *= the kernel-weighted fraction of the rays first[p]:first[p+1] that are not
    blocked (sum of w over the free rays / sum of w), unless skip[p]; a pair with no blocked ray
    keeps F as it is, and one whose weights are all 0 takes the plain fraction."""
    for p in prange(pairs.shape[0]):
        if skip[p]:
            continue
        blocked = 0
        wall = 0.0
        wfree = 0.0
        for k in range(first[p], first[p + 1]):
            wall += w[k]
            if hit[k]:
                blocked += 1
            else:
                wfree += w[k]
        total = first[p + 1] - first[p]
        if blocked:
            if wall > 0.0:
                F[pairs[p]] *= wfree / wall
            else:
                F[pairs[p]] *= 1.0 - blocked / total
