"""Per-task costs of the Dask precompute, measured with Dask's own scheduling, and a model built from them.

Measure (``--measure``, the default when no ``--from`` is given), on a LocalCluster of
2 single-thread worker processes with ``NUMBA_NUM_THREADS=1`` (one core per task, so a
task's CPU seconds are its cost on one core of a bigger machine):

1. a whole ``factorize_distributed`` run at ``--patches`` (eps 0.05, near field on, the
   top merges by row panels): every task's record (leaf form factors, leaf SVD + near split
   + statistics, whole merges, panel Gram / small step / forming / V chunks, row slices);
2. at each of ``--sizes`` (default 40,000 and 163,000 patches): ``--leaves`` column blocks
   spread over the z-order, two whole merges of pairs of them and one merge of those two
   by ``--panels`` row panels -- the costs of the leaves and of the merge steps at that n.

Model (always): per-task cost laws fitted to those records (CPU seconds on one core),
the rank law k(n) of the measured runs in ``benchmarks/results/scale-*.json``, and the
client-side assembly (near-field set-up + Woodbury) measured by the single-machine runs
at 39K and 163K; then the wall time and memory per worker for 163K patches on 8 and 64
workers of 2 cores and 1M patches on 64 workers of 32 cores (eps 0.05, near field).
Every assumption is printed with the table and stored in the JSON.

    python benchmarks/bench_cluster_model.py                        # measure (a few minutes) + model
    python benchmarks/bench_cluster_model.py --from results/cluster-model.json   # the model again
"""

from __future__ import annotations

import os

os.environ.setdefault("NUMBA_NUM_THREADS", "1")   # before numba is imported here or in the workers

import argparse   # noqa: E402
import json   # noqa: E402
import math   # noqa: E402
import sys   # noqa: E402
import time   # noqa: E402
from pathlib import Path   # noqa: E402

import numpy as np   # noqa: E402

from common import RESULTS_DIR, header, print_table, write_json   # noqa: E402

EPS = 0.05
BLOCK = 256


# -- measuring ---------------------------------------------------------------------------------------
def _collect(client, topic: str, sink: list):
    def handler(event):
        msg = event[1] if isinstance(event, tuple) else event
        if msg.get("kind") == "task":
            sink.append(msg["record"])
    client.subscribe_topic(topic, handler)


def measure_full(cluster, patches: int) -> dict:
    from hfrad.distributed import factorize_distributed
    from hfrad.precompute import DaskBackend, PrecomputeOptions, plan_precompute
    from hfrad.precompute.options import near_entries
    from hfrad.scene.load import load_scene

    scene = load_scene("cornell", patches=patches)
    options = plan_precompute(scene, EPS, near_field=near_entries("auto", scene.n_patches),
                              options=PrecomputeOptions(block_size=BLOCK), reciprocity=False)
    records = []
    load0 = os.getloadavg()[0]
    t = time.perf_counter()
    fac = factorize_distributed(scene, options, DaskBackend(scheduler=cluster, records=records))
    wall = time.perf_counter() - t
    info = fac.lowrank.info
    return {"n": scene.n_patches, "wall_s": wall, "rank": fac.rank, "relative_error": fac.relative_error,
            "near_nnz": info.get("near_nnz"), "time_nearfield_setup": info.get("time_nearfield_setup"),
            "n_blocks": info["n_blocks"], "panelled_merges": info["panelled_merges"],
            "row_panels": info["row_panels"], "loadavg_before": load0, "loadavg_after": os.getloadavg()[0],
            "records": records}


