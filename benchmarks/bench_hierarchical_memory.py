"""Peak memory of ``far_field="hierarchical"`` with the H-matrix's values in float32 and in bfloat16 (issue 43).

For each size and each kind of value (``HMatrixOptions.values``), one precompute
``hfrad.factorize(cornell, eps, far_field="hierarchical")`` runs in a process of its own (so each
peak is its own), with its resident memory sampled every 0.25 s and marked at the stages the
precompute reports; then one solve of the scene's emission with its error figure. Side by side in
one run: peak RSS (getrusage) against the estimate the precompute checked
(:func:`hfrad.memory.precompute_peak_bytes`), the H-matrix's bytes, wall and stage seconds, rank,
certificate, per-solve figures, and how far the bfloat16 run's radiosity lies from the float32
run's (``||B16 - B32||_A / ||B32 - E||_A`` a channel: the per-solve figure's norm).

Not a test: prints a table and writes results/hierarchical-memory-values-SCENE-SIZES.json with the
machine. Run: ``PYTHONPATH=src python3 benchmarks/bench_hierarchical_memory.py --patches 163000
[--values float32,bfloat16] [--eps 0.05] [--no-memory-check]``. Memory: each run needs what the estimate says
(``hfrad precompute --help``); they run one after the other.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

import common
from bench_far_field import reflected_difference


def _rss_bytes() -> int:
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


class _Sampler:
    """This process's RSS every ``period`` s in a thread, with the precompute's stage marks."""

    def __init__(self, period: float = 0.25) -> None:
        self.t0, self.samples, self.marks, self.period = time.perf_counter(), [], [], period
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(self.period):
            self.samples.append((time.perf_counter() - self.t0, _rss_bytes()))

    def mark(self, what) -> None:
        self.marks.append((time.perf_counter() - self.t0, str(what)[:120], _rss_bytes()))

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()


def child(scene_name: str, patches: int, values: str, eps: float, out: Path, check: bool = True) -> None:
    """One precompute and one solve, in this process; writes ``out``.json and ``out``.npy (B). Without
    ``check`` the precompute's memory checks (before the run and as the basis grows) are switched off:
    to measure the peak of a run that the estimate refuses."""
    import hfrad
    import hfrad.precompute.hierarchical as hierarchical

    if not check:
        hierarchical.check_hierarchical_memory = lambda *a, **k: None
        hierarchical.basis_guard = lambda *a, **k: (lambda columns, more: None)
    from hfrad.formfactors.hmatrix import HMatrixOptions
    from hfrad.precompute.options import HMATRIX_EPS_SHARE, plan_precompute

    scene = common.load_bench_scene(scene_name, patches)
    options = hfrad.PrecomputeOptions(hmatrix=HMatrixOptions(tolerance=HMATRIX_EPS_SHARE * eps, values=values))
    plan = plan_precompute(scene, eps, near_field="auto", far_field="hierarchical", options=options)  # factorize's
    estimate = hierarchical.hierarchical_peak_bytes(plan, scene.is_clustered)   # the check's own figure
    sampler = _Sampler()
    t0 = time.perf_counter()
    fac = hfrad.factorize(scene, eps, far_field="hierarchical", options=options, status=sampler.mark)
    wall = time.perf_counter() - t0
    E = np.asarray(scene.emission, float)
    B, err = fac.solve(E, return_error=True)
    sampler.stop()
    info = fac.lowrank.info
    h = info["hierarchical"]
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    row = {"n": scene.n_patches, "values": values, "memory_check": check, "wall_s": wall,
           "peak_rss_gib": peak / 2 ** 30, "estimate_gib": estimate / 2 ** 30, "hmatrix_gib": h["bytes"] / 2 ** 30,
           "storage_floats": h["storage_floats"],
           "rank": fac.rank, "basis": h["factorization"]["basis"], "near_nnz": info.get("near_nnz"),
           "pairs_share": h["pairs_share"], "exact_share": h["exact_pairs"] / scene.n_patches ** 2,
           "hierarchical": {k: v for k, v in h.items() if k != "factorization"},
           "certificate_relative": h["certificate"]["error_estimate"] / fac.lowrank.norm,
           "figure": [float(x) for x in np.ravel(err.bound)],
           "stages": {k: info[k] for k in ("time_formfactors", "time_statistics", "time_certificate",
                                           "time_factorization", "time_assemble") if k in info},
           "marks": sampler.marks,
           "rss_gib": [(round(t, 2), round(r / 2 ** 30, 3)) for t, r in sampler.samples[::4]]}
    np.save(f"{out}.npy", B)
    Path(f"{out}.json").write_text(json.dumps(common._jsonable(row)))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--patches", default="40000")
    p.add_argument("--values", default="float32,bfloat16")
    p.add_argument("--eps", type=float, default=0.05)
    p.add_argument("--scene", default="cornell")
    p.add_argument("--no-memory-check", action="store_true",
                   help="switch the precompute's memory checks off (to measure a run the estimate refuses; "
                        "it may run the machine out of memory)")
    p.add_argument("--child", nargs=2, metavar=("VALUES", "OUT"), help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.child:
        child(args.scene, int(args.patches), args.child[0], args.eps, Path(args.child[1]), not args.no_memory_check)
        return
    m = common.header("far_field='hierarchical': peak memory with float32 and bfloat16 values")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for size in common.parse_sizes(args.patches):
            answers = {}
            for values in common.parse_list(args.values):
                out = Path(tmp) / f"{size}-{values}"
                subprocess.run([sys.executable, __file__, "--patches", str(size), "--scene", args.scene,
                                "--eps", str(args.eps), "--child", values, str(out)]
                               + (["--no-memory-check"] if args.no_memory_check else []), check=True)
                row = json.loads(Path(f"{out}.json").read_text())
                answers[values] = np.load(f"{out}.npy")
                rows.append(row)
            if {"float32", "bfloat16"} <= answers.keys():
                scene = common.load_bench_scene(args.scene, size)
                rows[-1]["vs_float32"] = reflected_difference(answers["bfloat16"], answers["float32"],
                                                              np.asarray(scene.emission, float), scene.areas)
    common.print_table(f"{args.scene}, eps {args.eps}: peak memory by the H-matrix's values", rows,
                       ["n", "values", "wall_s", "peak_rss_gib", "estimate_gib", "hmatrix_gib", "rank", "pairs_share",
                        "certificate_relative", "figure", "vs_float32"])
    path = common.write_json(f"hierarchical-memory-values-{args.scene}-" + "-".join(
        str(n) for n in dict.fromkeys(r["n"] for r in rows)), {"machine": m, "eps": args.eps, "rows": rows})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
