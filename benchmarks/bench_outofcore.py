"""Benchmark: out-of-core precomputation (form factors + factorization) when F never fits in memory.

Out of core, every pass over F regenerates all of its column blocks (form factors with
visibility): a method that needs P passes pays P x the generation time. Per case:

* ``hf-1pass`` (measured, real): ``hfrad.pipeline.factorize`` end to end, blocks generated
  once and streamed into HF (float32).
* ``T_setup`` + ``T_pass``: measured once per case, the form-factor engine's setup (geometry,
  Embree scene) and one pass generating every column block with it.
* ``rsvd q=Q`` (modelled): the library's adaptive randomized SVD (sample size grown 1.5x and
  restarted until eps is met) with Q power iterations, run in core on the same G to get its
  passes and compute time; out of core = T_setup + passes x T_pass + in-core compute time.
  ``rsvd-oracle q=Q`` is the same with the final sample size known in advance (one
  attempt: 2Q + 2 passes), the best case for rSVD.
* ``sketch`` (modelled): single-pass sketch grown until eps is met (each attempt: a sketch
  pass + a verification pass), same model; ``sketch-oracle``: one attempt, 2 passes.
* ``rsvd-oracle q=Q real`` (measured, ``--real-max-n``): the oracle rSVD run for real out of
  core, every pass regenerating the blocks with ``iter_column_blocks``, to check the model.

The modelled in-core compute time double-counts the (small) time to read G from memory.

Run:  python benchmarks/bench_outofcore.py --quick
      python benchmarks/bench_outofcore.py --sizes 10000
Writes benchmarks/results/outofcore[-SUFFIX].json.
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
from hfrad import PrecomputeOptions
from hfrad.lowrank.baselines import randomized_factorization, sketch_factorization
from hfrad.lowrank.factors import truncation_rank
from hfrad.pipeline import factorize


def streamed_rsvd(scene, perm, rho_max, *, l: int, q: int, eps: float, block_size: int = 256, rng=0):
    """Oracle rSVD (Halko Alg. 4.4, sample size l, q power iterations) with every pass over
    G = diag(rho_max) F regenerating the column blocks. Returns (rank, rel_err, passes, seconds,
    seconds generating blocks)."""
    from hfrad.formfactors.blocks import FormFactorEngine, iter_column_blocks
    rng = np.random.default_rng(rng)
    n = scene.n_patches
    rows = rho_max[perm].astype(np.float32)[:, None]
    t0 = time.perf_counter()
    engine = FormFactorEngine(scene)
    t_gen = [time.perf_counter() - t0]           # engine setup counts as generation

    def blocks():
        it = iter_column_blocks(scene, block_size, order=perm, dtype=np.float32, engine=engine)
        t = time.perf_counter()
        for a, b, Fb in it:
            t_gen[0] += time.perf_counter() - t
            yield a, b, rows * Fb
            t = time.perf_counter()

    passes = 1
    Y = np.zeros((n, l), np.float32)
    norm2 = 0.0
    for a, b, Gb in blocks():                        # pass 1: Y = G Omega, ||G||_F
        Y += Gb @ rng.standard_normal((b - a, l)).astype(np.float32)
        norm2 += float(np.sum(np.square(Gb, dtype=np.float64)))
    P = sla.qr(Y, mode="economic", check_finite=False)[0]
    for _ in range(q):
        Z = np.empty((n, l), np.float32)
        for a, b, Gb in blocks():                    # Z = G^T P
            Z[a:b] = Gb.T @ P
        Z = sla.qr(Z, mode="economic", check_finite=False)[0]
        Y[:] = 0
        for a, b, Gb in blocks():                    # Y = G Z
            Y += Gb @ Z[a:b]
        P = sla.qr(Y, mode="economic", check_finite=False)[0]
        passes += 2
    Bm = np.empty((l, n), np.float32)
    for a, b, Gb in blocks():                        # B = P^T G
        Bm[:, a:b] = P.T @ Gb
    passes += 1
    s = sla.svd(Bm, compute_uv=False, check_finite=False).astype(np.float64)
    resid2 = max(norm2 - float(np.sum(s ** 2)), 0.0)
    # error of rank i truncation: resid2 + tail of s; smallest i within eps
    k, d2 = truncation_rank(s, max(eps * eps * norm2 - resid2, 0.0))
    seconds = time.perf_counter() - t0
    engine.close()
    return k, math.sqrt((resid2 + d2) / norm2), passes, seconds, t_gen[0]


def measure_pass(scene, perm, block_size: int) -> tuple[float, float]:
    """(engine setup seconds, seconds of one pass generating every column block with that engine)."""
    from hfrad.formfactors.blocks import FormFactorEngine, iter_column_blocks
    t0 = time.perf_counter()
    engine = FormFactorEngine(scene)
    t_setup = time.perf_counter() - t0
    t0 = time.perf_counter()
    for _ in iter_column_blocks(scene, block_size, order=perm, dtype=np.float32, engine=engine):
        pass
    t_pass = time.perf_counter() - t0
    engine.close()
    return t_setup, t_pass


def bench_case(scene_name: str, patches: int, args) -> list[dict]:
    case = common.load_case(scene_name, patches)
    scene = common.load_bench_scene(scene_name, patches)
    n = scene.n_patches
    assert n == case.n, "cached case and scene disagree"
    perm = case.perm("zorder")
    rows = []
    print(f"\n[{scene_name} n={n}]", file=sys.stderr, flush=True)
    G = None
    t_setup, t_pass = measure_pass(scene, perm, args.block_size)
    print(f"  one pass over F: engine setup {t_setup:.2f} s + {t_pass:.2f} s of blocks", file=sys.stderr)
    for eps in args.eps:
        base = {"scene": scene_name, "n": n, "eps": eps}
        # -- HF, one real pass: form factors + HF, end to end
        t0 = time.perf_counter()
        fac = factorize(scene, eps=eps, dtype="float32", options=PrecomputeOptions(block_size=args.block_size),
                        far_field="exact")     # the column pass, whose HF goes out of core
        total = time.perf_counter() - t0
        info = fac.lowrank.info
        rows.append(dict(base, method="hf-1pass", kind="measured", passes=1, rank=fac.rank,
                         rel_err=fac.relative_error, t_generate=info["time_formfactors"],
                         t_compute=info["time_total"], total=total, t_pass=t_pass))
        t_hf = total
        print(f"  eps={eps} hf: {total:.1f} s (form factors {info['time_formfactors']:.1f} s, HF {info['time_total']:.1f} s)",
              file=sys.stderr, flush=True)
        del fac
        gc.collect()
        if G is None:
            G = case.G(perm, np.float32)
        # -- modelled multi-pass baselines
        for q in args.power_iters:
            t = time.perf_counter()
            lr = randomized_factorization(G, eps=eps, dtype=np.float32, n_power_iter=q, rng=0)
            tc = time.perf_counter() - t
            P, l = lr.info["passes"], lr.info["sample_size"]
            rows.append(dict(base, method=f"rsvd q={q}", kind="modelled", passes=P, rank=lr.rank,
                             rel_err=lr.relative_error, t_generate=t_setup + P * t_pass, t_compute=tc,
                             total=t_setup + P * t_pass + tc, sample_size=l, t_pass=t_pass))
            t = time.perf_counter()
            lr = randomized_factorization(G, eps=eps, dtype=np.float32, n_power_iter=q, rng=0,
                                          initial_rank=max(l - 10, 1))
            tc = time.perf_counter() - t
            P = lr.info["passes"]
            rows.append(dict(base, method=f"rsvd-oracle q={q}", kind="modelled", passes=P, rank=lr.rank,
                             rel_err=lr.relative_error, t_generate=t_setup + P * t_pass, t_compute=tc,
                             total=t_setup + P * t_pass + tc, sample_size=lr.info["sample_size"], t_pass=t_pass))
            if n <= args.real_max_n:
                k, err, P, sec, tg = streamed_rsvd(scene, perm, case.rho_max, l=lr.info["sample_size"], q=q,
                                                  eps=eps, block_size=args.block_size)
                rows.append(dict(base, method=f"rsvd-oracle q={q} real", kind="measured", passes=P, rank=k,
                                 rel_err=err, t_generate=tg, t_compute=sec - tg, total=sec,
                                 sample_size=lr.info["sample_size"], t_pass=t_pass))
            print(f"  eps={eps} rsvd q={q} done", file=sys.stderr, flush=True)
        if "sketch" in args.methods:
            t = time.perf_counter()
            lr = sketch_factorization(G, eps=eps, dtype=np.float32, rng=0, block_size=args.block_size)
            tc = time.perf_counter() - t
            P, ks = lr.info["passes"], lr.info["sketch_rank"]
            rows.append(dict(base, method="sketch", kind="modelled", passes=P, rank=lr.rank,
                             rel_err=lr.relative_error, t_generate=t_setup + P * t_pass, t_compute=tc,
                             total=t_setup + P * t_pass + tc, sample_size=ks, t_pass=t_pass))
            t = time.perf_counter()
            lr = sketch_factorization(G, eps=eps, dtype=np.float32, rng=0, block_size=args.block_size,
                                      initial_rank=ks)
            tc = time.perf_counter() - t
            P = lr.info["passes"]
            rows.append(dict(base, method="sketch-oracle", kind="modelled", passes=P, rank=lr.rank,
                             rel_err=lr.relative_error, t_generate=t_setup + P * t_pass, t_compute=tc,
                             total=t_setup + P * t_pass + tc, sample_size=ks, t_pass=t_pass))
        for r in rows:
            if r["eps"] == eps and r["n"] == n and r["scene"] == scene_name:
                r["total/hf"] = r["total"] / t_hf
                r["loadavg"] = common.check_load()
    del G
    gc.collect()
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scenes", default="cornell")
    p.add_argument("--sizes", default="2500,10000")
    p.add_argument("--eps", default="0.05,0.02")
    p.add_argument("--power-iters", default="0,1,2", help="rSVD power iterations to model")
    p.add_argument("--methods", default="rsvd,sketch")
    p.add_argument("--block-size", type=int, default=256)
    p.add_argument("--real-max-n", type=int, default=3000,
                   help="run the oracle rSVD for real (every pass regenerates F) up to this n")
    p.add_argument("--quick", action="store_true", help="2500 patches, eps 0.05, Cornell box")
    p.add_argument("--out", default="outofcore")
    common.add_blas_arg(p)
    args = p.parse_args(argv)
    if args.quick:
        args.scenes, args.sizes, args.eps = "cornell", "2500", "0.05"
    scenes, sizes = common.parse_list(args.scenes), common.parse_sizes(args.sizes)
    args.eps = common.parse_list(args.eps, float)
    args.power_iters = common.parse_list(args.power_iters, int)
    args.methods = common.parse_list(args.methods)
    mach = common.header("Out of core: form factors + factorization, F regenerated on every pass", args.blas_threads)
    t_start = time.perf_counter()
    rows = []
    for scene in scenes:
        for size in sizes:
            rows += bench_case(scene, size, args)
    common.print_table("precompute time (s) out of core (total/hf > 1: HF faster)", rows,
                       ["scene", "n", "eps", "method", "kind", "passes", "sample_size", "rank", "rel_err",
                        "t_generate", "t_compute", "total", "total/hf", "loadavg"])
    path = common.write_json(args.out, {"benchmark": "outofcore", "machine": mach, "args": vars(args),
                                        "wall_seconds": time.perf_counter() - t_start, "rows": rows})
    print(f"\nwrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
