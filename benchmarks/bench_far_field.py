"""The sampled far field against the exact pass, side by side in one run (issue 43).

Two parts. **Per block** (default, ``--blocks K``): K column blocks spread over the Z-order
of an n-patch scene, each computed exactly (every row, in this process, rays on every core,
no reciprocity copy) and by the sampled far field, one after the other: seconds per block,
the share of the block's pairs evaluated (all, with rays, kernel only, probe rays), the
sampled block's error against the exact one (``||G - G~||_F / ||G||_F`` over the blocks) and
the certificate's estimate of it. This is what scales to a million patches here. With
``--redraws R`` the certificate is drawn again with R seeds on the same blocks (from their exact
values: no more rays), beside the systematic sample of before (estimate + 2 standard errors, and
the same sample with this certificate's multiplier): how often each upper figure falls below the
measured error, and the range of estimate / measured.
**End to end** (``--end-to-end``): ``hfrad.factorize(scene, eps, far_field=...)`` runs with ``"exact"`` (every
pair; half copied by reciprocity) and ``"sampled"`` (near rows exactly, far rows from a checked
interpolative decomposition, visibility of far pairs from cluster tests and probe rays), on
the same scene, one after the other. Columns: wall time of the whole precompute, form-factor
time, rank, the share of the n^2 pairs evaluated (and with rays), the sampled field's
certified ``||G - G~||_F`` (estimate and upper figure from the certification rows) against a
second, held-out sample of exact rows, and the radiosity of the scene's lights: sampled
against exact, relative to the reflected light (``||B_s - B_e||_A / ||B_e - E||_A`` per
channel), beside the per-solve error figure each gives for its own solution.

**After the form factors** (``--downstream``): the same sampled blocks through the pass statistics
and HF's leaf, handed on in pieces (exact rows + W X) and made dense, side by side.

Not a test: prints tables and writes results/far-field-{blocks,end-to-end,downstream}-SCENE-SIZES.json.
Run: ``PYTHONPATH=src python3 benchmarks/bench_far_field.py [--patches 40000,163000] [--blocks 6]
[--eps 0.02] [--scene cornell] [--redraws 50]`` or ``... --end-to-end [--modes exact,sampled,hierarchical]
[--repeat 3]`` or ``... --downstream``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

import common
import hfrad
from hfrad.atomic import atomic_path
from hfrad.formfactors.farfield import CERTIFICATE_FAILURE, FarFieldOptions


def reflected_difference(B, B_ref, E, areas) -> list[float]:
    """Per channel ``||B - B_ref||_A / ||B_ref - E||_A``."""
    w = np.asarray(areas)[:, None]
    return list(np.sqrt((w * (B - B_ref) ** 2).sum(axis=0) / (w * (B_ref - E) ** 2).sum(axis=0)))


def run(scene, mode: str, eps: float) -> dict:
    options = hfrad.PrecomputeOptions(far=FarFieldOptions(holdout_rows=256))
    t0 = time.perf_counter()
    fac = hfrad.factorize(scene, eps, far_field=mode, options=options)
    wall = time.perf_counter() - t0
    info = fac.lowrank.info
    E = np.asarray(scene.emission, float)
    B, err = fac.solve(E, return_error=True)
    row = {"mode": mode, "n": scene.n_patches, "wall_s": wall, "formfactors_s": info.get("time_formfactors"),
           "hf_s": info.get("time_total"), "rank": fac.rank, "B": B,
           "figure": [float(x) for x in np.ravel(err.bound)],
           "operator_error": [float(x) for x in fac.error_estimate().operator_error]}
    far = info.get("far_field")
    if far:
        row.update(pairs_share=far["pairs_share"], traced_share=far["traced_share"],
                   certificate=far["error_estimate"], certificate_upper=far["error_upper"],
                   holdout=far.get("holdout_estimate"), exact_groups=far["exact_groups"], groups=far["groups"],
                   refined_groups=far["refined_groups"], skeleton_mean=far["skeleton_mean"], far_field=far)
    elif "hierarchical" in info:
        h = info["hierarchical"]
        n2 = scene.n_patches ** 2
        row.update(pairs_share=h["pairs_share"], traced_share=h["exact_pairs"] / n2,
                   certificate=h["certificate"]["error_estimate"], certificate_upper=h["certificate"]["error_upper"],
                   hierarchical={k: v for k, v in h.items() if k != "factorization"},
                   basis=h["factorization"]["basis"], near_nnz=info.get("near_nnz"), norm=fac.lowrank.norm,
                   # the certificate is absolute (||A^1/2 diag(rho) (F - F_H) A^-1/2||_F): as a share of ||G||_F
                   certificate_relative=h["certificate"]["error_estimate"] / fac.lowrank.norm,
                   stages={k: info[k] for k in ("time_formfactors", "time_statistics", "time_certificate",
                                                "time_factorization", "time_assemble") if k in info})
    else:
        copied = info.get("reciprocity", {}).get("copied_pairs", 0)
        row.update(pairs_share=1.0 - copied / scene.n_patches ** 2, traced_share=None)
    return row


def systematic_figure(q: np.ndarray, n: int, z: float = 2.0) -> tuple[float, float]:
    """The certificate before 2026-12-06 15:00 (for the redraws' "before"): a systematic sample's
    per-row sums ``q``, estimate and estimate + z standard errors from successive differences."""
    m = q.size
    total = n * float(q.mean())
    var = n ** 2 * float((np.diff(q) ** 2).sum()) / (2.0 * m * max(m - 1, 1))
    return float(np.sqrt(total)), float(np.sqrt(total + z * np.sqrt(var)))


class Redraws:
    """The certificate redrawn with ``count`` seeds on the measured blocks, from their exact values
    (no rays): this design and the systematic sample of before, side by side."""

    def __init__(self, n: int, rows: int, count: int) -> None:
        from hfrad.formfactors.farfield import FarFieldCertificate, _spread
        self.n = n
        self.new = [FarFieldCertificate.design(n, rows, 1000 + r) for r in range(count)]
        self.old_index = [np.unique(_spread(np.arange(n), rows, np.random.default_rng([1000 + r, 1])))
                          for r in range(count)]
        self.old_q = [np.zeros(i.size) for i in self.old_index]

    def add(self, j: int, start: int, parts: list, exact: np.ndarray, d2: np.ndarray, rho, w) -> None:
        """``exact``: the block's exact F (n x b); ``d2``: its weighted squared errors, row sums (n,)."""
        for c in self.new:
            c.add_block(j, start, parts, lambda rows, a, b: exact[rows, a:b], rho, w)
        for index, q in zip(self.old_index, self.old_q):
            q += d2[index]

    def summary(self, measured: float) -> dict:
        new = np.array([c.frobenius() for c in self.new]) / measured
        old = np.array([systematic_figure(q, self.n) for q in self.old_q]) / measured
        # the systematic sample with this design's multiplier: what the design itself brings
        z = np.sqrt(1.0 / CERTIFICATE_FAILURE - 1.0)
        wide = np.array([systematic_figure(q, self.n, z) for q in self.old_q]) / measured
        out = {"redraws": len(self.new)}
        for name, r in (("", new), ("systematic_", old), ("systematic_wide_", wide)):
            out.update({f"{name}estimate_ratio_min": float(r[:, 0].min()),
                        f"{name}estimate_ratio_max": float(r[:, 0].max()),
                        f"{name}upper_ratio_min": float(r[:, 1].min()),
                        f"{name}upper_ratio_median": float(np.median(r[:, 1])),
                        f"{name}upper_below": int((r[:, 1] < 1.0).sum())})
        return out


def best_runs(scene, modes: list[str], eps: float, repeat: int, keep=None) -> dict:
    """Each mode's fastest of ``repeat`` runs (the modes in turn, so that a drift of the machine
    reaches all alike), with every run's wall time in ``walls_s``; ``keep(mode, result)`` is called
    as each mode's best so far is found (a long run's answer is saved before the next mode runs)."""
    if repeat < 1:
        raise SystemExit(f"--repeat must be at least 1, got {repeat}")
    best: dict = {}
    walls: dict = {mode: [] for mode in modes}
    for _ in range(repeat):
        for mode in modes:
            r = run(scene, mode, eps)
            walls[mode].append(r["wall_s"])
            if mode not in best or r["wall_s"] < best[mode]["wall_s"]:
                best[mode] = r
                if keep is not None:
                    keep(mode, r)
    for mode, r in best.items():
        r["walls_s"] = walls[mode]
    return best


def per_block(scene, blocks: int, eps: float, block_size: int = 256, redraws: int = 0) -> dict:
    """Seconds, pairs and errors of ``blocks`` column blocks, exact and sampled (see the module docstring);
    with ``redraws``, the certificate redrawn that many times on the same blocks (:class:`Redraws`)."""
    from hfrad.formfactors.budget import ray_budget
    from hfrad.formfactors.engine import FormFactorEngine
    from hfrad.formfactors.farfield import SampledFarField
    from hfrad.scene.zorder import zorder_permutation

    n = scene.n_patches
    perm = zorder_permutation(scene.centroids)
    rho = scene.reflectance.max(axis=1)[perm]
    w = np.asarray(scene.areas)[perm]
    engine = FormFactorEngine(scene, ray_budget=ray_budget(scene, eps / 4), ray_threads=None)
    producer = SampledFarField(scene, engine, perm, block_size, rho, eps, weights=w,
                               options=FarFieldOptions(holdout_rows=256))
    engine.block(perm[:2000], perm[:block_size])          # compile and warm up both paths
    producer.block(0)
    producer.stats = type(producer.stats)()              # count the measured blocks only
    for c in (producer.certificate, producer.holdout):
        c.q[:] = 0.0
    m = -(-n // block_size)
    t_exact = t_sampled = err2 = norm2 = werr2 = 0.0
    draws = Redraws(n, producer.certificate.q.size, redraws) if redraws else None
    producer.keep_parts = draws is not None
    for j in np.linspace(1, m - 1, blocks).astype(int):
        cols = perm[j * block_size:(j + 1) * block_size]
        t0 = time.perf_counter()
        exact = engine.block(perm, cols)
        t_exact += time.perf_counter() - t0
        t0 = time.perf_counter()
        pieces, _ = producer.block(j)
        sampled = pieces.to_dense()
        t_sampled += time.perf_counter() - t0
        d = (exact - sampled) * rho[:, None]
        err2 += float(np.square(d).sum())
        # the certificate's norm: A^1/2 (G - G~) A^-1/2
        d2 = np.square(d * np.sqrt(w[:, None] / w[None, j * block_size:(j + 1) * block_size])).sum(axis=1)
        werr2 += float(d2.sum())
        if draws is not None:
            draws.add(j, j * block_size, producer.last_parts, exact, d2, rho, w)
        norm2 += float(np.square(exact * rho[:, None]).sum())
    far = producer.stats.as_dict(n)
    pairs = n * block_size * blocks
    # the certificate and the held-out sample estimate the whole matrix's error from these blocks' columns:
    # scaled to the blocks measured (m / blocks of the columns), they estimate this run's error
    cert, upper = producer.certificate.frobenius()
    held = producer.holdout.frobenius()[0]
    producer.close()
    return {"n": n, "blocks": blocks, "exact_s_per_block": t_exact / blocks,
            "sampled_s_per_block": t_sampled / blocks, "speedup": t_exact / t_sampled,
            "pairs_share": far["pairs"] / pairs, "traced_share": far["traced_pairs"] / pairs,
            "kernel_share": far["kernel_pairs"] / pairs, "near_share": far["near_pairs"] / pairs,
            "mixed_share": far["mixed_pairs"] / pairs, "certify_share": far["certify_pairs"] / pairs,
            "probe_rays_per_pair": far["probe_rays"] / pairs, "relative_error": float(np.sqrt(err2 / norm2)),
            "weighted_error": float(np.sqrt(werr2)), "certificate": cert, "certificate_upper": upper,
            "holdout": held, "certificate_ratio": cert / max(np.sqrt(werr2), 1e-300),
            "target": FarFieldOptions().share * eps, "certificate_rows": int(producer.certificate.q.size),
            **(draws.summary(float(np.sqrt(werr2))) if draws is not None else {}), "far_field": far}


def downstream(scene, blocks: int, eps: float, block_size: int = 256) -> dict:
    """Seconds a block costs after the form factors (pass statistics, per-solve samples, HF's leaf),
    for the sampled far field's blocks handed on in pieces and the same blocks made dense, at one
    BLAS thread (as the precompute's pushes run while the form factors are computed)."""
    from hfrad.formfactors.budget import ray_budget
    from hfrad.formfactors.engine import FormFactorEngine
    from hfrad.formfactors.farfield import SampledFarField
    from hfrad.lowrank.hf import ErrorBudget, compress_leaf, compress_leaf_pieces
    from hfrad.resources import blas_threads
    from hfrad.scene.zorder import zorder_permutation
    from hfrad.solve.stats import PassStatistics

    n = scene.n_patches
    perm = zorder_permutation(scene.centroids)
    rho = scene.reflectance.max(axis=1)[perm]
    w = np.asarray(scene.areas)[perm]
    engine = FormFactorEngine(scene, ray_budget=ray_budget(scene, eps / 4), ray_threads=None)
    producer = SampledFarField(scene, engine, perm, block_size, rho, eps, weights=w)
    m = -(-n // block_size)
    budget = ErrorBudget(eps, True, m, 0.5)
    stats = {mode: PassStatistics(n, w, reflectance=scene.reflectance[perm]) for mode in ("pieces", "dense")}
    seconds = {"pieces": 0.0, "dense": 0.0}
    ranks = {"pieces": [], "dense": []}
    dense_rows = 0
    with blas_threads(1):
        for j in np.linspace(1, m - 1, blocks).astype(int):
            P = producer.block(j)[0].astype(np.float32)
            dense_rows += P.rows.size
            start = j * block_size
            for mode in ("pieces", "dense"):
                t = time.perf_counter()
                A = P if mode == "pieces" else P.to_dense()
                G, norm2 = stats[mode].add_scaled(start, start + P.shape[1], A, rho[:, None].astype(np.float32))
                node = (compress_leaf_pieces if mode == "pieces" else compress_leaf)(G, budget, j, norm2)
                seconds[mode] += time.perf_counter() - t
                ranks[mode].append(int(node.s.size))
    producer.close()
    return {"n": n, "blocks": blocks, "pieces_s_per_block": seconds["pieces"] / blocks,
            "dense_s_per_block": seconds["dense"] / blocks, "speedup": seconds["dense"] / seconds["pieces"],
            "dense_row_share": dense_rows / (blocks * n), "same_leaf_ranks": ranks["pieces"] == ranks["dense"]}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--patches", default="40000")
    p.add_argument("--eps", type=float, default=0.02)
    p.add_argument("--modes", default="exact,sampled")
    p.add_argument("--scene", default="cornell")
    p.add_argument("--blocks", type=int, default=6)
    p.add_argument("--redraws", type=int, default=0,
                   help="per block: redraw the certificate this many times (and the systematic one of before)")
    p.add_argument("--end-to-end", action="store_true")
    p.add_argument("--save-radiosity", metavar="DIR", default=None,
                   help="with --end-to-end: keep each mode's radiosity as DIR/radiosity-SCENE-N-MODE.npy "
                        "(user order, W/m^2), to check the answers afterwards")
    p.add_argument("--reference", metavar="FILE", default=None,
                   help="with --end-to-end and without the exact mode: compare each mode with this exact "
                        "radiosity (a --save-radiosity file of an earlier run), e.g. when both do not fit "
                        "in one process")
    p.add_argument("--repeat", type=int, default=1,
                   help="with --end-to-end: run the modes this many times, in turn, and keep each one's "
                        "fastest run (its wall times all in walls_s)")
    p.add_argument("--downstream", action="store_true",
                   help="what a block costs after the form factors, in pieces and dense")
    common.add_blas_arg(p)
    args = p.parse_args()
    m = common.header("The sampled far field against the exact pass", args.blas_threads)
    if args.downstream:
        rows = [downstream(common.load_bench_scene(args.scene, size), args.blocks, args.eps)
                for size in common.parse_sizes(args.patches)]
        common.print_table(f"{args.scene}, eps {args.eps}: after the form factors, {args.blocks} blocks", rows,
                           ["n", "pieces_s_per_block", "dense_s_per_block", "speedup", "dense_row_share",
                            "same_leaf_ranks"])
        path = common.write_json(f"far-field-downstream-{args.scene}-" + "-".join(str(r["n"]) for r in rows),
                                 {"machine": m, "eps": args.eps, "rows": rows})
        print(f"wrote {path}")
        return
    if not args.end_to_end:
        rows = [per_block(common.load_bench_scene(args.scene, size), args.blocks, args.eps, redraws=args.redraws)
                for size in common.parse_sizes(args.patches)]
        common.print_table(f"{args.scene}, eps {args.eps}: {args.blocks} column blocks, exact and sampled", rows,
                           ["n", "exact_s_per_block", "sampled_s_per_block", "speedup",
                            "pairs_share", "traced_share", "kernel_share",
                            "near_share", "mixed_share", "probe_rays_per_pair",
                            "relative_error", "target", "weighted_error", "certificate", "certificate_upper",
                            "holdout"] + (["upper_below", "upper_ratio_min", "estimate_ratio_min",
                                           "estimate_ratio_max", "systematic_upper_below",
                                           "systematic_upper_ratio_min", "systematic_estimate_ratio_min",
                                           "systematic_wide_upper_below"] if args.redraws else []))
        path = common.write_json(f"far-field-blocks-{args.scene}-" + "-".join(str(r["n"]) for r in rows),
                                 {"machine": m, "eps": args.eps, "rows": rows})
        print(f"wrote {path}")
        return
    rows = []
    for size in common.parse_sizes(args.patches):
        scene = common.load_bench_scene(args.scene, size)

        def keep(mode, r, n=scene.n_patches):     # written at once: a later mode may not finish
            if args.save_radiosity:
                path = Path(args.save_radiosity) / f"radiosity-{args.scene}-{n}-{mode}.npy"
                path.parent.mkdir(parents=True, exist_ok=True)
                with atomic_path(path) as tmp, open(tmp, "wb") as fh:
                    np.save(fh, r["B"])

        results = best_runs(scene, common.parse_list(args.modes), args.eps, args.repeat, keep)
        exact = results.get("exact")
        if exact is None and args.reference:
            exact = {"B": np.load(args.reference), "wall_s": float("nan")}
        for r in results.values():
            if exact is not None and r is not exact:
                r["vs_exact"] = reflected_difference(r["B"], exact["B"], np.asarray(scene.emission, float),
                                                     scene.areas)
                r["time_ratio"] = exact["wall_s"] / r["wall_s"]
            rows.append({k: v for k, v in r.items() if k != "B"})
    common.print_table(f"{args.scene}, eps {args.eps}: exact pass vs sampled far field", rows,
                       ["n", "mode", "wall_s", "formfactors_s", "rank", "pairs_share",
                        "traced_share", "certificate", "certificate_upper",
                        "holdout", "vs_exact", "figure", "time_ratio"] + (["walls_s"] if args.repeat > 1 else []))
    path = common.write_json(f"far-field-end-to-end-{args.scene}-" + "-".join(str(r["n"]) for r in rows[::len(results)]),
                             {"machine": m, "eps": args.eps, "rows": rows})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
