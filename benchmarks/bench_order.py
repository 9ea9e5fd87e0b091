"""Benchmark: patch ordering (Z-order, Hilbert, random, input) for HF time and rank.

The cached F of each case is permuted by each ordering (rows and columns alike) and
factored by the same one-pass HF (float32, blocks of 256) in the same run. METHOD.md
section 4: on a 10K Cornell box the prototype saw random order ~2.5x slower than Z-order.
``leaf_rank`` is the mean rank of the leaf SVDs (how compressible one column block is).

Run:  python benchmarks/bench_order.py --quick
      python benchmarks/bench_order.py --scenes cornell --sizes 10000
Writes benchmarks/results/order[-SUFFIX].json.
"""

from __future__ import annotations

import argparse
import gc
import sys
import time

import numpy as np

import common
from hfrad.lowrank.hf import hierarchical_factorization

ORDERS = ("zorder", "hilbert", "random", "input")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scenes", default="cornell,cbox-original")
    p.add_argument("--sizes", default="2500,10000")
    p.add_argument("--eps", default="0.05,0.02")
    p.add_argument("--orders", default=",".join(ORDERS))
    p.add_argument("--block-size", type=int, default=256)
    p.add_argument("--dtype", default="float32", choices=("float32", "float64"))
    p.add_argument("--repeat", type=int, default=2)
    p.add_argument("--quick", action="store_true", help="2500 patches, Cornell box only")
    p.add_argument("--out", default="order")
    common.add_blas_arg(p)
    args = p.parse_args(argv)
    if args.quick:
        args.scenes, args.sizes = "cornell", "2500"
    scenes, sizes = common.parse_list(args.scenes), common.parse_sizes(args.sizes)
    eps_list, orders = common.parse_list(args.eps, float), common.parse_list(args.orders)
    dtype = np.dtype(args.dtype)
    mach = common.header("Patch ordering: HF time and rank", args.blas_threads)
    t_start = time.perf_counter()
    rows = []
    for scene in scenes:
        for size in sizes:
            case = common.load_case(scene, size)
            n, b = case.n, args.block_size
            for order in orders:
                G = case.G(case.perm(order, rng=0), dtype)
                for eps in eps_list:
                    def go():
                        return hierarchical_factorization((G[:, a:a + b] for a in range(0, n, b)), n,
                                                          eps=eps, dtype=dtype, n_blocks=-(-n // b))
                    t = common.best_of(go, args.repeat, max_seconds=60)
                    lr = t.result
                    rows.append({"scene": scene, "n": n, "eps": eps, "order": order, "time": t.best,
                                 "times": t.times, "rank": lr.rank, "rel_err": lr.relative_error,
                                 "leaf_rank": float(np.mean(lr.info["leaf_ranks"])),
                                 "time_leaf": lr.info["time_leaf"], "time_merge": lr.info["time_merge"],
                                 "loadavg": common.check_load()})
                    print(f"  {scene} n={n} eps={eps} {order}: {t.best:.2f} s rank {lr.rank}",
                          file=sys.stderr, flush=True)
                del G
                gc.collect()
    for r in rows:   # ratios to Z-order of the same case, same run
        z = next((q for q in rows if (q["scene"], q["n"], q["eps"], q["order"]) ==
                  (r["scene"], r["n"], r["eps"], "zorder")), None)
        if z:
            r["time/zorder"] = r["time"] / z["time"]
            r["rank/zorder"] = r["rank"] / z["rank"]
    common.print_table("HF by patch order (time/zorder > 1: Z-order faster)", rows,
                       ["scene", "n", "eps", "order", "time", "time/zorder", "rank", "rank/zorder",
                        "leaf_rank", "time_leaf", "time_merge", "rel_err", "loadavg"])
    path = common.write_json(args.out, {"benchmark": "order", "machine": mach, "args": vars(args),
                                        "wall_seconds": time.perf_counter() - t_start, "rows": rows})
    print(f"\nwrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
