"""Benchmark: HF against LAPACK full SVD, randomized SVD and a single-pass sketch, on the same G.

For each scene and size, G = diag(rho_max) F is built once in Z-order (from the cached F,
see common.load_case) and every method factors that same matrix in the same run:

* ``hf32`` / ``hf64``: one-pass hierarchical factorization (hfrad.lowrank.hf), blocks of 256
  columns, float32 / float64;
* ``svd32`` / ``svd64``: LAPACK thin SVD (scipy ``gesdd``) of the whole matrix, then the
  smallest rank within eps. One SVD serves every eps (the truncation is free), so its time
  is the same on every eps row. Skipped above ``--svd-max-n`` (O(n^3));
* ``rsvd``: randomized SVD (Halko et al., 2 power iterations), sample size grown by 1.5x
  until eps is met (float32); ``passes`` counts passes over G;
* ``sketch``: single-pass sketch (Tropp et al. 2017) grown until eps is met, each attempt =
  1 sketch pass + 1 verification pass (float32).

``k_opt`` is the optimal rank at the target eps, from the float64 SVD when it ran (else the
float32 one); ``k_opt@err`` is the optimal rank at the error HF actually achieved (equal
achieved error). Ratios are of times measured in this run.

Run:  python benchmarks/bench_factorize.py --quick
      python benchmarks/bench_factorize.py --scenes cornell --sizes 10000,20000
Writes benchmarks/results/factorize[-SUFFIX].json.
"""

from __future__ import annotations

import argparse
import gc
import math
import sys
import time

import numpy as np
import scipy.linalg as sla

import common
from hfrad.lowrank.baselines import randomized_factorization, sketch_factorization
from hfrad.lowrank.hf import hierarchical_factorization
from hfrad.lowrank.factors import truncation_rank

ALL_METHODS = ("hf32", "hf64", "svd32", "svd64", "rsvd", "sketch")


def true_error(G: np.ndarray, Q: np.ndarray, V: np.ndarray, chunk: int = 1024) -> float:
    """||G - Q V^T||_F computed explicitly in float64 (chunked over columns)."""
    tot = 0.0
    Q64 = Q.astype(np.float64)
    for a in range(0, G.shape[1], chunk):
        D = G[:, a:a + chunk].astype(np.float64) - Q64 @ V[a:a + chunk].astype(np.float64).T
        tot += float(np.sum(D * D))
    return math.sqrt(tot)


