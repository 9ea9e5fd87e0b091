"""Benchmark: ACA (formfactors/aca.py) over the far blocks of a k-d cluster tree of the Cornell box.

The tree and its far blocks are the H-matrix's (``hmatrix.cluster_tree``: median split of the
patch centroids along the longest side of their box, leaves of at most ``--leaf`` patches;
``hmatrix.block_partition``: far when the gap between the boxes is at least ``--eta`` x the larger
diagonal). ``--blocks`` far blocks are drawn at random (seed 0) and factored by one
``aca_blocks`` call at each ``--tol`` (after one untimed call, which compiles or loads numba's
cache); a subset (``--check``) is compared with the dense block (the kernel's block function).

Printed: far blocks in the tree, sampled ones, their entries (sum m b), entries evaluated by ACA
and their fraction, time, time per entry evaluated and per block, ranks (mean, max), blocks not
ok, the measured relative Frobenius error on the checked subset (median, max), and the dense
block function's time per entry on the same subset for comparison.

Run:  python benchmarks/bench_aca.py [--patches 40000] [--blocks 10000] [--tol 1e-2 1e-3] [--max-rank 64]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from hfrad.formfactors.aca import aca_blocks
from hfrad.formfactors.clustered import kernel_for
from hfrad.formfactors.farfield import patch_boxes
from hfrad.formfactors.hmatrix import block_partition, cluster_tree
from hfrad.scene.load import load_scene


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--patches", type=int, default=40000)
    ap.add_argument("--blocks", type=int, default=10000)
    ap.add_argument("--leaf", type=int, default=32)
    ap.add_argument("--eta", type=float, default=0.5)
    ap.add_argument("--tol", type=float, nargs="+", default=[1e-2, 1e-3])
    ap.add_argument("--max-rank", type=int, default=64)
    ap.add_argument("--check", type=int, default=200)
    args = ap.parse_args()

    scene = load_scene("cornell", patches=args.patches)
    geometry, block = kernel_for(scene)
    t0 = time.perf_counter()
    lo, hi = patch_boxes(scene)
    tree = cluster_tree(scene.centroids, lo, hi, args.leaf)
    far_r, far_c, _, _ = block_partition(tree, args.eta)
    pairs = list(zip(far_r, far_c))
    print(f"{scene.n_patches} patches; tree and {len(pairs)} far blocks in {time.perf_counter() - t0:.1f} s")
    rng = np.random.default_rng(0)
    pick = rng.choice(len(pairs), min(args.blocks, len(pairs)), replace=False)
    rows = [tree.perm[tree.start[pairs[k][0]]:tree.stop[pairs[k][0]]] for k in pick]
    cols = [tree.perm[tree.start[pairs[k][1]]:tree.stop[pairs[k][1]]] for k in pick]
    m = np.array([len(r) for r in rows])
    b = np.array([len(c) for c in cols])
    R, C = np.concatenate(rows), np.concatenate(cols)
    rp, cp = np.concatenate([[0], np.cumsum(m)]), np.concatenate([[0], np.cumsum(b)])
    entries = int((m * b).sum())
    print(f"{len(pick)} blocks drawn: m {m.min()}..{m.max()}, b {b.min()}..{b.max()}, {entries:,} entries")
    aca_blocks(geometry, R[:m[0]], rp[:2], C[:b[0]], cp[:2], args.tol[0], args.max_rank)   # compile / load
    check = rng.choice(len(pick), min(args.check, len(pick)), replace=False)
    block(geometry, rows[0][:1], cols[0][:1])                                            # load numba's cache
    t = time.perf_counter()
    dense = [block(geometry, rows[k], cols[k]) for k in check]
    dense_time = time.perf_counter() - t
    dense_entries = sum(d.size for d in dense)
    for tol in args.tol:
        t = time.perf_counter()
        res = aca_blocks(geometry, R, rp, C, cp, tol, args.max_rank)
        elapsed = time.perf_counter() - t
        ev = int(res.evaluated.sum())
        errors = []
        for d, k in zip(dense, check):
            U, V = res.factors(k)
            norm = np.linalg.norm(d)
            if norm > 0 and res.ok[k]:
                errors.append(np.linalg.norm(d - U.astype(float) @ V.astype(float).T) / norm)
        print(f"tol {tol:g}: {elapsed:.2f} s, evaluated {ev:,} ({ev / entries:.2%} of the blocks' entries), "
              f"{elapsed / ev * 1e9:.0f} ns/entry evaluated, {elapsed / len(pick) * 1e6:.0f} us/block; "
              f"rank mean {res.ranks.mean():.2f} max {res.ranks.max()} (ACA's {res.aca_ranks.mean():.2f}), "
              f"rank 0: {(res.ranks == 0).sum()}, not ok: {(~res.ok).sum()}; "
              f"error/tol on {len(errors)} checked non-zero blocks: median {np.median(errors) / tol:.2f} "
              f"max {np.max(errors) / tol:.2f}; U+V {(res.U.nbytes + res.V.nbytes) / 1e6:.1f} MB")
    print(f"dense block function on the {len(check)} checked blocks: {dense_entries:,} entries, "
          f"{dense_time:.2f} s, {dense_time / dense_entries * 1e9:.1f} ns/entry")


if __name__ == "__main__":
    main()
