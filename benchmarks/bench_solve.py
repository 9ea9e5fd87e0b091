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
B_exact from the float64 LU solve, next to the eq. 5 bound (``fac.error_bound()``, worst channel).

Hardware context, measured in the same run:

* ``bw_ratio``: HF single-solve time / (bytes of Y_c and V the solve reads, 3 x (Y_c + V) in
  the factor dtype, / copy bandwidth of a large ``np.copyto``, counted as read + write);
* ``gemm_frac``: GEMM-equivalent throughput of the batched HF solve / the throughput of the
  bare float32 GEMMs of the same shapes (3 x [V^T E_c (k x n x m), Y_c W_c (n x k x m)]).

Run:  python benchmarks/bench_solve.py --quick
      python benchmarks/bench_solve.py --sizes 10000
Writes benchmarks/results/solve[-SUFFIX].json.

``--relight`` benchmarks the relighting solve alone on the built-in Cornell box, precomputed
as ``hfrad precompute --near-field off`` does (``hfrad.pipeline.factorize``, eps 0.02, the
plain Woodbury solver; cached as ``benchmarks/.cache/relight-cornell-N.hfr``), against the
memory-bandwidth limit:

* one RGB emission (the scene's light), median and best of >= 20 solves, for the present solver
  (Q, V and three k x k inverses; Q and V read once per RGB solve) and the previous one (three n x k
  ``Y_c = -D_c Q M_c^{-1}`` rebuilt here, float64 set-up as it was; the solve read V and the Y_c);
* the time to read Q and V once (2nk words), measured in the same run three ways: half of a
  ``np.copyto`` of 2nk words (the issue's definition: copy bandwidth, read + write), a streaming
  ``Q.sum() + V.sum()``, and a matrix-vector product with each (BLAS gemv);
* set-up (the k x k ``M_c`` and their inverses) in float32 and float64, and the old Y set-up; the
  radiosity difference float32 vs float64 set-up, next to the HF error;
* ``.hfr`` size and load time: format 3 (stores the inverses) vs format 2 (stores Y; a loaded v2 file
  recomputes the inverses from Q and V).

      PYTHONPATH=src python benchmarks/bench_solve.py --relight --sizes 10000,20000
Writes benchmarks/results/solve-relight.json.
"""

from __future__ import annotations

import argparse
import gc
import sys
import time

import numpy as np

import common
from hfrad import factorize_matrix
from hfrad.solve.denselu import LUFactorization
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
    fac = factorize_matrix(case.F, rho, eps=args.eps, dtype=np.float32, order=case.perm("zorder"))
    t_fac = time.perf_counter() - t0
    bound = float(np.max(fac.error_bound()))
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


def _median_solve(fn, repeat: int) -> tuple[float, float, object]:
    """(median, best, last result) of ``repeat`` timed calls, after one untimed warm-up."""
    out = fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), float(min(times)), out


def read_limits(Q: np.ndarray, V: np.ndarray, repeat: int = 7) -> dict:
    """Seconds to read Q and V once (2nk words), three ways, best of ``repeat`` (see module docstring)."""
    src = np.concatenate([Q.ravel(), V.ravel()])
    dst = np.empty_like(src)
    x, y = np.ones(Q.shape[1], Q.dtype), np.ones(Q.shape[0], Q.dtype)
    copy = common.best_of(lambda: np.copyto(dst, src), repeat).best
    return {"read_2nk_copy": copy / 2,            # a copy reads and writes 2nk words
            "read_2nk_sum": common.best_of(lambda: (Q.sum(), V.sum()), repeat).best,
            "read_2nk_gemv": common.best_of(lambda: (Q @ x, V.T @ y), repeat).best,
            "copy_bandwidth_gbs": 2 * src.nbytes / copy / 1e9}


def old_woodbury_y(fac) -> tuple[np.ndarray, float]:
    """The previous method's (3, n, k) ``Y_c = -D_c Q M_c^{-1}`` (float64 set-up, stored in the factor dtype), seconds."""
    import scipy.linalg as sla
    t0 = time.perf_counter()
    n, k = fac.Q.shape
    Y = np.empty((3, n, k), fac.dtype)
    V64 = fac.V.astype(np.float64)
    for c in range(3):
        Qc = fac.Q.astype(np.float64) * fac._D[:, c:c + 1]
        M = np.eye(k) - V64.T @ Qc
        lu_piv = sla.lu_factor(M.T, check_finite=False)
        Y[c] = -sla.lu_solve(lu_piv, Qc.T, check_finite=False).T
    return Y, time.perf_counter() - t0


def old_solve(fac, Y, E: np.ndarray) -> np.ndarray:
    """The previous method's RGB solve ``B_c = E_c - Y_c (V^T E_c)`` of (n, 3) E (user order)."""
    Ei = E[fac.perm]
    W = fac.V.T @ Ei.astype(fac.dtype)                                   # (k, 3)
    B = Ei.copy()
    for c in range(3):
        B[:, c] -= Y[c] @ W[:, c]
    return B[fac.inv_perm]


def write_v2(src, dst, Y: np.ndarray) -> None:
    """Copy a format-3 .hfr to the format-2 layout: Y (3, n, k) instead of the k x k inverses."""
    import h5py
    from hfrad.solve import hfr
    with h5py.File(src) as f, h5py.File(dst, "w") as g:
        for key, val in f.attrs.items():
            g.attrs[key] = val
        g.attrs["format_version"] = 2
        for name in f:
            if name != "factors":
                f.copy(name, g)
        fac_g = g.create_group("factors")
        for name in f["factors"]:
            if name != "capacitance_inverse":
                f.copy(f"factors/{name}", fac_g)
        hfr._dataset(fac_g, "Y", Y)
        g.attrs[hfr.DIGEST] = hfr._attrs_digest(g)


def relight_case(n_target: int, args) -> dict:
    """One size of ``--relight`` (see the module docstring)."""
    import os
    from hfrad.pipeline import factorize as precompute
    from hfrad.scene.load import load_scene
    from hfrad.solve.hfr import load_hfr, save_hfr
    from hfrad.solve.woodbury import capacitance, invert_capacitance, low_rank_correction

    cache = common.CACHE_DIR / f"relight-cornell-{n_target}.hfr"
    if cache.exists():
        fac = load_hfr(cache)
        time_precompute = fac.timings.get("precompute")
    else:
        t0 = time.perf_counter()
        # the plain solver (near field off): the one whose storage changed from Y to Q, V, M_c^-1
        fac = precompute(load_scene("cornell", patches=n_target), eps=args.eps, processes=2, near_field=None)
        time_precompute = time.perf_counter() - t0
        cache.parent.mkdir(parents=True, exist_ok=True)
        save_hfr(fac, cache, timings={"precompute": time_precompute})
    n, k = fac.Q.shape
    row = {"n": n, "k": k, "eps": args.eps, "achieved_error": fac.relative_error, "dtype": fac.dtype.name,
           "time_precompute": time_precompute, "loadavg_start": os.getloadavg()[0]}
    print(f"\n[relight cornell n={n} k={k}]", file=sys.stderr, flush=True)
    E = fac.scene.emission.copy()

    # set-up: new (M_c in float32 / float64, inverted) vs old (three Y_c, float64)
    def setup(dtype):
        M = capacitance(fac.Q, fac.V, fac._D, dtype=dtype)
        return np.stack([invert_capacitance(M[c], "M", fac.dtype) for c in range(3)])
    t32 = common.best_of(lambda: setup(np.float32), 2)
    t64 = common.best_of(lambda: setup(np.float64), 2)
    row["setup_new_f32"], row["setup_new_f64"] = t32.best, t64.best
    Y, row["setup_old_y"] = old_woodbury_y(fac)
    Ei = E[fac.perm][:, :, None]
    B32, B64 = ((Ei + low_rank_correction(fac.Q, fac.V, fac._D, inv, Ei, False))[fac.inv_perm, :, 0]
                for inv in (t32.result, t64.result))
    row["setup_f32_vs_f64"] = float(np.linalg.norm(B32 - B64) / np.linalg.norm(B64))
    print(f"  set-up: new f32 {t32.best:.2f} s, f64 {t64.best:.2f} s, old Y {row['setup_old_y']:.2f} s; "
          f"f32 vs f64 radiosity {row['setup_f32_vs_f64']:.1e}", file=sys.stderr, flush=True)

    # the RGB solve, new vs old, and reading the factors once
    before = read_limits(fac.Q, fac.V)
    med, best, B_new = _median_solve(lambda: fac.solve(E), args.relight_repeat)
    row["solve_new_median"], row["solve_new_best"] = med, best
    med, best, B_old = _median_solve(lambda: old_solve(fac, Y, E), args.relight_repeat)
    row["solve_old_median"], row["solve_old_best"] = med, best
    row["new_vs_old_radiosity"] = float(np.linalg.norm(B_new - B_old) / np.linalg.norm(B_old))
    after = read_limits(fac.Q, fac.V)                    # before and after the solves: the faster of the two
    row.update({key: min(before[key], after[key]) for key in before if key.startswith("read")},
               copy_bandwidth_gbs=max(before["copy_bandwidth_gbs"], after["copy_bandwidth_gbs"]))
    row["new_over_2nk_copy"] = row["solve_new_median"] / row["read_2nk_copy"]
    row["new_over_2nk_sum"] = row["solve_new_median"] / row["read_2nk_sum"]
    row["old_over_2nk_copy"] = row["solve_old_median"] / row["read_2nk_copy"]
    row["solve_old/new"] = row["solve_old_median"] / row["solve_new_median"]
    item = fac.dtype.itemsize
    row["memory_new_mb"] = (2 * n * k + 3 * k * k) * item / 1e6
    row["memory_old_mb"] = 5 * n * k * item / 1e6

    # the file: format 3 (as this hfrad writes it) vs format 2, size and load time
    v3, v2 = (cache.with_name(f"{cache.stem}-{v}.hfr") for v in ("v3", "v2"))
    save_hfr(fac, v3, timings=fac.timings)
    write_v2(v3, v2, Y)
    del Y
    row["file_v3_mb"], row["file_v2_mb"] = v3.stat().st_size / 1e6, v2.stat().st_size / 1e6
    row["load_v3"] = common.best_of(lambda: load_hfr(v3), 2).best
    t = common.best_of(lambda: load_hfr(v2), 2)
    row["load_v2"] = t.best
    np.testing.assert_allclose(t.result.solve(E), B_new, rtol=0, atol=1e-5 * np.abs(B_new).max())
    v2.unlink()
    v3.unlink()
    row["loadavg_end"] = os.getloadavg()[0]
    print(f"  solve median new {row['solve_new_median'] * 1e3:.1f} ms, old {row['solve_old_median'] * 1e3:.1f} ms; "
          f"read 2nk: copy/2 {row['read_2nk_copy'] * 1e3:.1f} ms, sum {row['read_2nk_sum'] * 1e3:.1f} ms; "
          f"ratio {row['new_over_2nk_copy']:.2f}", file=sys.stderr, flush=True)
    return row


def relight_main(args, sizes) -> int:
    import numba
    mach = common.header("Relighting solve vs reading the factors once (Cornell box)", args.blas_threads)
    if args.blas_threads and args.blas_threads > 0:        # the solve's streaming kernels (hfrad.solve.thin)
        numba.set_num_threads(min(args.blas_threads, numba.config.NUMBA_NUM_THREADS))
    mach["numba_threads"] = numba.get_num_threads()
    print(f"BLAS threads {args.blas_threads}, numba threads {mach['numba_threads']}")
    rows = [relight_case(n, args) for n in sizes]
    common.print_table("one RGB solve (median of %d), seconds; read_2nk = reading Q and V once" % args.relight_repeat,
                       rows, ["n", "k", "solve_new_median", "solve_old_median", "solve_old/new", "read_2nk_copy",
                              "read_2nk_sum", "read_2nk_gemv", "new_over_2nk_copy", "new_over_2nk_sum",
                              "old_over_2nk_copy", "loadavg_start"])
    common.print_table("set-up (s), radiosity difference f32 vs f64 set-up, memory and file (MB), load (s)", rows,
                       ["n", "k", "achieved_error", "setup_new_f32", "setup_new_f64", "setup_old_y",
                        "setup_f32_vs_f64", "memory_new_mb", "memory_old_mb", "file_v3_mb", "file_v2_mb",
                        "load_v3", "load_v2", "loadavg_end"])
    path = common.write_json(args.out, {"benchmark": "solve-relight", "machine": mach, "args": vars(args),
                                        "rows": rows})
    print(f"\nwrote {path}")
    return 0


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
    p.add_argument("--out", default=None, help="results/OUT.json (default solve, or solve-relight)")
    p.add_argument("--relight", action="store_true",
                   help="relighting solve vs the memory-bandwidth limit, old vs new solver (module docstring)")
    p.add_argument("--relight-repeat", type=int, default=25, help="timed solves per method with --relight")
    common.add_blas_arg(p)
    args = p.parse_args(argv)
    if args.quick:
        args.scenes, args.sizes = "cornell", "2500"
    args.out = args.out or ("solve-relight" if args.relight else "solve")
    scenes, sizes = common.parse_list(args.scenes), common.parse_sizes(args.sizes)
    if args.relight:
        return relight_main(args, sizes)
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
