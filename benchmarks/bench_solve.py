"""Benchmark: per-solve time and accuracy, HF Woodbury vs LU vs Jacobi / Gauss-Seidel / Southwell / GMRES.

For each case the HF factorization (float32 factors, Z-order, eps as given) and the dense
LU of (I - R_c F) (scipy ``lu_factor``, float64, three channels) are built once; then

* one RGB emission (the scene's lights): HF ``fac.solve``, ``lu_solve``, and the iterative
  solvers on the dense float64 F to a relative residual of ``--rtol`` (1e-4);
* a batch of ``--batch`` (1,000) random emissions (1% of the patches emit, random RGB),
  solved as one (n, 3, m) array by HF and by LU. The iterative solvers are not run on the
  batch: their batch time is modelled as m x the single-emission time (they have no
  batched form here), and marked ``modelled``.

Accuracy is the relative radiosity error ||B - B_exact|| / ||B_exact|| (worst channel) with
B_exact from the float64 LU solve, next to the eq. 5 bound (``fac.error_bound``, worst channel).

Hardware context, measured in the same run:

* ``bw_ratio``: HF single-solve time / (bytes of Y_c and V the solve reads, 3 x (Y_c + V) in
  the factor dtype, / copy bandwidth of a large ``np.copyto``, counted as read + write);
* ``gemm_frac``: GEMM-equivalent throughput of the batched HF solve / the throughput of the
  bare float32 GEMMs of the same shapes (3 x [V^T E_c (k x n x m), Y_c W_c (n x k x m)]).

Run:  python benchmarks/bench_solve.py --quick
      python benchmarks/bench_solve.py --sizes 10000
Writes benchmarks/results/solve[-SUFFIX].json.
"""

from __future__ import annotations

import argparse
import gc
import sys
import time

import numpy as np

import common
from hfrad import factorize
from hfrad.solve.direct import LUFactorization
from hfrad.solve.iterative import gauss_seidel, gmres, jacobi, southwell

ITERATIVE = ("jacobi", "gauss_seidel", "southwell", "gmres")