def run_hf(G, eps, block_size, dtype, repeat):
    n = G.shape[0]
    m = -(-n // block_size)

    def go():
        return hierarchical_factorization((G[:, a:a + block_size] for a in range(0, n, block_size)), n,
                                          eps=eps, dtype=dtype, n_blocks=m)
    return common.best_of(go, repeat, max_seconds=60)


def full_svd(G, repeat):
    def go():
        return sla.svd(G, full_matrices=False, lapack_driver="gesdd", check_finite=False)
    t = common.best_of(go, repeat, max_seconds=60)
    U, s, Wt = t.result
    return t, U, s, Wt


def bench_case(scene: str, patches: int, args) -> list[dict]:
    case = common.load_case(scene, patches)
    n = case.n
    perm = case.perm("zorder")
    methods = args.methods
    G32 = case.G(perm, np.float32)
    G64 = case.G(perm, np.float64) if {"hf64", "svd64"} & set(methods) else None
    norm2 = float(np.sum(np.square(G32, dtype=np.float64)))
    print(f"\n[{scene} n={n}] ||G||_F = {math.sqrt(norm2):.4g}", file=sys.stderr, flush=True)
    rows: list[dict] = []
    svd = {}
    for name, G in (("svd64", G64), ("svd32", G32)):
        if name not in methods:
            continue
        if n > args.svd_max_n:
            print(f"  {name}: skipped (n = {n} > --svd-max-n {args.svd_max_n}; O(n^3))", file=sys.stderr)
            continue
        t, U, s, Wt = full_svd(G, 1)
        del U, Wt
        gc.collect()
        svd[name] = {"time": t.best, "s": s.astype(np.float64)}
        print(f"  {name}: {t.best:.2f} s", file=sys.stderr, flush=True)
    s_ref = svd.get("svd64", svd.get("svd32", {})).get("s")
    for eps in args.eps:
        target2 = eps * eps * norm2
        k_opt = truncation_rank(s_ref, target2)[0] if s_ref is not None else None
        base = {"scene": scene, "n": n, "eps": eps, "k_opt": k_opt}
        for name in methods:
            r = dict(base, method=name)
            if name in ("hf32", "hf64"):
                dt = np.float32 if name == "hf32" else np.float64
                t = run_hf(G32 if dt is np.float32 else G64, eps, args.block_size, dt, args.repeat)
                lr = t.result
                r.update(time=t.best, times=t.times, rank=lr.rank, rel_err=lr.relative_error,
                         time_leaf=lr.info["time_leaf"], time_merge=lr.info["time_merge"], passes=1)
                if s_ref is not None:
                    r["k_opt_at_err"] = truncation_rank(s_ref, (lr.achieved_error * (1 + 1e-9)) ** 2)[0]
                if n <= args.verify_max_n:
                    r["rel_err_true"] = true_error(G32 if dt is np.float32 else G64, lr.Q, lr.V) / math.sqrt(norm2)
            elif name in ("svd32", "svd64"):
                if name not in svd:
                    continue
                s = svd[name]["s"]
                k, d2 = truncation_rank(s, target2)
                r.update(time=svd[name]["time"], rank=k, rel_err=math.sqrt(d2 / norm2), passes=None)
            elif name == "rsvd":
                t = common.best_of(lambda: randomized_factorization(G32, eps=eps, dtype=np.float32, rng=0,
                                                                    n_power_iter=args.power_iter),
                                   args.repeat, max_seconds=10)
                lr = t.result
                r.update(time=t.best, times=t.times, rank=lr.rank, rel_err=lr.relative_error,
                         passes=lr.info["passes"], sample_size=lr.info["sample_size"])
            elif name == "sketch":
                t = common.best_of(lambda: sketch_factorization(G32, eps=eps, dtype=np.float32, rng=0,
                                                                block_size=args.block_size),
                                   args.repeat, max_seconds=10)
                lr = t.result
                r.update(time=t.best, times=t.times, rank=lr.rank, rel_err=lr.relative_error,
                         passes=lr.info["passes"], sample_size=lr.info["sketch_rank"])
            r["loadavg"] = common.check_load()
            if k_opt:
                r["rank_over_opt"] = r["rank"] / k_opt
            rows.append(r)
            print(f"  eps={eps} {name}: {r['time']:.2f} s rank {r['rank']} err {r['rel_err']:.4f}"
                  f" (k_opt {k_opt})", file=sys.stderr, flush=True)
            gc.collect()
    del G32, G64
    gc.collect()
    return rows


def summarize(rows: list[dict]) -> list[dict]:
    """One row per (scene, n, eps): times and ranks side by side, ratios to HF."""
    out = []
    keys = sorted({(r["scene"], r["n"], r["eps"]) for r in rows}, key=lambda x: (x[0], x[1], -x[2]))
    for key in keys:
        by = {r["method"]: r for r in rows if (r["scene"], r["n"], r["eps"]) == key}
        s = {"scene": key[0], "n": key[1], "eps": key[2], "k_opt": next(iter(by.values())).get("k_opt")}
        for mth, r in by.items():
            s[f"t_{mth}"] = r["time"]
            s[f"k_{mth}"] = r["rank"]
            if mth in ("rsvd", "sketch"):
                s[f"passes_{mth}"] = r["passes"]
        if "hf32" in by:
            s["k_opt@hf_err"] = by["hf32"].get("k_opt_at_err")
            s["err_hf32"] = by["hf32"]["rel_err"]
        for num, den in (("svd64", "hf64"), ("svd32", "hf32"), ("svd64", "hf32"), ("rsvd", "hf32"),
                         ("sketch", "hf32")):
            if num in by and den in by:
                s[f"{num}/{den}"] = by[num]["time"] / by[den]["time"]
        out.append(s)
    return out


SUMMARY_COLUMNS = ["scene", "n", "eps", "t_hf32", "t_hf64", "t_svd32", "t_svd64", "t_rsvd", "t_sketch",
                   "k_hf32", "k_hf64", "k_opt", "k_opt@hf_err", "k_rsvd", "passes_rsvd", "k_sketch",
                   "passes_sketch", "svd64/hf64", "svd32/hf32", "svd64/hf32", "rsvd/hf32", "sketch/hf32"]
DETAIL_COLUMNS = ["scene", "n", "eps", "method", "time", "rank", "k_opt", "rank_over_opt", "rel_err",
                  "rel_err_true", "passes", "sample_size", "loadavg"]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scenes", default="cornell", help="comma list of: " + ", ".join(common.SCENES))
    p.add_argument("--sizes", default="2500,10000,20000", help="target patch counts, e.g. 2500,10k")
    p.add_argument("--eps", default="0.05,0.02,0.01", help="relative Frobenius targets")
    p.add_argument("--methods", default=",".join(ALL_METHODS), help="comma list of " + ", ".join(ALL_METHODS))
    p.add_argument("--block-size", type=int, default=256)
    p.add_argument("--repeat", type=int, default=2, help="best of k (fewer when a run exceeds 60 s)")
    p.add_argument("--power-iter", type=int, default=2, help="rSVD power iterations")
    p.add_argument("--svd-max-n", type=int, default=12000, help="skip the full SVD above this n")
    p.add_argument("--verify-max-n", type=int, default=5000,
                   help="check HF's reported error against an explicit ||G - QV^T||_F up to this n")
    p.add_argument("--quick", action="store_true", help="small sizes: 2500 patches, three scenes")
    p.add_argument("--out", default="factorize", help="results/NAME.json")
    common.add_blas_arg(p)
    args = p.parse_args(argv)
    if args.quick:
        args.scenes, args.sizes = "cornell,cbox-original,cbox-empty", "2500"
        if args.methods == ",".join(ALL_METHODS):   # the sketch alone would take ~5 of the 10 minutes
            args.methods = "hf32,hf64,svd32,svd64,rsvd"
    args.scenes = common.parse_list(args.scenes)
    args.sizes = common.parse_sizes(args.sizes)
    args.eps = common.parse_list(args.eps, float)
    args.methods = common.parse_list(args.methods)
    bad = [m for m in args.methods if m not in ALL_METHODS]
    if bad:
        p.error(f"unknown methods {bad}; choose from {ALL_METHODS}")
    mach = common.header("Factorization: HF vs full SVD vs randomized SVD vs sketch (same G, same run)", args.blas_threads)
    t0 = time.perf_counter()
    rows = []
    for scene in args.scenes:
        for size in args.sizes:
            rows += bench_case(scene, size, args)
            common.write_json(args.out, {"benchmark": "factorize", "machine": mach, "args": vars(args),
                                         "partial": True, "rows": rows, "summary": summarize(rows)})
    summary = summarize(rows)
    common.print_table("per method", rows, DETAIL_COLUMNS)
    common.print_table("side by side (times in s; ratios > 1: HF faster)", summary,
                       [c for c in SUMMARY_COLUMNS if any(c in s for s in summary)])
    path = common.write_json(args.out, {"benchmark": "factorize", "machine": mach, "args": vars(args),
                                        "wall_seconds": time.perf_counter() - t0, "rows": rows,
                                        "summary": summary, "machine_end_load": list(__import__("os").getloadavg())})
    print(f"\nwrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
