from hfrad import LocalBackend
"""Benchmark: large scenes end to end (form factors + HF + Woodbury), and how each stage scales.

Every size runs in a fresh subprocess (so its peak RSS is its own) through
``hfrad.pipeline.factorize`` exactly as ``hfrad precompute`` runs it, and
reports per stage: form-factor wall time, HF time (leaf SVDs + merges),
Woodbury set-up, peak RSS, rank, eps and the achieved error, the a-posteriori
radiosity residual (one more streamed pass over F, optional), and one RGB
relighting solve against the copy-bandwidth limit of reading 2nk and 4nk
words (measured in the same process). Exponents of time and memory against n
are fitted over the sizes that finished.

``--ffprobe N`` measures the form-factor engine alone on a few column blocks of
the same scene: one process (numba threads + one Embree thread) vs worker
processes, pairs/s and rays/s, against raw ``embreex`` on the very same rays.

Not collected by pytest; not in CI. Reproduce (2 cores; 10K-20K take minutes,
40K ~15 min, 80K and 163K hours and most of the machine's memory)::

    PYTHONPATH=src python benchmarks/bench_scale.py --sizes 10000,20000,40000 --ffprobe 10000
    PYTHONPATH=src python benchmarks/bench_scale.py --sizes 10000 --scene sibenik --residual
    PYTHONPATH=src python benchmarks/bench_scale.py --report          # table of results/scale.json

Results accumulate in ``benchmarks/results/scale.json`` (one row per run, with
``n_patches``, the machine and the load average).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import common  # noqa: E402

RESULT = "scale"

#: Real scenes: (file under the shared scenes folder, load options).
REAL = {
    "sibenik": ("sibenik/sibenik.obj", {"area_light": (30.0, 30.0, 30.0)}),
    # the cathedral lit from inside: its stained-glass windows emit
    "sibenik-windows": ("sibenik/sibenik.obj", {"emit": {"staklo_zuto": (40.0, 36.0, 20.0), "staklo_plavo": (20.0, 20.0, 40.0),
                                                         "staklo_crveno": (40.0, 15.0, 15.0),
                                                         "staklo_zeleno": (15.0, 40.0, 15.0)}}),
    "sponza": ("sponza-dabrovic/sponza.obj", {"area_light": (30.0, 30.0, 30.0)}),
}


def load(scene: str, patches: int):
    from hfrad.scene.load import load_scene
    if scene == "cornell":
        return load_scene("cornell", patches=patches)
    rel, kw = REAL[scene]
    path = common.SHARED_SCENES / rel
    if not path.exists():
        raise FileNotFoundError(f"{path} not found (set HFRAD_SHARED_SCENES)")
    return load_scene(str(path), patches=patches, **kw)


def copy_seconds(nbytes: int, repeat: int = 5) -> float:
    """Best time to copy ``nbytes`` (reads nbytes, writes nbytes)."""
    src = np.ones(max(nbytes // 4, 1), np.float32)
    dst = np.empty_like(src)
    best = math.inf
    for _ in range(repeat):
        t = time.perf_counter()
        np.copyto(dst, src)
        best = min(best, time.perf_counter() - t)
    return best


def _status_printer(n: int, every: float = 60.0):
    """A ``status`` callback printing blocks done and rank to stderr about once a minute."""
    last = [time.perf_counter()]

    def show(state: dict) -> None:
        if time.perf_counter() - last[0] >= every:
            last[0] = time.perf_counter()
            print(f"    n={n:,}: {state['blocks']} blocks, rank {state['rank']:,}, {state['elapsed']:.0f} s, "
                  f"load {os.getloadavg()[0]:.1f}", file=sys.stderr, flush=True)
    return show


def run_one(args) -> dict:
    """One size, in this process: the precompute, then a relighting solve and the residual."""
    from hfrad.pipeline import factorize

    common.set_blas_threads(1)
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    scene = load(args.scene, args.one)
    t_load = time.perf_counter() - t0
    n = scene.n_patches
    t1 = time.perf_counter()
    checkpoint = None
    if args.checkpoint:
        Path(args.checkpoint).mkdir(parents=True, exist_ok=True)
        checkpoint = Path(args.checkpoint) / f"{args.scene}-{args.one}-{args.eps}-{args.near_field}.ckpt"
    with common.TreeMemorySampler() as memory:   # this process and its form-factor workers, summed
        fac = factorize(scene, eps=args.eps, near_field=args.near_field or None, status=_status_printer(n),
                        backend=LocalBackend(processes=args.processes), checkpoint=checkpoint)
    t_total = time.perf_counter() - t1
    info = fac.lowrank.info
    k = fac.rank
    row = {"scene": args.scene, "n_patches": n, "eps": args.eps, "rank": k, "solver": fac.solver,
           "achieved_error": fac.relative_error, "processes": args.processes,
           "time_load": t_load, "time_formfactors": info["time_formfactors"],
           "time_hf": info["time_total"], "time_hf_leaf": info["time_leaf"], "time_hf_merge": info["time_merge"],
           "time_woodbury": t_total - info["time_precompute"], "time_precompute": t_total,
           # the stream's own work besides form factors and HF: statistics, near split, checkpoints
           "time_stream_other": info["time_precompute"] - info["time_formfactors"] - info["time_total"],
           "time_checkpoints": info.get("time_checkpoints", 0.0),
           "time_nearfield_setup": info.get("time_nearfield_setup", 0.0),
           "loadavg_start": load0}
    if args.save:
        from hfrad.solve.hfr import save_hfr
        t = time.perf_counter()
        save_hfr(fac, args.save, scene=scene)
        row["time_save"] = time.perf_counter() - t
        row["saved"] = str(args.save)
    E = scene.emission
    if not (E > 0).any():
        E = np.zeros((n, 3))
        E[: max(1, n // 100)] = 10.0
    fac.solve(E)
    times = []
    for _ in range(7):
        t = time.perf_counter()
        B = fac.solve(E)
        times.append(time.perf_counter() - t)
    own_sweeps = int(getattr(fac, "last_sweeps", 0))      # of the scene's own emission
    row["solve_rgb_seconds"] = float(np.median(times))
    row["solve_rgb_best"] = float(min(times))
    itemsize = fac.Q.dtype.itemsize
    t_copy = copy_seconds(2 * n * k * itemsize)
    bw = 2 * (2 * n * k * itemsize) / t_copy            # bytes moved per second by a copy
    row["copy_bandwidth_gbs"] = bw / 1e9
    row["limit_2nk_seconds"] = 2 * n * k * itemsize / bw
    row["limit_4nk_seconds"] = 4 * n * k * itemsize / bw
    row["solve_over_2nk_limit"] = row["solve_rgb_best"] / max(row["limit_2nk_seconds"], 1e-12)
    # a harder relighting for the near-field sweeps: every 100th patch emits (emitters next to
    # every wall, not only the lamp, whose own near field is empty on the built-in box)
    spread = np.zeros((n, 3))
    spread[::100] = 10.0
    times = []
    for _ in range(5):
        t = time.perf_counter()
        fac.solve(spread)
        times.append(time.perf_counter() - t)
    row["solve_spread_best"] = float(min(times))
    row["near_sweeps_spread"] = int(getattr(fac, "last_sweeps", 0))
    N = getattr(fac, "N", None)
    if N is not None:
        # the near-field solve reads V, each distinct Z_c and, per sweep, N (value + column index)
        row["near_nnz"] = int(N.nnz)
        row["near_sweeps"] = own_sweeps
        once = n * k * itemsize + fac.Z.nbytes + N.nnz * (itemsize + 4)      # Z_c may be 16-bit
        row["near_solution_storage"] = fac.near_solution_storage
        row["limit_read_once_seconds"] = once / bw
        row["solve_over_read_once_limit"] = row["solve_rgb_best"] / max(row["limit_read_once_seconds"], 1e-12)
    if args.residual:
        from hfrad.formfactors import iter_column_blocks
        from hfrad.solve.bounds import residual_norm
        t = time.perf_counter()
        res = residual_norm(iter_column_blocks(scene, 256, processes=args.processes), scene.reflectance, E, B)
        row["residual"] = np.asarray(res).tolist()
        row["time_residual"] = time.perf_counter() - t
    row["error_bound_eq5"] = np.asarray(fac.error_bound()).tolist()
    row["peak_rss_gb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 1e9
    row["peak_rss_children_gb"] = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024 / 1e9
    # the precompute's peak of the whole process tree at one instant (PSS: shared slots once), and
    # how much more memory the machine held than before it (sampled every second)
    row["peak_tree_pss_gb"] = memory.peak_tree_pss / 1e9
    row["peak_system_used_gb"] = memory.peak_system_used / 1e9
    row["loadavg_end"] = os.getloadavg()[0]
    if args.image:
        from hfrad.render import render_image, save_png
        img = render_image(scene, B, camera=args.camera)
        save_png(img, args.image)
        row["image"] = str(args.image)
    return row


def ffprobe(args) -> dict:
    """Form-factor engine alone on a few blocks: 1 process vs workers, vs raw Embree on the same rays."""
    from hfrad.formfactors.blocks import FormFactorEngine, make_engine
    from hfrad.formfactors.budget import ray_budget
    from hfrad.scene.zorder import zorder_permutation

    scene = load(args.scene, args.ffprobe)
    n = scene.n_patches
    order = zorder_permutation(scene.centroids)
    b = 256
    starts = list(range(0, n, max(b, n // args.blocks)))[: args.blocks]
    col_sets = [order[s:s + b] for s in starts]
    pairs = n * sum(len(c) for c in col_sets)
    budget = ray_budget(scene, 0.25 * args.eps)  # the pipeline's: one-ray and few-rays rules
    out = {"scene": args.scene, "n_patches": n, "blocks": len(col_sets), "pairs": pairs,
           "one_ray_below": budget.one_ray_below, "few_rays_below": budget.few_rays_below, "loadavg_start": os.getloadavg()[0], "cpu_seconds": {}}
    warm = FormFactorEngine(scene)
    warm.block(order[:64], order[:64])  # numba cache load outside the timings
    for label, processes, rb in (("1 process", 1, None), ("1 process, ray budget", 1, budget),
                                 (f"{args.workers} processes", args.workers, None),
                                 (f"{args.workers} processes, ray budget", args.workers, budget)):
        eng = make_engine(scene, processes=processes, ray_budget=rb, dtype=np.float32)
        c0 = os.times()
        t = time.perf_counter()
        for _ in eng.iter_blocks(order, col_sets):
            pass
        wall = time.perf_counter() - t
        c1 = os.times()
        cpu = (c1.user - c0.user) + (c1.system - c0.system) + (c1.children_user - c0.children_user) \
            + (c1.children_system - c0.children_system)
        out[label] = {"seconds": wall, "pairs_per_s": pairs / wall, "rays": eng.rays,
                      "rays_per_s": eng.rays / wall, "embree_seconds": eng.embree_seconds,
                      "kernel_seconds": eng.kernel_seconds, "cpu_seconds": cpu}
        eng.close()
        print(f"  {label}: {wall:.2f} s, {pairs / wall / 1e6:.2f} M pairs/s, {eng.rays / 1e6:.1f} M rays, "
              f"{eng.rays / wall / 1e6:.2f} M rays/s (cpu {cpu:.1f} s)", flush=True)
    # raw embreex on the very same rays (the plain rule's rays), one thread, this process
    vis = warm.visibility
    rays, raw_t = 0, 0.0
    for cols in col_sets:
        F = warm._kernel(order, cols)
        for job in vis.jobs(F, order, cols):
            t = time.perf_counter()
            vis.caster._scene.run(job.o, job.d, query="OCCLUDED", dists=job.t)  # noqa: SLF001
            raw_t += time.perf_counter() - t
            rays += len(job.t)
            job.pool.put(job.buf)
    warm.close()
    out["raw_embree_rays_per_s"] = rays / raw_t
    out["raw_embree_rays"] = rays
    out["loadavg_end"] = os.getloadavg()[0]
    print(f"  raw embreex (1 thread) on the same {rays / 1e6:.1f} M rays: {rays / raw_t / 1e6:.2f} M rays/s", flush=True)
    return out


def fit(rows: list[dict], key: str) -> float | None:
    pts = [(r["n_patches"], r[key]) for r in rows if r.get(key)]
    if len({p[0] for p in pts}) < 2:
        return None
    x, y = np.log([p[0] for p in pts]), np.log([p[1] for p in pts])
    return float(np.polyfit(x, y, 1)[0])


def report(data: dict) -> None:
    rows = [r for r in data.get("runs", []) if "n_patches" in r]
    cols = [("scene", "scene"), ("n_patches", "n"), ("rank", "k"), ("achieved_error", "achieved"),
            ("time_formfactors", "FF s"), ("time_hf", "HF s"), ("time_woodbury", "Woodbury s"),
            ("time_precompute", "total s"), ("peak_rss_gb", "RSS GB"),
            ("peak_tree_pss_gb", "all processes PSS GB"), ("solve_rgb_best", "solve s"),
            ("solve_over_2nk_limit", "solve / 2nk limit"), ("near_sweeps", "sweeps"),
            ("solve_spread_best", "solve s (1% emit)"), ("near_sweeps_spread", "sweeps (1% emit)"),
            ("solve_over_read_once_limit", "solve / read-once limit"), ("loadavg_start", "load")]
    common.print_table("bench_scale: end to end", rows, cols)
    cornell = [r for r in rows if r["scene"] == "cornell"]
    for key in ("time_formfactors", "time_hf", "time_precompute", "peak_rss_gb", "rank"):
        e = fit(cornell, key)
        if e is not None:
            print(f"fitted exponent of {key} vs n (Cornell): {e:.2f}")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sizes", default="", help="patch counts, e.g. 10000,20000,40000")
    p.add_argument("--scene", default="cornell", choices=["cornell", *REAL])
    p.add_argument("--eps", type=float, default=0.02)
    p.add_argument("--processes", type=int, default=1, help="form-factor processes (default 1)")
    p.add_argument("--near-field", type=int, default=0)
    p.add_argument("--residual", action="store_true", help="also stream F once more for the residual")
    p.add_argument("--image", default=None, help="render the solution to this PNG (one size)")
    p.add_argument("--save", default=None, help="also write the factorization to this .hfr (one size)")
    p.add_argument("--camera", default="auto")
    p.add_argument("--ffprobe", type=int, default=0, help="probe the form-factor engine at this patch count")
    p.add_argument("--blocks", type=int, default=6)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--checkpoint", default=None,
                   help="folder for checkpoints: an interrupted size resumes when rerun (large runs)")
    p.add_argument("--report", action="store_true")
    p.add_argument("--out", default=RESULT, help="results/NAME.json to add to (default scale)")
    p.add_argument("--one", type=int, default=0, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.one:
        print("ROW " + json.dumps(common._jsonable(run_one(args))), flush=True)  # noqa: SLF001
        return
    path = common.RESULTS_DIR / f"{args.out}.json"
    data = json.loads(path.read_text()) if path.exists() else {"runs": [], "ffprobe": []}
    if args.report:
        report(data)
        return
    m = common.header("bench_scale: large scenes end to end", 1)
    if args.ffprobe:
        r = ffprobe(args)
        r["machine"] = m
        data.setdefault("ffprobe", []).append(r)
        common.write_json(args.out, data)
    for size in common.parse_sizes(args.sizes) if args.sizes else []:
        cmd = [sys.executable, __file__, "--one", str(size), "--scene", args.scene, "--eps", str(args.eps),
               "--near-field", str(args.near_field), f"--camera={args.camera}"]
        cmd += ["--processes", str(args.processes)] if args.processes else []
        cmd += ["--residual"] if args.residual else []
        cmd += ["--image", args.image] if args.image else []
        cmd += ["--save", args.save] if args.save else []
        cmd += ["--checkpoint", args.checkpoint] if args.checkpoint else []
        print(f"running {args.scene} at {size:,} patches (load {os.getloadavg()[0]:.1f}) ...", flush=True)
        proc = subprocess.run(cmd, stdout=subprocess.PIPE, text=True)  # its progress goes to stderr
        rows = [json.loads(line[4:]) for line in proc.stdout.splitlines() if line.startswith("ROW ")]
        if proc.returncode or not rows:
            print(f"  failed (exit {proc.returncode}; its messages are above)", flush=True)
            continue
        row = rows[0] | {"machine": m}
        print(f"  n={row['n_patches']:,} rank {row['rank']:,} FF {row['time_formfactors']:.0f} s, "
              f"HF {row['time_hf']:.0f} s, total {row['time_precompute']:.0f} s, RSS {row['peak_rss_gb']:.2f} GB "
              f"(all processes {row['peak_tree_pss_gb']:.2f} GB), "
              f"solve {1e3 * row['solve_rgb_best']:.1f} ms ({row['solve_over_2nk_limit']:.1f}x the 2nk limit, "
              f"{row.get('solve_over_read_once_limit', row['solve_over_2nk_limit']):.1f}x reading every factor once), "
              f"load {row['loadavg_start']:.1f}-{row['loadavg_end']:.1f}", flush=True)
        data["runs"].append(row)
        common.write_json(args.out, data)
    report(data)


if __name__ == "__main__":
    main()
