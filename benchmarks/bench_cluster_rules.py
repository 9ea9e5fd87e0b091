"""Benchmark: the clustered kernel's rules, cost and error against an all-triangle-pairs reference.

A shared scene is loaded and clustered as ``hfrad precompute --area-light 50,50,50 --patches N``
does; 24 rows spread over the patches (``--rows``) are computed (no visibility) by

- the clustered kernel (``formfactors/clustered.py``, options as JSON, e.g. ``'{"point_far": 1e9}'``
  for eq. (1) on every triangle of eq. (3)), and
- the reference: kernel.py's per-triangle-pair rules over every triangle pair of the two patches,
  tightened (adaptive path below 4 (D_t + D_u), tolerance 1e-4; point to point only beyond 12).

It prints the relative Frobenius error of the rows, and per rule (far, quadrants, middle, near,
touching) the share of pairs, the error's contribution and its relative size within the rule, the
rule's share of the rows' norm and its CPU time per pair (one thread, the rule's pairs one by one).

With ``--pass`` it also times the kernel as a precompute's pass asks for it: every column block of
256 in Z-order against all rows but those the reciprocity copy takes (blocks 8 or more before),
CPU seconds on one thread, with and without the memo (``ClusterGeometry(memo=False)``), and the
pairs of each rule that the pass computes.

Run:  python benchmarks/bench_cluster_rules.py [--scene sponza] [--patches 3000] [--rows 24] [--options JSON]
      [--pass] [--json FILE]
The reference is cached in the temporary folder (``hfrad-cluster-rules-ref-<scene>-<n>[-<rows>].npy``;
Sponza at 3K: ~15 s for 24 rows, ~5 min for 200). 24 rows are too few to rank variants of a rule whose
error is a few large pairs: the near rule's points by a Morton curve over each patch measured
4.77% -> 3.69% on 24 rows of Sponza, 4.56% -> 5.08% on 200.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import common
import numpy as np
from numba import njit

from hfrad.formfactors import clustered as cl
from hfrad.formfactors.kernel import PatchGeometry, unoccluded_block
from hfrad.scene.load import load_scene

SCENES = {
    "sponza": (common.SHARED_SCENES / "sponza-dabrovic" / "sponza.obj", {}),
    "sibenik": (common.SHARED_SCENES / "sibenik" / "sibenik.obj", {}),
    "conference": (common.SHARED_SCENES / "conference" / "conference.ply", {"unit_scale": 0.01}),
}
RULES = ("far", "quadrants", "middle", "near", "touching")


@njit
def _pairs(T, N, start, K, A, S, C, D, M, MN, MS, MW, Q, QN, W, pi, pj, far, near, eps, TA, TC, TD,
           TR, tol, exact, exact_near, far2):
    total = 0.0
    for k in range(pi.shape[0]):
        total += cl._cluster_pair_area_ff(pi[k], pj[k], T, N, start, K, A, S, C, D, M, MN, MS, MW, Q, QN, W, far,
                                          near, eps, TA, TC, TD, TR, tol, exact, exact_near, far2)
    return total


def pairs_seconds(g: cl.ClusterGeometry, pi: np.ndarray, pj: np.ndarray) -> float:
    """CPU seconds of the pairs (pi[k], pj[k]) one by one on one thread (best of 2)."""
    def run(a, b):
        return _pairs(g.triangles, g.tri_normals, g.start, g.scale_kept, g.areas, g.area_vectors, g.centroids,
                      g.diameters, g.mid_points, g.mid_normals, g.mid_vectors, g.mid_weights, g.points,
                      g.point_normals, g.weights, a, b, g.far, g.near, g.eps, g.tri_areas, g.tri_centroids,
                      g.tri_diameters, g.touching_rules, g.tolerance, g.exact_pairs, g.exact_near, g.point_far ** 2)
    run(pi[:1], pj[:1])
    best = np.inf
    for _ in range(2):
        t = time.process_time()
        run(pi, pj)
        best = min(best, time.process_time() - t)
    return best


def rule_of_pairs(g: cl.ClusterGeometry, rows: np.ndarray) -> np.ndarray:
    """(rows, n) int in 0..4: the rule (RULES) of each pair, as _cluster_pair_area_ff chooses it."""
    cnt = np.diff(g.start)
    d2 = ((g.centroids[rows][:, None] - g.centroids[None]) ** 2).sum(-1)
    reach = g.diameters[rows][:, None] + g.diameters[None]
    single = (cnt[rows][:, None] == 1) & (cnt[None] == 1)
    rule = np.full(d2.shape, 3)
    rule[(d2 < (g.exact_near * reach) ** 2) & (cnt[rows][:, None] * cnt[None] <= g.exact_pairs)] = 4
    rule[d2 >= (g.near * reach) ** 2] = 2
    rule[~single & (d2 >= (0.5 * g.far * reach) ** 2)] = 1
    rule[~single & (d2 >= (g.far * reach) ** 2)] = 0
    return rule


def pass_seconds(scene, options: dict) -> dict:
    """CPU seconds (one thread) of the kernel over a precompute's pass, memo off and on (see the docstring)."""
    import numba

    from hfrad.formfactors.mirror import MIRROR_LAG
    from hfrad.precompute.options import plan_precompute

    plan = plan_precompute(scene)
    perm, b, n = plan.perm, plan.block_size, scene.n_patches
    starts = list(range(0, n, b))
    out = {"block_size": b, "mirror_lag": MIRROR_LAG}
    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        for memo in (False, True):
            g = cl.ClusterGeometry(scene, **options, memo=memo)
            cl.clustered_block(g, perm[:1], perm[:1])          # compiled before the clock starts
            g = cl.ClusterGeometry(scene, **options, memo=memo)
            t = time.process_time()
            for k, lo in enumerate(starts):
                copied = starts[k - MIRROR_LAG] if k >= MIRROR_LAG else 0   # rows of blocks < k - lag
                cl.clustered_block(g, perm[copied:], perm[lo:lo + b])
            out["memo" if memo else "plain"] = time.process_time() - t
    finally:
        numba.set_num_threads(threads)
    rule = rule_of_pairs(g, perm)[:, perm]
    blk = np.arange(n) // b
    computed = ~(blk[:, None] < blk[None, :] - MIRROR_LAG)
    out["pairs_computed"] = {name: int((computed & (rule == k)).sum()) for k, name in enumerate(RULES)}
    out["pairs"] = {name: int((rule == k).sum()) for k, name in enumerate(RULES)}
    out["memo_pairs"] = int(len(g.memo_cols))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="sponza", choices=sorted(SCENES))
    ap.add_argument("--patches", type=int, default=3000)
    ap.add_argument("--rows", type=int, default=24, help="rows compared with the reference")
    ap.add_argument("--options", default="{}", help="ClusterGeometry keyword arguments as JSON")
    ap.add_argument("--pass", dest="whole_pass", action="store_true",
                    help="also time the kernel over a precompute's pass, memo off and on")
    ap.add_argument("--json", help="also write the results to this file")
    args = ap.parse_args()
    path, kw = SCENES[args.scene]
    scene = load_scene(str(path), area_light=(50, 50, 50), patches=args.patches, **kw)
    g = cl.ClusterGeometry(scene, **json.loads(args.options))
    rows = np.linspace(0, g.n - 1, args.rows).astype(np.int64)
    cols = np.arange(g.n)
    tail = "" if args.rows == 24 else f"-{args.rows}"
    cache = Path(tempfile.gettempdir()) / f"hfrad-cluster-rules-ref-{args.scene}-{g.n}{tail}.npy"
    if cache.exists():
        ref = np.load(cache)
    else:
        ref = unoccluded_block(PatchGeometry(scene, near=12.0, adaptive=4.0, tolerance=1e-4), rows, cols)
        np.save(cache, ref)
    F = cl.clustered_block(g, rows, cols)
    err, norm = F - ref, np.linalg.norm(ref)
    rule = rule_of_pairs(g, rows)
    out = {"scene": args.scene, "patches": g.n, "rows": args.rows, "options": json.loads(args.options),
           "relative_error": float(np.linalg.norm(err) / norm), "rules": {}}
    for k, name in enumerate(RULES):
        m = rule == k
        r, c = np.nonzero(m)
        seconds = pairs_seconds(g, rows[r], c.astype(np.int64)) if m.any() else 0.0
        out["rules"][name] = {"pairs": float(m.mean()), "error": float(np.linalg.norm(err[m]) / norm),
                              "error_in_rule": float(np.linalg.norm(err[m]) / max(np.linalg.norm(ref[m]), 1e-300)),
                              "norm_share": float(np.linalg.norm(ref[m]) / norm),
                              "us_per_pair": 1e6 * seconds / max(m.sum(), 1)}
    if args.whole_pass:
        out["pass"] = pass_seconds(scene, json.loads(args.options))
    print(json.dumps(out, indent=1))
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
