"""Form factors of two source trees side by side: the whole F of the Cornell box, streamed.

Each tree runs in a fresh subprocess (``PYTHONPATH=<tree>/src``) that streams the
full n x n F in Z-ordered column blocks of 256 (float32, the precompute's path,
``iter_column_blocks``) with the pipeline's ray budget, and prints seconds, pairs/s
and the row sums. The trees alternate, so slow phases of the machine hit both.

    git archive <rev> src | tar -x -C /tmp/old          # the older tree
    PYTHONPATH=src python benchmarks/ff_side_by_side.py --trees /tmp/old,. --patches 40000 --processes 2

One JSON line per run is appended to ``results/ff-side-by-side-<n>.jsonl``.
Not collected by pytest; not in CI.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import common  # noqa: E402

_CHILD = """
import json, os, sys, time
import numpy as np
from hfrad.scene.load import load_scene
from hfrad.formfactors.blocks import iter_column_blocks
from hfrad.formfactors.budget import ray_budget
from hfrad.scene.zorder import patch_order
n_req, processes, eps = int(sys.argv[1]), int(sys.argv[2]), float(sys.argv[3])
scene = load_scene("cornell", patches=n_req)
n = scene.n_patches
perm = patch_order(scene.centroids, "zorder")
budget = ray_budget(scene, eps / 4)
t = time.perf_counter()
rows = np.zeros(n)
for start, stop, block in iter_column_blocks(scene, 256, order=perm, processes=processes, dtype=np.float32,
                                             ray_budget=budget):
    rows += block.sum(axis=1, dtype=np.float64)
seconds = time.perf_counter() - t
err = np.abs(rows - 1.0)
print("ROW " + json.dumps({"n_patches": n, "seconds": seconds, "pairs_per_second": n * n / seconds,
                          "row_sum_mean_error": float(err.mean()), "row_sum_worst_error": float(err.max()),
                          "cpu_seconds_children": sum(os.times()[2:4])}))
"""


def run(tree: str, patches: int, processes: int, eps: float) -> dict:
    env = {**os.environ, "PYTHONPATH": str(Path(tree).resolve() / "src")}
    proc = subprocess.run([sys.executable, "-c", _CHILD, str(patches), str(processes), str(eps)], env=env,
                          stdout=subprocess.PIPE, text=True, check=True)
    row = next(json.loads(line[4:]) for line in proc.stdout.splitlines() if line.startswith("ROW "))
    return row | {"tree": tree, "processes": processes, "eps": eps}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--trees", required=True, help="comma-separated source trees (each with src/hfrad)")
    p.add_argument("--patches", type=int, default=10000)
    p.add_argument("--processes", type=int, default=2)
    p.add_argument("--eps", type=float, default=0.02, help="the precompute's eps (ray budget eps/4)")
    p.add_argument("--repeat", type=int, default=1)
    args = p.parse_args()
    machine = common.header("ff_side_by_side: form factors of two trees", 1)
    for tree in args.trees.split(","):
        run(tree, 1000, args.processes, args.eps)   # compiles the tree's numba cache outside the timings
    rows = []
    for rep in range(args.repeat):
        for tree in args.trees.split(","):
            row = run(tree, args.patches, args.processes, args.eps) | {"repeat": rep, "loadavg": os.getloadavg()[0]}
            rows.append(row)
            print(f"{tree:>20s}  n={row['n_patches']:,}  {row['seconds']:7.1f} s  "
                  f"{row['pairs_per_second'] / 1e6:5.2f} M pairs/s  row sums {row['row_sum_mean_error']:.2e} / "
                  f"{row['row_sum_worst_error']:.2e}  load {row['loadavg']:.1f}", flush=True)
    out = common.RESULTS_DIR / f"ff-side-by-side-{rows[0]['n_patches'] // 1000}k.jsonl"
    with open(out, "a") as f:
        for row in rows:
            f.write(json.dumps(row | {"machine": machine, "time": time.strftime("%Y-%m-%d %H:%M")}) + "\n")
    print(f"appended to {out}")


if __name__ == "__main__":
    main()