def measure_sample(cluster, patches: int, leaves: int, panel_count: int) -> dict:
    """``leaves`` leaf tasks at this n, whole merges of pairs, one panelled merge of two of those."""
    import uuid

    from hfrad.distributed import run
    from hfrad.distributed.tasks import leaf_task, merge_task
    from hfrad.distributed.panels import panel_bounds
    from hfrad.precompute import PrecomputeOptions, plan_precompute
    from hfrad.precompute.options import near_entries
    from hfrad.scene.load import load_scene

    client = cluster.client
    t = time.perf_counter()
    scene = load_scene("cornell", patches=patches)
    time_load = time.perf_counter() - t
    options = plan_precompute(scene, EPS, near_field=near_entries("auto", scene.n_patches),
                              options=PrecomputeOptions(block_size=BLOCK), reciprocity=False)
    token = uuid.uuid4().hex[:12]
    job = run.make_job(scene, options, 1, token)
    task_records: list = []
    _collect(client, job.topic, task_records)
    load0 = os.getloadavg()[0]
    t = time.perf_counter()
    [job_f] = client.scatter([job], broadcast=True, hash=False)
    time_scatter = time.perf_counter() - t
    m = options.n_blocks
    blocks = sorted({int(round(x)) for x in np.linspace(1, m - 2, leaves)})
    # a warm-up leaf per worker first: the engine (and Embree scene) is built once per worker and run
    warm = [client.submit(leaf_task, job_f, 0, key=f"warm-{w}-{token}", workers=[w], pure=False)
            for w in sorted(client.scheduler_info()["workers"])]
    warm_records = [f.result().records[0] for f in warm]
    del warm
    parts = [client.submit(leaf_task, job_f, j, key=f"leaf-{j}-{token}", pure=False) for j in blocks]
    pairs = [client.submit(merge_task, job_f, m + i, parts[2 * i], parts[2 * i + 1],
                           key=f"merge-{i}-{token}", pure=False) for i in range(len(parts) // 2)]
    bounds = panel_bounds(scene.n_patches, panel_count)
    addresses = sorted(client.scheduler_info()["workers"])
    left, right = (run._as_panels(client, job_f, 10**6 + i, pairs[i], bounds, token) for i in range(2))
    top = run._panel_merge(client, job_f, 2 * 10**6, left, right, 4 * BLOCK, bounds, addresses, token)
    done = [f.result() for f in top.U] + [f.result() for f in top.V] + [top.meta.result()]
    tree = [r for p in (f.result() for f in pairs) for r in p.records]
    small = [r for r in top.meta.result()["records"]]
    wall = time.perf_counter() - t
    time.sleep(1.0)   # the last events
    del done, parts, pairs, left, right, top
    client.unsubscribe_topic(job.topic)
    return {"n": scene.n_patches, "time_load_client": time_load, "time_scatter": time_scatter, "wall_s": wall,
            "blocks": blocks, "warmup_records": warm_records, "records": tree + small + task_records,
            "loadavg_before": load0, "loadavg_after": os.getloadavg()[0], "panels": int(panel_count)}


def measure_top_shapes(shapes) -> list[dict]:
    """The merge steps at the shapes of the real top merges (n rows, children of rank k each), in this
    process on one core: whole merge (``merge_nodes``) where it fits, and a panel's Gram, the small step
    and a panel's forming at n / P rows. Random orthonormal children with decaying singular values."""
    import threadpoolctl

    from hfrad.distributed import panels
    from hfrad.distributed.tasks import node_meta
    from hfrad.lowrank.hf import ErrorBudget, _Node, merge_nodes

    out = []
    rng = np.random.default_rng(0)
    with threadpoolctl.threadpool_limits(1, user_api="blas"):
        for n, k, P, whole in shapes:
            rows = n // P if P > 1 else n
            nodes = []
            for _ in range(2):
                U = np.linalg.qr(rng.standard_normal((n if whole else rows, k)).astype(np.float32))[0]
                s = np.geomspace(1.0, 1e-3, k).astype(np.float32)
                nodes.append(_Node(1, U, s, np.eye(k, dtype=np.float32), float(np.sum(s.astype(float) ** 2)), 0.0, 0.0))
            budget = ErrorBudget(EPS, True, 2, 0.5)
            rec = {"n": n, "k": k, "panels": P, "rows": rows}
            if whole:
                c = time.process_time()
                merge_nodes(nodes[0], nodes[1], budget, "top")
                rec["whole_cpu"] = time.process_time() - c
            U1, U2 = nodes[0].U[:rows], nodes[1].U[:rows]
            c = time.process_time()
            G = panels.panel_gram(U1, U2)
            rec["gram_cpu"] = time.process_time() - c
            c = time.process_time()
            res = panels.merge_small(G * P, node_meta(nodes[0]), node_meta(nodes[1]), budget.merge(2.0))
            rec["small_cpu"] = time.process_time() - c
            c = time.process_time()
            panels.panel_form(U1, U2, res["B"], np.float32)
            rec["form_cpu"] = time.process_time() - c
            rec["rank"] = int(res["B"].shape[1])
            out.append(rec)
            print(f"top shape n={n} k={k} P={P}: {rec}", flush=True)
    return out


TOP_SHAPES = [(164988, 224, 8, True), (164988, 224, 64, False), (1_000_000, 265, 64, False),
              (164988, 1000, 8, False)]


# -- fitting -----------------------------------------------------------------------------------------
def fit_power(xs, ys) -> tuple[float, float]:
    """``y = a x^p`` by least squares in logs; (a, p)."""
    lx, ly = np.log(np.asarray(xs, float)), np.log(np.asarray(ys, float))
    if np.ptp(lx) == 0:
        return float(np.exp(np.mean(ly - lx))), 1.0
    p, c = np.polyfit(lx, ly, 1)
    return float(np.exp(c)), float(p)


def fit_rate(units, cpu) -> float:
    """CPU seconds per unit (a line through the origin, least squares)."""
    u, c = np.asarray(units, float), np.asarray(cpu, float)
    return float((u @ c) / (u @ u))


def cost_laws(meas: dict) -> dict:
    leaves, merges, gram, small, form, chunk = [], [], [], [], [], []
    runs = [meas["full"], *meas["samples"]]
    for run_ in runs:
        for r in run_["records"]:
            kind = r["kind"]
            if kind == "leaf":
                leaves.append((run_["n"], r["columns"], r["cpu_formfactors"], r["cpu"] - r["cpu_formfactors"],
                               r["rank"]))
            elif kind == "merge" and "panels" not in r:
                merges.append((run_["n"], sum(r["ranks_in"]), r["cpu"]))
            elif kind == "merge":
                small.append((sum(r["ranks_in"]), r["cpu"]))
            elif kind == "gram":
                gram.append((r["rows"], sum(r["ranks_in"]), r["cpu"]))
            elif kind == "form":
                form.append((r["rows"], sum(r["ranks_in"]), r["rank"], r["cpu"]))
            elif kind == "chunk":
                chunk.append((r["columns"], r["ranks_in"][0], r["rank"], r["cpu"]))
    L = np.array([x for x in leaves if x[1] == BLOCK])
    # form factors of one full block: cpu / (n b) per pair, as a power of n
    ns = sorted(set(L[:, 0]))
    per_pair = [float(np.mean(L[L[:, 0] == n, 2])) / (n * BLOCK) for n in ns]
    # the law through the two largest sizes: small scenes carry fixed per-block costs that do not scale
    a_ff, p_ff = fit_power(ns[-2:], per_pair[-2:])
    other = [float(np.mean(L[L[:, 0] == n, 3])) for n in ns]
    leaf_rate = fit_rate([n * BLOCK * BLOCK for n in ns], other)        # Gram leaf ~ n b^2 (+ split, stats ~ n b)
    leaf_rank = {int(n): float(np.mean(L[L[:, 0] == n, 4])) for n in ns}
    M = np.array(merges)
    merge_rate = fit_rate(M[:, 0] * M[:, 1] ** 2, M[:, 2])               # whole merge ~ n K^2
    laws = {
        "ff_s_per_pair": {"a": a_ff, "p": p_ff, "law": "cpu/(n b) = a n^p",
                          "measured": dict(zip(map(int, ns), per_pair))},
        "leaf_other_s_per_nb2": {"rate": leaf_rate, "law": "cpu = rate n b^2",
                                 "measured": dict(zip(map(int, ns), other))},
        "leaf_rank": leaf_rank,
        "merge_s_per_nK2": {"rate": merge_rate, "law": "cpu = rate n K^2, K = k1 + k2", "points": len(M)},
    }
    for t in meas.get("top_shapes", []):   # the real top merges' shapes, one core (see measure_top_shapes)
        K = 2 * t["k"]
        gram.append((t["rows"], K, t["gram_cpu"]))
        small.append((K, t["small_cpu"]))
        form.append((t["rows"], K, t["rank"], t["form_cpu"]))
        if "whole_cpu" in t:
            merges.append((t["n"], K, t["whole_cpu"]))
    M = np.array(merges)
    laws["merge_s_per_nK2"] = {"rate": fit_rate(M[:, 0] * M[:, 1] ** 2, M[:, 2]),
                               "law": "cpu = rate n K^2, K = k1 + k2", "points": len(M)}
    if gram:
        G = np.array(gram)
        laws["gram_s_per_rowK2"] = {"rate": fit_rate(G[:, 0] * G[:, 1] ** 2, G[:, 2]), "points": len(G)}
        F = np.array(form)
        laws["form_s_per_rowKk"] = {"rate": fit_rate(F[:, 0] * F[:, 1] * F[:, 2], F[:, 3]), "points": len(F)}
        S = np.array(small)
        laws["small_s_per_K3"] = {"rate": fit_rate(S[:, 0] ** 3, S[:, 1]), "points": len(S),
                                  "floor_s": float(S[:, 1].min())}
        C = np.array(chunk)
        laws["chunk_s_per_colKk"] = {"rate": fit_rate(C[:, 0] * C[:, 1] * C[:, 2], C[:, 3]), "points": len(C)}
    return laws


# -- the model -----------------------------------------------------------------------------------------
def _scale_runs() -> list[dict]:
    """The eps-EPS runs of the single-machine scale results, oldest file first (a later file's run
    of the same size wins in the dicts built from them)."""
    out = []
    for path in sorted(RESULTS_DIR.glob("scale-*.json")):
        try:
            runs = json.loads(path.read_text()).get("runs", [])
        except (ValueError, OSError):
            continue
        out += [r for r in runs if r.get("eps") == EPS]
    return out


def rank_law() -> dict:
    """k(n) = a n^p through the measured eps-0.05 near-field ranks of the single-machine scale runs."""
    pts = {int(r["n_patches"]): int(r["rank"]) for r in _scale_runs() if "near_nnz" in r and r.get("rank")}
    a, p = fit_power(list(pts), list(pts.values()))
    return {"a": a, "p": p, "points": pts, "source": "benchmarks/results/scale-*.json (eps 0.05, near field)"}


ASSUMPTIONS = {
    "network_bytes_per_s": 1.25e9,      # 10 Gbit/s Ethernet per worker, full rate
    "latency_s": 1e-3,                  # per transfer or scheduler round trip on the critical path
    "scheduler_s_per_task": 6e-3,       # Dask's cost per task, measured with no-op tasks on this machine (5-6 ms)
    "core_efficiency": 1.0,             # a task on one core of a c-core worker runs as on one core here
    "client_assembly": "the single-machine runs' assembly (time_woodbury = everything after the stream: "
                       "near-field set-up + Woodbury; the near-field set-up is part of it, not added), power law "
                       "through the 39K and 163K measurements, at least linear in n",
    "assembly_on_cluster": "from 3 workers the near-field set-up runs as Dask tasks (one LU per channel, then "
                           "64-column panels): its wall is the client's part plus the critical path (one LU + one "
                           "panel solve + products), a share of the serial assembly measured at 20K on "
                           "LocalCluster(2): (2.67 + 7.22) / 25.3 CPU s (benchmarks/README.md, 'Assembly in pieces')",
    "assembly_spread_share": (2.67 + 7.22) / 25.3,
    "assembly_neumann": "from 3 workers the near-field set-up has no LU (hfrad.distributed.assembly, neumann=True): "
                        "its wall is the client's part (2.67 of the 25.3 serial CPU s at 20K, as measured on "
                        "LocalCluster(2)) plus the critical path: N's spectral bound (one task) and one 16-column "
                        "panel's Neumann sweeps (+ its products), measured at 9,986 patches (nnz(N) 1.03 M, rho "
                        "0.397, 11 sweeps to SETUP_TOL 1e-7: 1.11 s per 64 columns, bound 0.095 s; 2 numba threads "
                        "at load ~3, taken as one core's), linear in n (nnz(N) ~ n, the sweeps independent of n)",
    "assembly_client_share": 2.67 / 25.3,
    "neumann_measured": {"n": 9986, "panel_s_per_column": 1.109 / 64, "bound_s": 0.0947, "columns": 16},
    "tasks": "the Dask tasks the built code submits (hfrad.distributed.run._submit run against a counting client with "
             "the tile plan of the run: fused group tasks, tiles, merges, panelled merges) plus the assembly's "
             "(a spectral bound, and per distinct channel (3) and 16-column panel: near columns, row maxima, "
             "products), each costing the scheduler scheduler_s_per_task, not overlapped with the work",
    "worker_memory_bytes": {"2": 16e9, "32": 64e9},   # per worker, by cores; the tiles get TILE_SHARE of it
    "reciprocity": "Dask's reciprocity copy (hfrad.distributed.tiles): pairs computed from the tile plan the run "
                   "makes (group, band within TILE_SHARE of the worker memory); each pair saved costs a share "
                   "of a computed one, from the measured 4,120-patch ratio: form-factor CPU 0.63 for 0.531 of the "
                   "pairs (1.19x per pair: the engine's per-call cost on 512-column tiles; held at 163K and 1M, "
                   "where tiles are 2,048-4,096 columns); tiles move at the network rate, not overlapped; "
                   "one Dask task per tile, per group leaf and per leaf selection",
    "reciprocity_cost_per_pair": 0.63 / 0.531,
    "tasks_per_worker": "one task per core for 2-core workers; 4 tasks x 8 numba threads for 32-core workers "
                        "(leaf memory), leaf SVD on 1 BLAS thread per task",
    "startup_s": "10 s cluster start + the scene sent from the client to each worker in turn + each "
                 "worker's form-factor engine build (the warm-up leaf's extra CPU at the largest sampled n, "
                 "linear in n, on one core)",
    "overlap": "merges below the row-panelled top run while leaves are computed; the merges on the path "
               "from the last leaf to the root follow them (critical path), each level after the previous",
}


def _client_assembly(n: int) -> tuple[float, dict]:
    """Seconds of the single machine's serial assembly at n: ``time_woodbury`` of the scale runs, which is
    everything after the stream (the near-field set-up included: not added to it again)."""
    pts = {int(r["n_patches"]): float(r["time_woodbury"]) for r in _scale_runs() if r.get("time_woodbury")}
    a, p = fit_power(list(pts), list(pts.values()))
    p_used = max(p, 1.0)    # no sublinear extrapolation: linear in n at least
    n0 = max(pts)
    return pts[n0] * (n / n0) ** p_used, {"points": pts, "fitted_p": p, "used_p": p_used}


def task_count(n: int, workers: int, cores: int, copy: bool = True) -> dict:
    """The Dask tasks of the tree at n on ``workers`` workers as the built code submits them
    (:func:`hfrad.distributed.run._submit` against a client that only counts), by kind."""
    import collections

    from hfrad.distributed import panels, run, tiles

    class _Future:
        def done(self):
            return True

    class _Counter:
        def __init__(self):
            self.kinds = collections.Counter()

        def submit(self, fn, *args, key=None, **kw):
            self.kinds[(key or fn.__name__).split("-")[1]] += 1
            return _Future()

    m = math.ceil(n / BLOCK)
    plan = None
    if copy and workers > 1:
        budget = tiles.TILE_SHARE * ASSUMPTIONS["worker_memory_bytes"][str(cores)]
        plan = tiles.plan(n, BLOCK, 4, workers, budget_bytes=int(budget))
    client = _Counter()
    run._submit(client, _Future(), m, "count", set(), n=n, block_size=BLOCK,
                panel_leaves=run.default_panel_leaves(m, workers), bounds=panels.panel_bounds(n, workers),
                workers=[f"w{i}" for i in range(workers)], plan=plan)
    return {"total": int(sum(client.kinds.values())), "by_kind": dict(client.kinds)}


def reciprocity_terms(n: int, workers: int, cores: int) -> dict:
    """The Dask reciprocity copy's plan at n on ``workers`` workers: share of the pairs computed, tiles
    per worker (bytes), bytes a leaf receives, extra tasks (:mod:`hfrad.distributed.tiles`)."""
    from hfrad.distributed import tiles

    s = 4
    budget = tiles.TILE_SHARE * ASSUMPTIONS["worker_memory_bytes"][str(cores)]
    plan = tiles.plan(n, BLOCK, s, workers, budget_bytes=int(budget))
    m, G, g = plan.blocks, plan.groups, plan.group
    share = plan.pairs_computed() / float(n) ** 2
    rows_in = min(2 * plan.band * g * BLOCK, n - g * BLOCK)       # rows a leaf takes from tiles
    return {"group": g, "groups": G, "band": plan.band, "pairs_share": share,
            "tile_bytes_per_worker": tiles.tile_bytes_per_worker(G, plan.band, g * BLOCK, s, workers),
            "bytes_per_leaf": rows_in * BLOCK * s, "extra_tasks": len(plan.tiles()) + G + m}


def startup_costs(meas: dict) -> dict:
    """Engine build seconds per patch (warm-up leaf minus an ordinary leaf, largest sample) and the
    scene's pickled bytes per patch."""
    import pickle

    from hfrad.scene.load import load_scene

    big = max(meas["samples"], key=lambda s: s["n"])
    warm = float(np.mean([r["cpu"] for r in big["warmup_records"]]))
    plain = float(np.mean([r["cpu"] for r in big["records"] if r["kind"] == "leaf"]))
    if "scene_bytes_per_patch" not in meas:
        scene = load_scene("cornell", patches=20000)
        meas["scene_bytes_per_patch"] = len(pickle.dumps(scene, protocol=5)) / scene.n_patches
    return {"engine_s_per_patch": max(warm - plain, 0.0) / big["n"], "from_n": big["n"],
            "scene_bytes_per_patch": meas["scene_bytes_per_patch"]}


def predict(n: int, workers: int, cores: int, laws: dict, ranks: dict, name: str, start: dict,
            copy: bool = True, assembly_on_cluster: bool = True, neumann: bool = True) -> dict:
    """Wall time and the busiest worker's memory of one configuration.

    ``copy``: Dask's reciprocity copy (on by default in the runs); ``assembly_on_cluster``: the
    near-field set-up as Dask tasks (what runs do from 3 workers on); ``neumann``: those tasks
    without LUs (what runs do; False: one LU per channel on the critical path, as measured). Both False: the model of the
    last stop (every pair computed, the assembly serial on the client).
    """
    A = ASSUMPTIONS
    bw, lat = A["network_bytes_per_s"], A["latency_s"]
    b = BLOCK
    m = math.ceil(n / b)
    k = ranks["a"] * n ** ranks["p"]
    # leaf ranks: measured mean at the largest sampled n, grown with n like k
    n_l, k_l = max(laws["leaf_rank"].items())
    k_leaf = k_l * (n / n_l) ** ranks["p"]
    ff = laws["ff_s_per_pair"]
    # CPU s per leaf, form factors: the per-pair cost of the largest sample, times (n / n_s)^p only where
    # p > 0 (the fitted p < 0 would make pairs cheaper at 1M than measured: not assumed)
    n_s = max(int(x) for x in ff["measured"])
    per_pair = {int(x): v for x, v in ff["measured"].items()}[n_s]
    rec = reciprocity_terms(n, workers, cores) if copy and workers > 1 else None
    pairs = 1.0 if rec is None else min(1.0, rec["pairs_share"] * A["reciprocity_cost_per_pair"])
    leaf_ff = pairs * per_pair * max(n / n_s, 1.0) ** max(ff["p"], 0.0) * n * b
    leaf_svd = laws["leaf_other_s_per_nb2"]["rate"] * n * b * b
    slots = workers * cores                                   # cores doing leaves at once
    tasks_per_worker = cores if cores <= 2 else 4
    leaves_cpu = m * (leaf_ff + leaf_svd)
    # leaves: form factors use every core (numba threads), the SVD part one core per task
    leaves_wall = m * leaf_ff / slots + m * leaf_svd / (workers * tasks_per_worker)
    if rec is not None:     # the tiles a worker's leaves receive, not overlapped with their work
        leaves_wall += m / workers * rec["bytes_per_leaf"] / bw
    # merges: level l has m / 2^l merges of K = 2 k_l, k_l from k_leaf up to k (geometric in the levels)
    levels = max(1, math.ceil(math.log2(m)))
    rate = laws["merge_s_per_nK2"]["rate"]
    merge_cpu, critical, transfer_crit = 0.0, 0.0, 0.0
    from hfrad.distributed.run import default_panel_leaves

    panel_leaves = default_panel_leaves(m, workers)
    for lvl in range(1, levels + 1):
        kl = k_leaf * (k / k_leaf) ** ((lvl - 1) / max(levels - 1, 1))
        count = max(1, m // 2 ** lvl)
        K = 2 * kl
        child_bytes = n * kl * 4
        if 2 ** lvl <= panel_leaves:
            t_merge = rate * n * K * K
            merge_cpu += count * t_merge
            crit = t_merge + child_bytes / bw + lat
        else:   # by row panels over all workers: Gram, reduction of K x K float64, small step, forming
            P = workers
            t_gram = laws["gram_s_per_rowK2"]["rate"] * (n / P) * K * K
            t_form = laws["form_s_per_rowKk"]["rate"] * (n / P) * K * kl
            t_small = max(laws["small_s_per_K3"]["rate"] * K ** 3, laws["small_s_per_K3"]["floor_s"])
            red = math.ceil(math.log2(P)) * (K * K * 8 / bw + lat) + (K * kl * 8 / bw + lat)
            crit = t_gram + red + t_small + t_form + (child_bytes / P) / bw
            merge_cpu += P * (t_gram + t_form) + t_small
        critical += crit
        transfer_crit += child_bytes / bw
    # the tree after the last leaf: its merges up to the root are the critical path (overlap: all merges
    # but those on the path run while leaves are computed)
    compute_wall = max(leaves_wall + critical, (leaves_cpu + merge_cpu) / slots + critical)
    tasks = task_count(n, workers, cores, copy=copy)
    spread = assembly_on_cluster and workers >= 3          # run.ASSEMBLY_MIN_WORKERS
    nm = A["neumann_measured"]
    assembly_tasks = 1 + 3 * 3 * math.ceil(k / nm["columns"]) if spread else 0
    scheduler = A["scheduler_s_per_task"] * (tasks["total"] + assembly_tasks)
    near_bytes = 24 * 120 * n
    gather = (2 * n * k * 4 + near_bytes + 3 * 176 * n) / bw
    serial_assembly = _client_assembly(n)[0]
    if spread and neumann:      # no LU: the client's part, N's bound, one panel's sweeps (linear in n)
        grow = n / nm["n"]
        assembly_critical = (nm["bound_s"] + nm["panel_s_per_column"] * nm["columns"]) * grow + 3 * lat
        assembly = serial_assembly * A["assembly_client_share"] + assembly_critical
    elif spread:
        assembly_critical = serial_assembly * (A["assembly_spread_share"] - A["assembly_client_share"])
        assembly = serial_assembly * A["assembly_spread_share"]
    else:
        assembly_critical, assembly = 0.0, serial_assembly
    startup = 10.0 + start["scene_bytes_per_patch"] * n * workers / bw + start["engine_s_per_patch"] * n
    wall = startup + compute_wall + scheduler + gather + assembly
    # memory of the busiest worker (bytes)
    from hfrad.distributed import sizing
    lt = min(levels, max(1, math.floor(math.log2(panel_leaves))))   # the last level merged whole
    k_t = k_leaf * (k / k_leaf) ** ((lt - 1) / max(levels - 1, 1))
    mem = sizing.worker_bytes(n, b, int(k), near_entries=120, workers=workers, tasks=tasks_per_worker,
                              transition_rank=int(k_t))
    mem += rec["tile_bytes_per_worker"] if rec else 0
    return {"case": name, "n": n, "workers": workers, "cores_per_worker": cores, "blocks": m, "rank": round(k),
            "leaf_rank": round(k_leaf), "leaf_ff_cpu_s": leaf_ff, "leaf_svd_cpu_s": leaf_svd,
            "leaves_cpu_s": leaves_cpu, "merges_cpu_s": merge_cpu, "leaves_wall_s": leaves_wall,
            "critical_merges_s": critical, "scheduler_s": scheduler, "gather_s": gather,
            "client_assembly_s": assembly, "assembly_critical_s": assembly_critical, "tasks": tasks["total"],
            "tasks_by_kind": tasks["by_kind"], "assembly_tasks": assembly_tasks, "startup_s": startup, "wall_s": wall,
            "worker_memory_gb": mem / 1e9, "panel_leaves": panel_leaves, "pairs_computed": pairs,
            "reciprocity": rec, "assembly_on_cluster": bool(spread)}


def model(meas: dict) -> dict:
    laws = cost_laws(meas)
    ranks = rank_law()
    start = startup_costs(meas)
    cases = [predict(164988, 8, 2, laws, ranks, "163K, 8 x 2 cores", start),
             predict(164988, 64, 2, laws, ranks, "163K, 64 x 2 cores", start),
             predict(1_000_000, 64, 32, laws, ranks, "1M, 64 x 32 cores", start)]
    # check against this machine: the model's own 163K on 1 worker of 2 cores
    here = predict(164988, 1, 2, laws, ranks, "163K, 1 x 2 cores (this machine)", start)
    # the last stop's model (no copy, serial assembly), for comparison
    whatif = [predict(164988, 8, 2, laws, ranks, "before: 163K, 8 x 2, no copy, serial assembly", start,
                      copy=False, assembly_on_cluster=False),
              predict(164988, 64, 2, laws, ranks, "before: 163K, 64 x 2, no copy, serial assembly", start,
                      copy=False, assembly_on_cluster=False)]
    reference = json.loads((RESULTS_DIR / "scale-163k-v11.json").read_text())["runs"][0]
    t_ref = float(reference["time_precompute"])
    for c in cases + whatif + [here]:
        c["speedup_vs_measured_163k"] = t_ref / c["wall_s"] if c["n"] == 164988 else None
    goals = {"163K 8 workers >= 4x": bool(cases[0]["speedup_vs_measured_163k"] >= 4),
             "163K 64 workers >= 16x": bool(cases[1]["speedup_vs_measured_163k"] >= 16),
             "1M <= 2 h": bool(cases[2]["wall_s"] <= 7200),
             "no worker > 64 GB": bool(all(c["worker_memory_gb"] <= 64 for c in cases))}
    return {"laws": laws, "rank_law": ranks, "startup": start, "client_assembly": _client_assembly(164988)[1],
            "assumptions": ASSUMPTIONS, "cases": cases, "this_machine_model": here, "what_if": whatif,
            "measured_163k_single_machine_s": t_ref, "goals_met": goals}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--patches", type=int, default=5000, help="the whole Dask run's size")
    ap.add_argument("--sizes", default="40000,163000", help="sizes of the sampled leaves and merges")
    ap.add_argument("--leaves", type=int, default=4, help="sampled leaves per size (even)")
    ap.add_argument("--panels", type=int, default=8, help="row panels of the sampled panelled merge")
    ap.add_argument("--from", dest="source", help="a JSON of an earlier run: rebuild the model only")
    ap.add_argument("--name", default="cluster-model")
    args = ap.parse_args(argv)
    mach = header("Dask per-task costs and the cluster model")
    if args.source:
        out = json.loads(Path(args.source).read_text())
        meas = out["measured"]
        if "top_shapes" not in meas:
            meas["top_shapes"] = measure_top_shapes(TOP_SHAPES)
            meas["top_shapes_load"] = os.getloadavg()[0]
    else:
        from hfrad.distributed import connect

        meas = {"machine": mach, "numba_threads": os.environ.get("NUMBA_NUM_THREADS"), "samples": []}
        with connect(workers=2) as cluster:
            meas["full"] = measure_full(cluster, args.patches)
            print(f"whole run: {meas['full']['n']} patches, {meas['full']['wall_s']:.1f} s, rank "
                  f"{meas['full']['rank']}, load {meas['full']['loadavg_before']:.1f}-"
                  f"{meas['full']['loadavg_after']:.1f}", flush=True)
            for size in (int(x) for x in args.sizes.split(",") if x):
                s = measure_sample(cluster, size, args.leaves, args.panels)
                meas["samples"].append(s)
                print(f"sample: {s['n']} patches, {len(s['blocks'])} leaves + merges, {s['wall_s']:.1f} s, load "
                      f"{s['loadavg_before']:.1f}-{s['loadavg_after']:.1f}", flush=True)
        meas["top_shapes"] = measure_top_shapes(TOP_SHAPES)
        meas["top_shapes_load"] = os.getloadavg()[0]
        out = {"measured": meas}
        write_json(args.name, out)   # the measurements, whatever the model makes of them
    out["model"] = model(meas)
    out["machine"] = out.get("machine", mach)
    mo = out["model"]
    print_table("Per-task cost laws (CPU seconds on one core of this machine)",
                [{"law": k, "value": json.dumps(v)[:110]} for k, v in mo["laws"].items()], ["law", "value"])
    cols = ["case", "rank", "leaves_wall_s", "critical_merges_s", "tasks", "scheduler_s", "gather_s",
            "client_assembly_s", "assembly_critical_s", "startup_s",
            "wall_s", "speedup_vs_measured_163k", "worker_memory_gb"]
    print_table("Model", mo["cases"] + [mo["this_machine_model"]] + mo.get("what_if", []), cols)
    print(f"\nmeasured 163K on this machine: {mo['measured_163k_single_machine_s']:.0f} s; goals: {mo['goals_met']}")
    print(f"rank law: k = {mo['rank_law']['a']:.3g} n^{mo['rank_law']['p']:.3f} from {mo['rank_law']['points']}")
    print("assumptions:", json.dumps(mo["assumptions"], indent=1))
    write_json(args.name, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