def copy_bandwidth(nbytes: int = 1 << 29, repeat: int = 5) -> float:
    """Bytes per second moved by ``np.copyto`` of a large float32 array (read + write)."""
    src = np.ones(nbytes // 4, np.float32)
    dst = np.empty_like(src)
    t = common.best_of(lambda: np.copyto(dst, src), repeat)
    return 2 * nbytes / t.best


def gemm_time(n: int, k: int, m: int, repeat: int = 3) -> float:
    """Best time of the bare float32 GEMMs a batched 3-channel HF solve does."""
    rng = np.random.default_rng(0)
    V = rng.random((n, k), dtype=np.float32)
    Y = rng.random((n, k), dtype=np.float32)
    E = rng.random((n, m), dtype=np.float32)

    def go():
        for _ in range(3):
            W = V.T @ E
            _ = Y @ W
    return common.best_of(go, repeat).best


def rel_err(B, ref) -> float:
    """Worst channel of ||B_c - ref_c||_F / ||ref_c||_F (over patches and, if batched, emissions)."""
    ref = ref.reshape(ref.shape[0], 3, -1)
    B = B.reshape(ref.shape)
    num = np.sqrt(((B - ref) ** 2).sum(axis=(0, 2)))
    den = np.sqrt((ref ** 2).sum(axis=(0, 2)))
    return float(np.max(num / np.where(den > 0, den, 1)))


def bench_case(scene: str, patches: int, args, bw: float) -> list[dict]:
    case = common.load_case(scene, patches)
    n = case.n
    rho = case.reflectance
    E1 = case.emission.copy()
    if not E1.any():
        E1[np.argmax(case.centroids[:, 1])] = 10.0
    rng = np.random.default_rng(0)
    m = args.batch
    Em = rng.random((n, 3, m)) * (rng.random((n, 1, m)) < 0.01)
    F64 = np.ascontiguousarray(case.F, dtype=np.float64)
    print(f"\n[{scene} n={n}]", file=sys.stderr, flush=True)

    t0 = time.perf_counter()
    fac = factorize(case.F, rho, eps=args.eps, dtype=np.float32, order=case.perm("zorder"))
    t_fac = time.perf_counter() - t0
    bound = float(np.max(fac.error_bound))
    k = fac.rank
    t0 = time.perf_counter()
    lu = LUFactorization(F64, rho)
    t_lu = time.perf_counter() - t0
    print(f"  HF factor {t_fac:.1f} s (k={k}), LU factor {t_lu:.1f} s", file=sys.stderr, flush=True)

    B1 = lu.solve(E1)
    Bm = lu.solve(Em)
    rows = []
    base = {"scene": scene, "n": n, "k": k, "eps": args.eps, "bound": bound}

    # -- one RGB emission
    fac.solve(E1)                                      # warm the caches and BLAS threads
    t = common.best_of(lambda: fac.solve(E1), max(args.repeat, 20), max_seconds=5)
    nbytes = 6 * n * k * fac.dtype.itemsize           # 3 channels x (Y_c + V) read once each
    t_bw = nbytes / bw
    rows.append(dict(base, method="hf-woodbury", batch=1, time=t.best, per_emission=t.best,
                     rel_err=rel_err(t.result, B1), precompute=t_fac, bw_ratio=t.best / t_bw,
                     bytes_read=nbytes))
    t_hf1 = t.best
    t = common.best_of(lambda: lu.solve(E1), max(args.repeat, 10), max_seconds=5)
    rows.append(dict(base, method="lu", batch=1, time=t.best, per_emission=t.best,
                     rel_err=rel_err(t.result, B1), precompute=t_lu))
    iters = {}
    for name in args.iterative:
        fn = {"jacobi": lambda: jacobi(F64, rho, E1, rtol=args.rtol),
              "gauss_seidel": lambda: gauss_seidel(F64, rho, E1, rtol=args.rtol),
              "southwell": lambda: southwell(F64, rho, E1, areas=case.areas, rtol=args.rtol),
              "gmres": lambda: gmres(F64, rho, E1, rtol=args.rtol)}[name]
        if name in ("gauss_seidel", "southwell"):   # numba: compile/load outside the timing
            small = np.ascontiguousarray(F64[:64, :64])
            (gauss_seidel if name == "gauss_seidel" else southwell)(small, rho[:64], E1[:64] + 1, rtol=1e-2)
        t = common.best_of(fn, args.repeat, max_seconds=20)
        res = t.result
        iters[name] = t.best
        rows.append(dict(base, method=name, batch=1, time=t.best, per_emission=t.best,
                         rel_err=rel_err(res.radiosity, B1), iterations=int(res.iterations.max()),
                         converged=res.converged))
        print(f"  {name}: {t.best:.3f} s", file=sys.stderr, flush=True)

    # -- a batch of m emissions
    t = common.best_of(lambda: fac.solve(Em), args.repeat, max_seconds=30)
    t_gemm = gemm_time(n, k, m)
    flops = 3 * 2 * (2.0 * n * k * m)
    rows.append(dict(base, method="hf-woodbury", batch=m, time=t.best, per_emission=t.best / m,
                     rel_err=rel_err(t.result, Bm), gflops=flops / t.best / 1e9,
                     gemm_gflops=flops / t_gemm / 1e9, gemm_frac=t_gemm / t.best,
                     speedup_vs_single=t_hf1 * m / t.best))
    t_hfm = t.best
    t = common.best_of(lambda: lu.solve(Em), args.repeat, max_seconds=30)
    rows.append(dict(base, method="lu", batch=m, time=t.best, per_emission=t.best / m,
                     rel_err=rel_err(t.result, Bm)))
    for name, t1 in iters.items():
        rows.append(dict(base, method=name, batch=m, time=t1 * m, per_emission=t1, modelled=True))
    for r in rows:
        same = next(q for q in rows if q["method"] == "hf-woodbury" and q["batch"] == r["batch"])
        r["time/hf"] = r["time"] / same["time"]
        r["loadavg"] = common.check_load()
    del F64, lu, fac
    gc.collect()
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scenes", default="cornell")
    p.add_argument("--sizes", default="2500,10000")
    p.add_argument("--eps", type=float, default=0.02, help="HF target (relative Frobenius on G)")
    p.add_argument("--rtol", type=float, default=1e-4, help="iterative solvers' relative residual")
    p.add_argument("--batch", type=int, default=1000, help="emissions in the batched solve")
    p.add_argument("--iterative", default=",".join(ITERATIVE))
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--quick", action="store_true", help="2500 patches, Cornell box")
    p.add_argument("--out", default="solve")
    common.add_blas_arg(p)
    args = p.parse_args(argv)
    if args.quick:
        args.scenes, args.sizes = "cornell", "2500"
    scenes, sizes = common.parse_list(args.scenes), common.parse_sizes(args.sizes)
    args.iterative = common.parse_list(args.iterative)
    mach = common.header("Solve: HF Woodbury vs LU vs iterative (per emission)", args.blas_threads)
    bw = copy_bandwidth()
    print(f"copy bandwidth (np.copyto, read + write): {bw / 1e9:.1f} GB/s")
    t_start = time.perf_counter()
    rows = []
    for scene in scenes:
        for size in sizes:
            rows += bench_case(scene, size, args, bw)
    common.print_table(f"per-solve time (s) and accuracy vs dense float64 LU (HF eps = {args.eps}, "
                       f"iterative rtol = {args.rtol})", rows,
                       ["scene", "n", "k", "method", "batch", "time", "per_emission", "time/hf", "rel_err",
                        "bound", "iterations", "bw_ratio", "gflops", "gemm_gflops", "gemm_frac", "modelled",
                        "loadavg"])
    path = common.write_json(args.out, {"benchmark": "solve", "machine": mach, "args": vars(args),
                                        "copy_bandwidth_Bps": bw, "wall_seconds": time.perf_counter() - t_start,
                                        "rows": rows})
    print(f"\nwrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
