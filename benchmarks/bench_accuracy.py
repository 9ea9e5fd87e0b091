"""Benchmark: form-factor accuracy against the closed forms, closure, and what it costs.

Run:  PYTHONPATH=src python benchmarks/bench_accuracy.py [--patches 3000,10000] [--repeat 2]
      [--baseline-ref 083c557] [--also-ref COMMIT,...] [--out accuracy]

1. Convergence: error of F_1->2 against the catalogue's closed forms for the
   kernel tolerance 1e-2 ... 1e-5, with every pair forced onto the adaptive path
   (near = adaptive = inf: the pure convergence of the adaptive rule) and with
   the default rules (what a user gets), with the kernel time.
2. Closure: row sums of F (visibility included) of the built-in Cornell box at
   each patch count: mean and worst |sum - 1|, patches off by more than 0.2%.
3. Visibility samples (``--samples-sweep``): row sums of the Cornell box at
   the smallest patch count with 4, 16, 36 and 64 rays per pair (every pair
   that needs rays), which shows what closing every row to 0.2% would cost.
4. Cost: the full F at the largest patch count, streamed in Z-order column
   blocks, with today's kernel (``--baseline-ref``, extracted with git archive),
   any ``--also-ref`` commits and this one, alternating in subprocesses of the
   same run; the load average is recorded with every timing.

Writes benchmarks/results/OUT.json (default accuracy.json). Not collected by pytest.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import header, print_table, write_json  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def convergence() -> list[dict]:
    from hfrad.formfactors import analytic
    from hfrad.formfactors.kernel import PatchGeometry, unoccluded_block
    from hfrad.scene.builtin import parallel_plates, perpendicular_plates
    from hfrad.scene.patches import subdivide

    cases = [("C-14 perpendicular 1,1,1 (shared edge)", perpendicular_plates(1, 1, 1),
              analytic.perpendicular_rectangles(1, 1, 1)),
             ("C-11 parallel 1x1 d0.1", parallel_plates(1, 1, 0.1), analytic.parallel_rectangles(1, 1, 0.1)),
             ("C-14 perpendicular 2,0.5,1", perpendicular_plates(2, 0.5, 1),
              analytic.perpendicular_rectangles(2, 0.5, 1))]
    rows = []
    for name, base, exact in cases:
        for splits in (1, 8):
            size = float(np.ptp(base.bounds, axis=0).max())
            scene = subdivide(base, max_edge=size / splits) if splits > 1 else base
            p1 = scene.group == scene.groups.index("plate1")
            p2 = scene.group == scene.groups.index("plate2")
            for mode, kw in (("adaptive only", {"near": 1e9, "adaptive": 1e9}), ("default rules", {})):
                for tol in (1e-2, 1e-3, 1e-4, 1e-5):
                    g = PatchGeometry(scene, tolerance=tol, **kw)
                    unoccluded_block(g, np.arange(2), np.arange(2))  # compile outside the timing
                    t = time.perf_counter()
                    F = unoccluded_block(g, np.arange(g.n), np.arange(g.n))
                    seconds = time.perf_counter() - t
                    f12 = float((scene.areas[p1, None] * F[np.ix_(p1, p2)]).sum() / scene.areas[p1].sum())
                    rows.append({"case": name, "patches": scene.n_patches, "rules": mode, "tolerance": tol,
                                 "rel_error": f12 / exact - 1, "kernel_s": seconds})
    return rows


def _worker(patches: int) -> dict:
    """One full F of the Cornell box in this interpreter's hfrad (run in a subprocess)."""
    from hfrad.formfactors.blocks import FormFactorEngine, iter_column_blocks
    from hfrad.scene.builtin import cornell_box
    from hfrad.scene.patches import subdivide
    from hfrad.scene.zorder import zorder_permutation

    warm = subdivide(cornell_box(), patches=200)  # load the numba cache outside the timing
    e = FormFactorEngine(warm)
    for _ in iter_column_blocks(warm, 64, engine=e):
        pass
    e.close()
    scene = subdivide(cornell_box(), patches=patches)
    order = zorder_permutation(scene.centroids)
    load0 = os.getloadavg()[0]
    t = time.perf_counter()
    cpu = time.process_time()  # all threads of this process: less sensitive to other users' load
    engine = FormFactorEngine(scene)
    sums = np.zeros(scene.n_patches)
    for _, _, block in iter_column_blocks(scene, 256, order=order, engine=engine):
        sums += block.sum(axis=1)
    seconds = time.perf_counter() - t
    cpu_s = time.process_time() - cpu
    err = np.abs(sums - 1)
    out = {"patches": scene.n_patches, "seconds": seconds, "cpu_s": cpu_s, "kernel_s": engine.kernel_seconds,
           "embree_s": engine.embree_seconds, "rays": engine.rays, "load_before": load0,
           "load_after": os.getloadavg()[0], "row_sum_mean_err": float(err.mean()),
           "row_sum_max_err": float(err.max()), "rows_off_by_0.2%": int((err > 2e-3).sum()),
           "hfrad": __import__("hfrad").__file__}
    engine.close()
    return out


def closure_vs_samples(patches: int) -> list[dict]:
    """Row sums of the Cornell box with more visibility rays per pair (the first round)."""
    from hfrad.formfactors.blocks import FormFactorEngine, iter_column_blocks
    from hfrad.scene.builtin import cornell_box
    from hfrad.scene.patches import subdivide

    scene = subdivide(cornell_box(), patches=patches)
    rows = []
    for samples in (4, 16, 36, 64):
        load0 = os.getloadavg()[0]
        t = time.perf_counter()
        engine = FormFactorEngine(scene, samples=samples)
        sums = np.zeros(scene.n_patches)
        for _, _, block in iter_column_blocks(scene, 256, engine=engine):
            sums += block.sum(axis=1)
        err = np.abs(sums - 1)
        rows.append({"patches": scene.n_patches, "samples": samples, "seconds": time.perf_counter() - t,
                     "rays_M": engine.rays / 1e6, "row_sum_mean_err": float(err.mean()),
                     "row_sum_max_err": float(err.max()), "rows_off_by_0.2%": int((err > 2e-3).sum()),
                     "load": load0})
        engine.close()
        print(rows[-1], flush=True)
    return rows


