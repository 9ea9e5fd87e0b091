"""Benchmark: one RGB relighting of a saved ``.hfr``, with its own reflectance and a grey one.

The near-field solver reads one ``Z_c`` per distinct channel (``D_c = rho_c /
rho_max``), so a coloured scene reads 3nk words where a grey one reads nk. This
loads a factorization (e.g. the one ``bench_scale.py --save`` kept), re-sets it
up with grey reflectances ``rho_max`` (``with_reflectance``: one channel's
sparse LU and Z), and times the scene's own emission on both, best and median
of 9, against the copy-bandwidth limit of reading 2nk words measured right
after each. Not collected by pytest; not in CI.

    PYTHONPATH=src python benchmarks/bench_relight_hfr.py /tmp/c163k.hfr --out relight-163k
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import common  # noqa: E402


def time_solve(fac, E, repeat: int = 9) -> dict:
    fac.solve(E)                                  # warm: numba, the transposed pattern
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fac.solve(E)
        times.append(time.perf_counter() - t)
    n, k = fac.n_patches, fac.rank
    src = np.ones(2 * n * k, fac.dtype)
    dst = np.empty_like(src)
    copies = []
    for _ in range(5):
        t = time.perf_counter()
        np.copyto(dst, src)
        copies.append(time.perf_counter() - t)
    bw = 2 * src.nbytes / min(copies)             # bytes moved per second (read + write)
    limit = src.nbytes / bw                       # reading 2nk words once
    return {"best_s": min(times), "median_s": float(np.median(times)), "sweeps": int(getattr(fac, "last_sweeps", 0)),
            "distinct_channels": len(getattr(fac, "distinct_channels", [0, 1, 2])),
            "copy_bandwidth_gbs": bw / 1e9, "limit_2nk_s": limit, "best_over_2nk": min(times) / limit,
            "median_over_2nk": float(np.median(times)) / limit}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("hfr")
    p.add_argument("--out", default="relight-hfr")
    args = p.parse_args()
    from hfrad.solve.hfr import load_hfr

    machine = common.header("bench_relight_hfr: one RGB relighting, own and grey reflectance", 1)
    t = time.perf_counter()
    fac = load_hfr(args.hfr)
    row = {"file": args.hfr, "n_patches": fac.n_patches, "rank": fac.rank, "solver": fac.solver,
           "time_load": time.perf_counter() - t}
    E = fac.scene.emission
    row["own"] = time_solve(fac, E)
    t = time.perf_counter()
    grey = fac.with_reflectance(np.repeat(fac.rho_max[:, None], 3, axis=1))
    row["time_grey_setup"] = time.perf_counter() - t
    row["grey"] = time_solve(grey, E)
    for name in ("own", "grey"):
        r = row[name]
        print(f"{name:5s} reflectance: {r['distinct_channels']} distinct channel(s), best {1e3 * r['best_s']:.1f} ms, "
              f"median {1e3 * r['median_s']:.1f} ms, {r['sweeps']} sweep(s); 2nk limit {1e3 * r['limit_2nk_s']:.1f} ms "
              f"({r['copy_bandwidth_gbs']:.1f} GB/s): best {r['best_over_2nk']:.2f}x, median {r['median_over_2nk']:.2f}x")
    common.write_json(args.out, {"runs": [row], "machine": machine})


if __name__ == "__main__":
    main()
