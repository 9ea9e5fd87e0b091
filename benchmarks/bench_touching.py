"""Benchmark: the clustered kernel's touching rule, cost and error against a tight reference.

A shared scene is loaded and clustered as ``hfrad precompute --area-light 50,50,50 --patches N``
does (the pickle of ``bench_visibility_rounds.py``); its *touching* pairs are those the clustered
kernel gives to the touching rule (centroids closer than EXACT_NEAR (D_P + D_Q), at most
EXACT_PAIRS triangle pairs). On the touching pairs of ``--rows`` rows spread over the patches:

- the reference: kernel.py's adaptive rule on every triangle pair that is not back to back,
  whatever its distance, at tolerance 1e-5 (MAX_DEPTH 8; cached in the temporary folder);
- the old rule: kernel.py's rules per triangle pair (``_pair_area_ff`` at CLUSTER_TOLERANCE, the
  touching rule until KERNEL_VERSION 11);
- the touching rule (``clustered.touching_pairs``) with each ``--rules`` (c1_from, q3_from, gap, slack,
  families).

Errors: sum |error| / sum of the reference (the touching pairs' total), signed sum / total, and per
row the sum of its touching pairs' errors over the row's A_i sum_j F_ij (the clustered kernel's row
without visibility): max and mean over the rows. Evaluations of eq. (1) a pair (the new rule's
counter). ``--time``: CPU seconds of each rule over all touching pairs of the scene on one thread,
old and new alternated ``--repeat`` times.

Run:  python benchmarks/bench_touching.py [--scene conference] [--rows 40] [--rules '[[1,0,0.1]]'] [--time]
      [--repeat 2] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numba
import numpy as np
from bench_cluster_rules import rule_of_pairs
from bench_visibility_rounds import scene_of
from numba import njit, prange

from hfrad.formfactors import clustered as cl
from hfrad.formfactors import kernel as kn


@njit(parallel=True)
def _reference(I, J, T, N, A, start, eps, tol, out):
    for k in prange(I.shape[0]):
        total = 0.0
        for t in range(start[I[k]], start[I[k] + 1]):
            for u in range(start[J[k]], start[J[k] + 1]):
                if A[t] <= 0.0 or A[u] <= 0.0 or kn._behind(t, u, T, N, eps) or kn._behind(u, t, T, N, eps):
                    continue
                p, q = kn._point_side(t, u, T, N, A, eps, False)
                total += kn._adaptive_area_ff(p, q, T, N, A, eps, tol)
        out[k] = total


@njit
def _old(I, J, T, N, A, C, D, start, index, eps, tol, out):
    for k in range(I.shape[0]):
        out[k] = kn._pair_area_ff(I[k], J[k], T, N, A, C, D, start, index, kn.NEAR, kn.ADAPTIVE, eps, tol)


#: (c1_from, q3_from, gap, slack, families) under which the touching rule takes kernel.py's choices per
#: triangle pair (the 6-point rule from ADAPTIVE = 1.5 (D_t + D_u), both rules and the 4-split nearer, no
#: shared budget): the old rule's count of contour integrals (its values agree to ~1e-15).
OLD_RULES = (kn.NEAR, kn.NEAR, kn.ADAPTIVE - 2.0 / 3.0, 0.0, 0.0)


def old_rule(g: cl.ClusterGeometry, I: np.ndarray, J: np.ndarray) -> np.ndarray:
    """The touching rule before KERNEL_VERSION 11: kernel.py's rules per triangle pair."""
    out = np.empty(len(I))
    _old(I, J, g.triangles, g.tri_normals, g.tri_areas, g.tri_centroids, g.tri_diameters, g.start,
         np.arange(len(g.triangles), dtype=np.int64), g.eps, g.tolerance, out)
    return out


def touching(g: cl.ClusterGeometry) -> tuple[np.ndarray, np.ndarray]:
    """(I, J), I < J: every touching pair of the scene."""
    I, J = [], []
    for lo in range(0, g.n, 256):
        rows = np.arange(lo, min(g.n, lo + 256))
        r, c = np.nonzero(rule_of_pairs(g, rows) == 4)
        keep = rows[r] < c
        I.append(rows[r][keep])
        J.append(c[keep])
    return np.concatenate(I).astype(np.int64), np.concatenate(J).astype(np.int64)


def errors(v: np.ndarray, ref: np.ndarray, si, sj, rows, row_af) -> dict:
    e = v - ref
    per_row = np.array([e[(si == r) | (sj == r)].sum() for r in rows])
    ok = row_af > 0
    rel = np.abs(per_row[ok] / row_af[ok])
    return {"abs_of_total": float(np.abs(e).sum() / ref.sum()), "signed_of_total": float(e.sum() / ref.sum()),
            "row_max": float(rel.max()), "row_mean": float(rel.mean())}


def one_thread_seconds(run) -> float:
    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        t = time.process_time()
        run()
        return time.process_time() - t
    finally:
        numba.set_num_threads(threads)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="conference")
    ap.add_argument("--patches", type=int, default=3000)
    ap.add_argument("--rows", type=int, default=40)
    ap.add_argument("--rules", default=json.dumps([list(cl.TOUCHING_RULES)]),
                    help="JSON list of (c1_from, q3_from, gap, slack, families)")
    ap.add_argument("--time", action="store_true", help="also time old and new over all touching pairs, one thread")
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--json", help="also write the results to this file")
    args = ap.parse_args()
    scene = scene_of(args.scene, args.patches)
    g = cl.ClusterGeometry(scene, memo=False)
    I, J = touching(g)
    rows = np.linspace(0, g.n - 1, args.rows).astype(np.int64)
    sel = np.isin(I, rows) | np.isin(J, rows)
    si, sj = I[sel], J[sel]
    cache = Path(tempfile.gettempdir()) / f"hfrad-touching-ref-{args.scene}-{g.n}-{args.rows}.npy"
    if cache.exists():
        ref = np.load(cache)
    else:
        ref = np.empty(len(si))
        _reference(si, sj, g.triangles, g.tri_normals, g.tri_areas, g.start, g.eps, 1e-5, ref)
        np.save(cache, ref)
    row_af = cl.clustered_block(g, rows, np.arange(g.n)).sum(axis=1) * g.areas[rows]
    out = {"scene": args.scene, "patches": g.n, "touching_pairs": len(I), "sample_pairs": len(si),
           "rows": args.rows, "old": errors(old_rule(g, si, sj), ref, si, sj, rows, row_af), "new": []}
    v, c = cl.touching_pairs(g, si, sj, rules=OLD_RULES, count=True)
    out["old"]["evaluations_a_pair"] = float(c.mean())
    out["old"]["agrees_with_old_rules"] = float(np.abs(v - old_rule(g, si, sj)).max() / ref.max())
    for rules in json.loads(args.rules):
        v, c = cl.touching_pairs(g, si, sj, rules=rules, count=True)
        out["new"].append({"rules": rules, "evaluations_a_pair": float(c.mean()),
                           **errors(v, ref, si, sj, rows, row_af)})
    if args.time:
        rules = np.asarray(json.loads(args.rules)[0], np.float64)
        old_rule(g, I[:2], J[:2])
        cl.touching_pairs(g, I[:2], J[:2], rules=rules)
        out["cpu_s"] = {"old": [], "new": []}
        for _ in range(args.repeat):
            out["cpu_s"]["old"].append(one_thread_seconds(lambda: old_rule(g, I, J)))
            out["cpu_s"]["new"].append(one_thread_seconds(lambda: cl.touching_pairs(g, I, J, rules=rules)))
    print(json.dumps(out, indent=1))
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
