"""Shared helpers of the benchmarks: machine description, timing, JSON, tables, cached matrices.

Not part of the installed package and not collected by pytest. Every benchmark
script imports this module from its own folder (``python benchmarks/X.py``).

Cached matrices
---------------
Form factors are the expensive part of a run and do not change between
factorization benchmarks, so ``load_case(scene, patches)`` builds F once per
(scene, patch count, kernel version, visibility samples) and keeps it as
float32 ``.npy`` (plus a small ``.npz`` of per-patch data) under
``benchmarks/.cache/`` (gitignored). Delete the folder to force a rebuild.
"""

from __future__ import annotations

import json
import os
import platform
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

BENCH_DIR = Path(__file__).resolve().parent
RESULTS_DIR = BENCH_DIR / "results"
CACHE_DIR = BENCH_DIR / ".cache"
SHARED_SCENES = Path(os.environ.get("HFRAD_SHARED_SCENES", "/work/shared/scenes"))

# name -> (load_scene source, load_scene keyword arguments). Patch counts are targets:
# subdivision gives n within a few percent of them.
SCENES: dict[str, tuple[str, dict]] = {
    "cornell": ("cornell", {}),
    # the two Cornell boxes of the McGuire archive (shared/scenes/cornell-box): the original
    # with two boxes (occlusion), and the empty one with a 0.95-reflectance wall (sigma_max near 1)
    "cbox-original": (str(SHARED_SCENES / "cornell-box" / "CornellBox-Original.obj"), {}),
    "cbox-empty": (str(SHARED_SCENES / "cornell-box" / "CornellBox-Empty-CO.obj"), {}),
    # the Šibenik cathedral (shared/scenes/sibenik), cleaned and clustered: many occluders (columns,
    # pews, galleries); it has no emitter of its own: a downward area light of 50 W/m^2 under its top
    "sibenik": (str(SHARED_SCENES / "sibenik" / "sibenik.obj"), {"area_light": (50, 50, 50)}),
}


