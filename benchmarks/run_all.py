"""Run every hfrad benchmark of a tier and write benchmarks/results/*-TIER.json.

Tiers
-----
quick  (< 10 minutes on 2 cores, F cached after the first run): ~2.5K patches; factorization
       on three scenes (built-in Cornell box and the two shared Cornell OBJs) with every
       method including both full SVDs; ordering, solve and out-of-core on the Cornell box.
large  (about an hour on 2 cores, plus ~5 minutes to build and cache F at 10K/20K once):
       10K and 20K patches (full SVD only up to 12K; the float64 SVD of a 10K matrix alone
       takes ~8 minutes here).

The form-factor benchmark (bench_formfactors.py) is separate and not run here.

Run:  python benchmarks/run_all.py [--tier quick|large] [--only factorize,solve]
      hfrad bench [--tier quick|large]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import common  # noqa: E402

TIERS: dict[str, list[tuple[str, list[str]]]] = {
    "quick": [
        ("factorize", ["--quick", "--out", "factorize-quick"]),
        ("order", ["--quick", "--out", "order-quick"]),
        ("solve", ["--quick", "--out", "solve-quick"]),
        ("outofcore", ["--quick", "--power-iters", "0,2", "--out", "outofcore-quick"]),
    ],
    "large": [
        ("factorize", ["--scenes", "cornell", "--sizes", "10000", "--methods", "hf32,hf64,svd32,svd64,rsvd,sketch",
                       "--repeat", "1", "--out", "factorize-large-cornell10k"]),
        ("factorize", ["--scenes", "cornell", "--sizes", "20000", "--methods", "hf32,hf64,rsvd",
                       "--repeat", "1", "--out", "factorize-large-cornell20k"]),
        ("factorize", ["--scenes", "cbox-original,cbox-empty", "--sizes", "10000",
                       "--methods", "hf32,hf64,rsvd,sketch", "--repeat", "1", "--out", "factorize-large-shared"]),
        ("order", ["--scenes", "cornell,cbox-original", "--sizes", "10000", "--repeat", "1",
                   "--out", "order-large"]),
        ("solve", ["--sizes", "10000", "--out", "solve-large"]),
        ("outofcore", ["--sizes", "10000", "--eps", "0.05,0.02", "--real-max-n", "0", "--out", "outofcore-large"]),
    ],
}


def run(tier: str = "quick", only: list[str] | None = None, extra: list[str] | None = None) -> int:
    """Run the benchmarks of ``tier`` in this process; returns 0 when all succeeded."""
    import bench_factorize
    import bench_order
    import bench_outofcore
    import bench_solve
    mains = {"factorize": bench_factorize.main, "order": bench_order.main, "solve": bench_solve.main,
             "outofcore": bench_outofcore.main}
    t0 = time.perf_counter()
    status = 0
    for name, argv in TIERS[tier]:
        if only and name not in only:
            continue
        print(f"\n===== {name} {' '.join(argv)} =====", flush=True)
        t = time.perf_counter()
        try:
            status |= mains[name](argv + list(extra or []))
        except Exception as exc:  # keep going: one failed benchmark should not hide the others
            print(f"FAILED: {name}: {type(exc).__name__}: {exc}", file=sys.stderr)
            status = 1
        print(f"===== {name}: {time.perf_counter() - t:.0f} s =====", flush=True)
    print(f"\ntier {tier}: {time.perf_counter() - t0:.0f} s in all; load now {os.getloadavg()[0]:.2f}")
    return status


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--tier", choices=sorted(TIERS), default="quick")
    p.add_argument("--only", default="", help="comma list of: factorize, order, solve, outofcore")
    args = p.parse_args(argv)
    return run(args.tier, common.parse_list(args.only) or None)


if __name__ == "__main__":
    sys.exit(main())
