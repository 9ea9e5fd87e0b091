"""End to end: precompute the Cornell box (form factors + HF + Woodbury), then relight it.

What issue "The paper's core" asks to record: ``hfrad precompute cornell
--patches 10000 --eps 0.02`` then a solve, on 2 cores: total time (goal < 3 min),
peak memory (goal < 4 GB), rank, achieved error, eq. 5 bound, and the time of
one RGB relighting solve ``fac.solve(E)`` (goal < 30 ms).

Each size runs in its own process so that peak memory (``ru_maxrss``) is that
run's alone.

    python benchmarks/bench_precompute.py                 # 10K patches
    python benchmarks/bench_precompute.py --patches 2500,10000 --eps 0.02
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time

import numpy as np

from common import machine, machine_line, parse_list, parse_sizes, print_table, write_json


def one_run(patches: int, eps: float, dtype: str) -> dict:
    """Precompute + solve in this process; returns the measurements."""
    import hfrad

    t0 = time.perf_counter()
    scene = hfrad.load_scene("cornell", patches=patches)
    fac = hfrad.factorize(scene, eps=eps, dtype=dtype)
    t_pre = time.perf_counter() - t0
    rng = np.random.default_rng(0)
    E = scene.emission
    fac.solve(E)  # first call: page in the factors
    solves = []
    for _ in range(20):
        E_new = E * rng.uniform(0.5, 1.5, size=3)  # a relighting: new lamp colour
        t = time.perf_counter()
        fac.solve(E_new)
        solves.append(time.perf_counter() - t)
    batch = np.repeat(E[:, :, None], 100, axis=2) * rng.uniform(0.5, 1.5, size=(1, 3, 100))
    t = time.perf_counter()
    fac.solve(batch)
    t_batch = (time.perf_counter() - t) / 100
    info = fac.lowrank.info
    return {
        "patches": fac.n_patches, "eps": eps, "dtype": dtype, "rank": fac.rank,
        "achieved_error": fac.relative_error, "sigma_max": list(fac.sigma_max()),
        "eq5_bound": list(fac.error_bound()), "precompute_s": t_pre,
        "formfactors_s": info["time_formfactors"], "hf_s": info["time_total"],
        "solve_rgb_ms_median": 1e3 * float(np.median(solves)), "solve_rgb_ms_min": 1e3 * min(solves),
        "solve_rgb_ms_batched_per_emission": 1e3 * t_batch,
        "peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20,
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--patches", default="10000", help="comma-separated patch counts (default 10000)")
    p.add_argument("--eps", default="0.02", help="comma-separated eps values")
    p.add_argument("--dtype", default="float32")
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.child:
        print(json.dumps(one_run(int(args.patches), float(args.eps), args.dtype)))
        return
    rows = []
    for n in parse_sizes(args.patches):
        for eps in parse_list(args.eps, float):
            t = time.perf_counter()
            out = subprocess.run([sys.executable, __file__, "--child", "--patches", str(n), "--eps", str(eps),
                                  "--dtype", args.dtype], capture_output=True, text=True, check=True)
            row = json.loads(out.stdout.strip().splitlines()[-1])
            row["wall_s"] = time.perf_counter() - t
            rows.append(row)
    print(machine_line())
    print_table("precompute + relight, Cornell box", rows,
                ["patches", "eps", "rank", ("achieved_error", "achieved"), ("precompute_s", "precompute s"),
                 ("formfactors_s", "form factors s"), ("hf_s", "HF s"), ("peak_rss_gb", "peak GB"),
                 ("solve_rgb_ms_median", "RGB solve ms"),
                 ("solve_rgb_ms_batched_per_emission", "batched ms/emission")])
    write_json("precompute", {"machine": machine(), "rows": rows})


if __name__ == "__main__":
    main()