# -- the machine --------------------------------------------------------------------------------
def _meminfo(key: str) -> int:
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith(key + ":"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _cpu_flags() -> list[str]:
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("flags"):
                    flags = set(line.split(":", 1)[1].split())
                    return sorted(f for f in flags if f in {"avx", "avx2", "fma", "avx512f", "avx512_bf16"})
    except OSError:
        pass
    return []


def blas_info() -> list[dict]:
    """BLAS/LAPACK libraries loaded by numpy and scipy, with their thread counts."""
    import scipy.linalg  # noqa: F401  (loads scipy's BLAS so threadpoolctl sees it)
    try:
        from threadpoolctl import threadpool_info
        return [{k: d.get(k) for k in ("internal_api", "version", "num_threads", "architecture",
                                       "threading_layer", "prefix")} for d in threadpool_info()]
    except Exception:  # threadpoolctl missing: fall back to numpy's build config
        try:
            cfg = np.show_config(mode="dicts")
            return [{"numpy_build": cfg.get("Build Dependencies", {}).get("blas", {})}]
        except Exception:
            return []


def machine() -> dict:
    """Cores (affinity), memory, CPU model, BLAS, library versions and the current load."""
    import numba
    import scipy
    return {
        "cores": len(os.sched_getaffinity(0)),
        "memory_gib": round(_meminfo("MemTotal") / 2**30, 1),
        "memory_available_gib": round(_meminfo("MemAvailable") / 2**30, 1),
        "cpu": _cpu_model(),
        "cpu_flags": _cpu_flags(),
        "blas": blas_info(),
        "numba_threads": numba.get_num_threads(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "loadavg": list(os.getloadavg()),
    }


def machine_line(m: dict | None = None) -> str:
    m = m or machine()
    blas = ", ".join(f"{b.get('internal_api')} {b.get('version')} x{b.get('num_threads')} ({b.get('architecture')})"
                     for b in m["blas"] if b.get("internal_api"))
    return (f"{m['cpu']}, {m['cores']} cores, {m['memory_gib']} GiB, BLAS: {blas or '?'}; "
            f"load {m['loadavg'][0]:.2f}")


def check_load(limit: float = 1.5) -> float:
    """The 1-minute load average, with a warning on stderr when it exceeds ``limit``."""
    load = os.getloadavg()[0]
    if load > limit:
        print(f"WARNING: load average {load:.2f} > {limit}: timings may be inflated by other processes",
              file=sys.stderr)
    return load


# -- memory of a process tree ------------------------------------------------------------------
def _children(pid: int) -> list[int]:
    """Direct children of ``pid`` (Linux: /proc/PID/task/*/children)."""
    out = []
    try:
        for task in os.listdir(f"/proc/{pid}/task"):
            with open(f"/proc/{pid}/task/{task}/children") as fh:
                out += [int(x) for x in fh.read().split()]
    except OSError:
        pass
    return out


def _pss_bytes(pid: int) -> int:
    """Proportional set size of ``pid`` (shared pages split between their users), 0 if gone."""
    try:
        with open(f"/proc/{pid}/smaps_rollup") as fh:
            for line in fh:
                if line.startswith("Pss:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


def tree_pss_bytes(root: int | None = None) -> int:
    """PSS summed over ``root`` (default: this process) and all its descendants: the memory the
    whole run holds, shared memory (the workers' block slots) counted once."""
    todo, total = [root or os.getpid()], 0
    while todo:
        pid = todo.pop()
        total += _pss_bytes(pid)
        todo += _children(pid)
    return total


class TreeMemorySampler:
    """Peaks of a run's memory, sampled every ``every`` seconds in a background thread.

    ``peak_tree_pss`` is the largest PSS of this process and its descendants summed at one
    instant (what ``ru_maxrss`` of the parent and of the largest child cannot say: their peaks
    need not coincide, and both count shared pages); ``peak_system_used`` the largest rise of
    ``MemTotal - MemAvailable`` over its value at the start (everything the run made the machine
    hold, page cache it could not drop included). Use as a context manager.
    """

    def __init__(self, every: float = 1.0) -> None:
        self.every = float(every)
        self.peak_tree_pss = 0
        self.peak_system_used = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._base = 0

    def _used(self) -> int:
        return _meminfo("MemTotal") - _meminfo("MemAvailable")

    def _sample(self) -> None:
        self.peak_tree_pss = max(self.peak_tree_pss, tree_pss_bytes())
        self.peak_system_used = max(self.peak_system_used, self._used() - self._base)

    def _run(self) -> None:
        while not self._stop.wait(self.every):
            self._sample()

    def __enter__(self) -> "TreeMemorySampler":
        self._base = self._used()
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()
        self._sample()


# -- timing -------------------------------------------------------------------------------------
@dataclass
class Timing:
    best: float
    times: list[float]
    result: object


def best_of(fn: Callable[[], object], k: int = 3, *, max_seconds: float = 30.0) -> Timing:
    """Run ``fn`` up to ``k`` times (stop early once ``max_seconds`` are spent); best wall time.

    Wall time by ``time.perf_counter``. Returns the result of the last run.
    """
    times: list[float] = []
    result = None
    spent = 0.0
    for _ in range(max(k, 1)):
        t0 = time.perf_counter()
        result = fn()
        dt = time.perf_counter() - t0
        times.append(dt)
        spent += dt
        if spent >= max_seconds:
            break
    return Timing(min(times), times, result)


# -- output -------------------------------------------------------------------------------------
def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, float) and not np.isfinite(x):
        return None
    return x


def write_json(name: str, data: dict, results_dir: Path | None = None) -> Path:
    """Write ``results/NAME.json`` atomically (temporary file, then rename)."""
    out_dir = Path(results_dir) if results_dir else RESULTS_DIR
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / f"{name}.json"
    tmp = path.with_suffix(".json.tmp")
    with open(tmp, "w") as fh:
        json.dump(_jsonable(data), fh, indent=1)
        fh.write("\n")
    os.replace(tmp, path)
    return path


def fmt(v, spec: str | None = None) -> str:
    if v is None:
        return "-"
    if isinstance(v, str):
        return v
    if spec:
        return format(v, spec)
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, float):
        if v != v:
            return "nan"
        a = abs(v)
        if a == 0:
            return "0"
        if a >= 100:
            return f"{v:.0f}"
        if a >= 1:
            return f"{v:.2f}"
        if a >= 1e-3:
            return f"{v:.4f}"
        return f"{v:.2e}"
    return str(v)


def table(rows: Sequence[dict], columns: Sequence[str | tuple[str, str]], *, markdown: bool = False) -> str:
    """Format rows as an aligned text (or Markdown) table. ``columns``: keys or (key, header)."""
    cols = [(c, c) if isinstance(c, str) else c for c in columns]
    cells = [[h for _, h in cols]] + [[fmt(r.get(k)) for k, _ in cols] for r in rows]
    widths = [max(len(row[i]) for row in cells) for i in range(len(cols))]
    if markdown:
        lines = ["| " + " | ".join(c.ljust(w) for c, w in zip(cells[0], widths)) + " |",
                 "|" + "|".join("-" * (w + 2) for w in widths) + "|"]
        lines += ["| " + " | ".join(c.rjust(w) for c, w in zip(r, widths)) + " |" for r in cells[1:]]
    else:
        lines = ["  ".join(c.rjust(w) for c, w in zip(cells[0], widths)),
                 "  ".join("-" * w for w in widths)]
        lines += ["  ".join(c.rjust(w) for c, w in zip(r, widths)) for r in cells[1:]]
    return "\n".join(lines)


def print_table(title: str, rows, columns) -> None:
    print(f"\n## {title}")
    print(table(rows, columns))
    sys.stdout.flush()


# -- scenes and cached matrices ------------------------------------------------------------------
def load_bench_scene(scene: str, patches: int):
    """The Scene of a benchmark case (see ``SCENES``)."""
    from hfrad.scene.load import load_scene
    if scene not in SCENES:
        raise ValueError(f"unknown benchmark scene {scene!r}; known: {', '.join(SCENES)}")
    source, kw = SCENES[scene]
    if source != "cornell" and not Path(source).exists():
        raise FileNotFoundError(f"{source} not found (set HFRAD_SHARED_SCENES to the shared scenes folder)")
    return load_scene(source, patches=patches, **kw)


@dataclass
class Case:
    """One benchmark matrix: F in the user's order plus the per-patch data the solvers need."""

    name: str
    scene: str
    n: int
    F: np.ndarray             # (n, n) float32, user order (memory-mapped from the cache)
    reflectance: np.ndarray   # (n, 3)
    emission: np.ndarray      # (n, 3) W/m^2
    centroids: np.ndarray     # (n, 3)
    areas: np.ndarray         # (n,)
    ff_seconds: float         # time to generate F (all column blocks, block 256), when built
    ff_block_size: int
    samples: int

    @property
    def rho_max(self) -> np.ndarray:
        return self.reflectance.max(axis=1)

    def perm(self, order: str = "zorder", rng=0) -> np.ndarray:
        from hfrad.scene.zorder import patch_order
        return patch_order(self.centroids, order, rng=rng)

    def G(self, perm: np.ndarray | None = None, dtype=np.float32, fortran: bool = True) -> np.ndarray:
        """``G = diag(rho_max) F`` in internal order ``perm`` (rows and columns), in ``dtype``.

        Fortran order by default, so column blocks ``G[:, a:b]`` are contiguous (as the
        freshly generated blocks of the streaming pipeline are).
        """
        perm = np.arange(self.n) if perm is None else perm
        G = np.empty((self.n, self.n), dtype=dtype, order="F" if fortran else "C")
        rho = self.rho_max[perm].astype(dtype)[:, None]
        step = 1024
        for a in range(0, self.n, step):   # chunked: never a second full-size temporary
            cols = perm[a:a + step]
            G[:, a:a + cols.size] = rho * self.F[np.ix_(perm, cols)].astype(dtype, copy=False)
        return G


def _cache_paths(scene: str, patches: int, samples: int):
    from hfrad.formfactors.kernel import KERNEL_VERSION
    stem = f"{scene}-p{patches}-s{samples}-k{KERNEL_VERSION}"
    return CACHE_DIR / f"{stem}.F32.npy", CACHE_DIR / f"{stem}.meta.npz"


def load_case(scene: str, patches: int, *, samples: int | None = None, block_size: int = 256,
              verbose: bool = True, mmap: bool = True) -> Case:
    """F (float32) of ``scene`` cut into ~``patches`` patches, from the cache or built and cached.

    The build streams column blocks (``iter_column_blocks``) into a float32 matrix, so
    peak memory is the float32 matrix plus one block; its time is recorded as
    ``ff_seconds`` (the cost of one pass over F generated out of core).
    """
    from hfrad.formfactors.blocks import iter_column_blocks
    from hfrad.formfactors.visibility import DEFAULT_SAMPLES
    samples = DEFAULT_SAMPLES if samples is None else int(samples)
    f_path, m_path = _cache_paths(scene, patches, samples)
    if f_path.exists() and m_path.exists():
        meta = np.load(m_path)
        F = np.load(f_path, mmap_mode="r" if mmap else None)
        return Case(f"{scene}-{F.shape[0]}", scene, F.shape[0], F, meta["reflectance"], meta["emission"],
                    meta["centroids"], meta["areas"], float(meta["ff_seconds"]), int(meta["ff_block_size"]),
                    samples)
    CACHE_DIR.mkdir(parents=True, exist_ok=True)
    sc = load_bench_scene(scene, patches)
    n = sc.n_patches
    if verbose:
        print(f"[cache] building F for {scene} with {n} patches ({n * n * 4 / 2**30:.2f} GiB float32) ...",
              file=sys.stderr, flush=True)
    tmp = f_path.with_suffix(".tmp.npy")
    F = np.lib.format.open_memmap(tmp, mode="w+", dtype=np.float32, shape=(n, n))
    t0 = time.perf_counter()
    for a, b, block in iter_column_blocks(sc, block_size, samples=samples, dtype=np.float64):
        F[:, a:b] = block
    ff_seconds = time.perf_counter() - t0
    F.flush()
    del F
    os.replace(tmp, f_path)
    np.savez(m_path, reflectance=sc.reflectance, emission=sc.emission, centroids=sc.centroids,
             areas=sc.areas, ff_seconds=ff_seconds, ff_block_size=block_size)
    if verbose:
        print(f"[cache] {f_path.name}: {ff_seconds:.1f} s", file=sys.stderr, flush=True)
    return load_case(scene, patches, samples=samples, block_size=block_size, verbose=verbose, mmap=mmap)


def parse_sizes(text: str) -> list[int]:
    """'2500,10k,20K' -> [2500, 10000, 20000]."""
    out = []
    for part in text.split(","):
        part = part.strip().lower()
        if not part:
            continue
        mult = 1000 if part.endswith("k") else 1
        out.append(int(float(part.rstrip("k")) * mult))
    return out


def parse_list(text: str, cast=str) -> list:
    return [cast(p.strip()) for p in text.split(",") if p.strip()]


_BLAS_LIMIT = None


def set_blas_threads(threads: int | None):
    """Limit the BLAS/LAPACK thread pools (numpy's and scipy's OpenBLAS) for the whole run.

    On the 2-core benchmark VM, 1 thread was measured 2-9x *faster* than the default 2
    (gesdd of a 5K matrix 28.5 s vs 55.6 s, HF at 2.5K 0.9 s vs 2.0 s, rSVD 3.1 s vs 7-29 s):
    numpy and scipy each load their own OpenBLAS, whose spinning worker threads fight over
    the two cores. Numba (form factors) is not affected. ``None`` keeps the library default.
    """
    global _BLAS_LIMIT
    if threads is None or threads <= 0:
        return None
    import scipy.linalg  # noqa: F401  (load scipy's BLAS before limiting it)
    from threadpoolctl import threadpool_limits
    _BLAS_LIMIT = threadpool_limits(limits=int(threads), user_api="blas")
    return _BLAS_LIMIT


def add_blas_arg(p) -> None:
    p.add_argument("--blas-threads", type=int, default=1,
                   help="BLAS threads for every method (default 1: fastest on the 2-core VM; 0 = library default)")


def header(title: str, blas_threads: int | None = None) -> dict:
    """Print the benchmark title and the machine; return the machine dict for the JSON."""
    set_blas_threads(blas_threads)
    m = machine()
    m["blas_threads_requested"] = blas_threads
    print(f"# {title}")
    print(f"machine: {machine_line(m)}")
    check_load()
    return m