def _run_worker(src: Path, patches: int) -> dict:
    env = dict(os.environ, PYTHONPATH=str(src))
    res = subprocess.run([sys.executable, __file__, "--worker", str(patches)], env=env, cwd=str(src.parent),
                         capture_output=True, text=True, check=True)
    return json.loads(res.stdout.strip().splitlines()[-1])


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--patches", default="3000,10000")
    p.add_argument("--repeat", type=int, default=2)
    p.add_argument("--baseline-ref", default="083c557", help="git commit with today's kernel (v2)")
    p.add_argument("--also-ref", default="", help="more git commits to time in the same alternation "
                   "(comma separated; e.g. main before a change)")
    p.add_argument("--out", default="accuracy", help="results/OUT.json")
    p.add_argument("--worker", type=int, help=argparse.SUPPRESS)
    p.add_argument("--skip-convergence", action="store_true")
    p.add_argument("--samples-sweep", action="store_true", help="only the row sums vs visibility rays table")
    args = p.parse_args()
    if args.worker:
        print(json.dumps(_worker(args.worker)))
        return
    m = header("form-factor accuracy and its cost")
    out = {"machine": m}
    sizes = [int(x) for x in args.patches.split(",")]
    if args.samples_sweep:
        out["closure_vs_samples"] = closure_vs_samples(min(sizes))
        print_table("row sums vs visibility rays per pair", out["closure_vs_samples"],
                    ["patches", "samples", "seconds", "rays_M", "row_sum_mean_err", "row_sum_max_err",
                     "rows_off_by_0.2%", "load"])
        print("wrote", write_json("accuracy_samples", out))
        return
    if not args.skip_convergence:
        out["convergence"] = convergence()
        print_table("error against the closed form vs kernel tolerance", out["convergence"],
                    ["case", "patches", "rules", "tolerance", "rel_error", "kernel_s"])
    with tempfile.TemporaryDirectory() as tmp:
        arms = []
        for ref in [args.baseline_ref] + [r for r in args.also_ref.split(",") if r]:
            archive = subprocess.run(["git", "archive", ref, "src"], cwd=ROOT, capture_output=True,
                                     check=True).stdout
            (Path(tmp) / ref).mkdir()
            subprocess.run(["tar", "-x", "-C", str(Path(tmp) / ref)], input=archive, check=True)
            arms.append((("baseline " if ref == args.baseline_ref else "ref ") + ref, Path(tmp) / ref / "src"))
        arms.append(("this kernel", ROOT / "src"))
        runs = []
        for n in sizes:
            for k in range(args.repeat if n == max(sizes) else 1):
                for label, src in arms:
                    r = _run_worker(src, n)
                    r["kernel"] = label
                    r["requested"] = n
                    r["ns_per_pair"] = 1e9 * r["seconds"] / r["patches"] ** 2
                    runs.append(r)
                    print(f"{label:20s} n={r['patches']} total {r['seconds']:.1f} s, cpu {r['cpu_s']:.1f} s (kernel {r['kernel_s']:.1f} s, "
                          f"embree {r['embree_s']:.1f} s, {r['rays'] / 1e6:.1f} M rays), row sums mean "
                          f"{r['row_sum_mean_err']:.2e} max {r['row_sum_max_err']:.2e} "
                          f"({r['rows_off_by_0.2%']} rows > 0.2%), load {r['load_before']:.1f}->{r['load_after']:.1f}",
                          flush=True)
    out["runs"] = runs
    print_table("full F of the Cornell box, baseline and this kernel alternating", runs,
                ["kernel", "patches", "seconds", "cpu_s", "ns_per_pair", "kernel_s", "embree_s", "rays", "row_sum_mean_err",
                 "row_sum_max_err",
                 "rows_off_by_0.2%", "load_before", "load_after"])
    big = [r for r in runs if r["requested"] == max(sizes)]
    new = min((r for r in big if r["kernel"] == "this kernel"), key=lambda r: r["seconds"])
    out["time_ratios_largest"] = {}
    for label, _ in arms[:-1]:
        old = min((r for r in big if r["kernel"] == label), key=lambda r: r["seconds"])
        ratio, per_pair = new["seconds"] / old["seconds"], new["ns_per_pair"] / old["ns_per_pair"]
        cpu_ratio = min(r["cpu_s"] for r in big if r["kernel"] == "this kernel") / \
            min(r["cpu_s"] for r in big if r["kernel"] == label)
        out["time_ratios_largest"][label] = {"ratio": ratio, "per_pair": per_pair, "cpu_ratio": cpu_ratio}
        if label.startswith("baseline"):
            # the new floor triangulation gives a few % more patches at the same request: per pair too
            out["time_ratio_largest"], out["time_ratio_per_pair_largest"] = ratio, per_pair
        print(f"time ratio this / {label} at --patches {max(sizes)} (best of {args.repeat}): {ratio:.2f}x "
              f"({new['patches']} vs {old['patches']} patches; per pair {per_pair:.2f}x; CPU seconds {cpu_ratio:.2f}x)")
    print("wrote", write_json(args.out, out))


if __name__ == "__main__":
    main()
