"""Benchmark: one RGB relighting of a saved ``.hfr``: float32 or 16-bit ``Z_c``, own or grey reflectance.

The near-field solver reads one ``Z_c`` per distinct channel (``D_c = rho_c /
rho_max``), so a coloured scene reads 3nk words of Z where a grey one reads
nk; stored in 16 bits (``QuantizedRows``, the default for float32 factors where
the error allows) they are half the bytes. This loads a factorization (e.g. the
one ``bench_scale.py --save`` kept), times it as stored, then re-sets it up
(sparse LU and Z per distinct channel) with its own reflectance and with grey
reflectances ``rho_max``, each with float32 and with 16-bit ``Z_c``, and times
the scene's own emission on each, best and median of 9, against the
copy-bandwidth limit of reading 2nk words measured right after each. Not
collected by pytest; not in CI.

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
    from hfrad.solve.nearfield import NearFieldFactorization

    machine = common.header("bench_relight_hfr: one RGB relighting, own and grey reflectance", 1)
    t = time.perf_counter()
    fac = load_hfr(args.hfr)
    row = {"file": args.hfr, "n_patches": fac.n_patches, "rank": fac.rank, "solver": fac.solver,
           "time_load": time.perf_counter() - t}
    E = fac.scene.emission
    row["stored"] = time_solve(fac, E)
    row["stored"]["near_solution"] = fac.near_solution_storage
    grey = np.repeat(fac.rho_max[:, None], 3, axis=1)
    for name, rho in (("own", fac.reflectance), ("grey", grey)):
        for storage, quantize in (("float32", False), ("int16", True)):
            t = time.perf_counter()
            other = NearFieldFactorization(fac.perm, fac.Q, fac.V, fac.N, fac.rho_max, rho, fac.lowrank,
                                           quantize=quantize, stats=fac.stats, scene=fac.scene)
            key = f"{name}_{storage}"
            row[f"time_setup_{key}"] = time.perf_counter() - t
            row[key] = time_solve(other, E)
            row[key]["quantization_share"] = float(other.quantization_error().max() / other.achieved_error)
            B = other.solve(E)
            if quantize:     # the 16-bit Z's radiosity against the float32 Z's (relative, per channel)
                row[key]["moved_vs_float32"] = (np.linalg.norm(B - B_float, axis=0)
                                                / np.linalg.norm(B_float, axis=0)).tolist()
            B_float = B
            del other
    for key in ("stored", "own_float32", "own_int16", "grey_float32", "grey_int16"):
        r = row[key]
        print(f"{key:13s}: {r['distinct_channels']} distinct channel(s), best {1e3 * r['best_s']:.1f} ms, "
              f"median {1e3 * r['median_s']:.1f} ms, {r['sweeps']} sweep(s); 2nk limit {1e3 * r['limit_2nk_s']:.1f} ms "
              f"({r['copy_bandwidth_gbs']:.1f} GB/s): best {r['best_over_2nk']:.2f}x, median {r['median_over_2nk']:.2f}x")
    common.write_json(args.out, {"runs": [row], "machine": machine})


if __name__ == "__main__":
    main()
