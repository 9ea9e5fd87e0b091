"""Machine resources: how many cores, how many BLAS threads, how busy the machine is.

One base module for the machine policy that every layer asks: the form-factor
engine and its worker processes (how many cores), the precompute (BLAS threads
while the engine runs, every thread for a large merge), HF's merges and the
near-field set-up (fewer BLAS threads where other processes keep cores busy,
measured from ``/proc``), the Dask cluster and the CLI (limits on worker counts).
The maths modules only ask; none of them counts cores or reads ``/proc`` itself.
"""

from __future__ import annotations

import contextlib
import math
import os
import time

__all__ = ["cores", "blas_threads", "blas_threads_now", "other_processes_cores", "spare_blas_threads",
           "spare_threads", "spare_cores_now", "solve_threads", "numba_loops_at_once", "numba_threads"]


def cores() -> int:
    """CPU cores this process may use (its affinity mask where the system has one), at least 1."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return max(1, os.cpu_count() or 1)    # pragma: no cover - non-Linux


@contextlib.contextmanager
def blas_threads(count: int | None):
    """Limit BLAS/LAPACK to ``count`` threads inside (None: leave them as they are).

    While the form-factor engine keeps the cores busy (numba kernel + Embree),
    multi-threaded OpenBLAS competing with it spin-waits and slows the small SVDs
    by an order of magnitude; a cluster's in-process workers share this process's pool.
    """
    if count is None:
        yield
        return
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=count, user_api="blas"):
        yield


def blas_threads_now() -> int:
    """BLAS threads of this process now (the largest pool's), at least 1."""
    from threadpoolctl import threadpool_info

    return max((lib.get("num_threads") or 1 for lib in threadpool_info() if lib.get("user_api") == "blas"),
               default=1)


# -- how busy the machine is (the load probe) ----------------------------------------------------
#: Seconds over which the other processes' CPU use is measured before a merge ...
_BUSY_WINDOW = 0.1
#: ... and for how long that measure is reused: at most ~0.3% of the time spent measuring where every
#: push measures (a caller without a thread limit; the pipeline's pushes run at one thread and skip it).
_BUSY_REUSE = 30.0
_busy_cache: list = [float("-inf"), 0.0]    # [when measured, other processes' cores]


def _own_pids() -> set[int]:
    """This process and its descendants (the form-factor workers), from /proc."""
    parent: dict[int, int] = {}
    for entry in os.scandir("/proc"):
        if entry.name.isdigit():
            try:
                with open(f"/proc/{entry.name}/stat", "rb") as fh:
                    rest = fh.read().rsplit(b")", 1)[1].split()
                parent[int(entry.name)] = int(rest[1])
            except (OSError, IndexError, ValueError):
                continue
    own, grew = {os.getpid()}, True
    while grew:
        more = {pid for pid, pp in parent.items() if pp in own} - own
        own |= more
        grew = bool(more)
    return own


def _jiffies(pids) -> int:
    """User + system clock ticks of ``pids`` (those still alive)."""
    total = 0
    for pid in pids:
        try:
            with open(f"/proc/{pid}/stat", "rb") as fh:
                rest = fh.read().rsplit(b")", 1)[1].split()
            total += int(rest[11]) + int(rest[12])
        except (OSError, IndexError, ValueError):
            continue
    return total


def _machine_jiffies() -> tuple[int, int]:
    """(busy, total) clock ticks of all CPUs from /proc/stat; steal counts as busy (not ours to use)."""
    with open("/proc/stat") as fh:
        values = [int(x) for x in fh.readline().split()[1:9]]
    idle = values[3] + values[4]                 # idle + iowait
    return sum(values) - idle, sum(values)


def other_processes_cores(window: float = _BUSY_WINDOW) -> float | None:
    """Cores' worth of CPU that processes other than this one and its children used over ``window`` s.

    None where /proc cannot be read (not Linux).
    """
    try:
        tick = os.sysconf("SC_CLK_TCK")
        own = _own_pids()
        busy0, _ = _machine_jiffies()
        mine0 = _jiffies(own)
        t0 = time.perf_counter()
        time.sleep(window)
        busy1, _ = _machine_jiffies()
        mine1 = _jiffies(own)
        seconds = time.perf_counter() - t0
    except (OSError, ValueError):
        return None
    return max(busy1 - busy0 - (mine1 - mine0), 0) / tick / seconds


def spare_blas_threads(limit: int) -> int:
    """At most ``limit`` BLAS threads, one fewer per core the machine's other processes keep busy.

    Multi-threaded OpenBLAS on cores that other processes also want spin-waits at every
    synchronisation, so a BLAS call on a loaded machine can take several times longer with
    two threads than with one (benchmarks/regression.md).
    This process's own children (the form-factor workers, which stop within a few blocks)
    are not counted. The measure is reused for ``_BUSY_REUSE`` seconds.
    """
    now = time.perf_counter()
    if now - _busy_cache[0] > _BUSY_REUSE:
        others = other_processes_cores()
        _busy_cache[:] = [now, 0.0 if others is None else others]
    return max(1, min(int(limit), cores() - math.ceil(_busy_cache[1] - 0.5)))


@contextlib.contextmanager
def spare_threads():
    """Lower the BLAS threads inside to :func:`spare_blas_threads` (never raise them; nothing to do at one)."""
    current = blas_threads_now()
    spare = spare_blas_threads(current) if current > 1 else current
    if spare >= current:
        yield
        return
    with blas_threads(spare):
        yield


# -- a solve's threads ------------------------------------------------------------------------------
#: A solve takes the machine's load from the time since the previous reading (no sleep: a relighting
#: may take milliseconds), re-read at most this often (seconds) ...
_QUICK_EVERY = 1.0
#: ... and a reading older than this says nothing of now (the next solve measures again, over this window).
_QUICK_STALE = 30.0
_QUICK_FIRST_WINDOW = 0.05
_quick: dict = {"t": None, "busy": 0, "mine": 0, "spare": None}


def spare_cores_now() -> int:
    """Cores a solve may use: :func:`cores` less the cores other processes kept busy since the last
    reading (read from /proc without waiting). On the first call, or after a stale reading, they
    are measured over ``_QUICK_FIRST_WINDOW`` seconds (once: a command's one solve is limited too;
    not the load average, which would count this process's own precompute of the last minute);
    every core where /proc cannot be read.

    A parallel numba loop or BLAS call whose threads compete with other processes for the cores
    spin-waits at every synchronisation: on the 2-core VM at load 9 a 3,000-patch near-field solve
    took 336 ms with two threads and 20 ms with one.
    """
    now = time.perf_counter()
    last = _quick["t"]
    if last is not None and now - last < _QUICK_EVERY and _quick["spare"] is not None:
        return _quick["spare"]
    try:
        tick = os.sysconf("SC_CLK_TCK")
        busy, _ = _machine_jiffies()
        mine = _jiffies({os.getpid()})
    except (OSError, ValueError):
        return cores()
    if last is not None and now - last < _QUICK_STALE:
        others = max(busy - _quick["busy"] - (mine - _quick["mine"]), 0) / tick / (now - last)
    else:
        others = other_processes_cores(_QUICK_FIRST_WINDOW) or 0.0
    spare = max(1, cores() - math.ceil(others - 0.5))
    _quick.update(t=now, busy=busy, mine=mine, spare=spare)
    return spare


@contextlib.contextmanager
def solve_threads():
    """numba and BLAS threads inside limited to :func:`spare_cores_now` (nothing changes on an idle machine)."""
    count = spare_cores_now()
    import numba

    if count >= numba.get_num_threads():
        yield
        return
    with numba_threads(count), blas_threads(count):
        yield


def numba_loops_at_once() -> bool:
    """Whether two threads of this process may run numba's parallel loops at the same time.

    numba's OpenMP and TBB threading layers allow it; its fallback, the workqueue layer
    (a machine with neither libgomp nor tbb), terminates the process when it sees it, so a
    caller then keeps its parallel loops on one thread. False as well before any parallel
    loop has run in this process (numba picks its layer then; compiling a loop only to ask
    would cost a second).
    """
    import numba

    try:
        return numba.threading_layer() in ("omp", "tbb")
    except ValueError:
        return False


@contextlib.contextmanager
def numba_threads(count: int | None):
    """``count`` numba threads for the parallel loops this thread runs inside (None: unchanged).

    numba's thread count is thread-local: a Dask task or one of several threads building parts of
    a job each set their own. BLAS is left as it is (the callers run with one BLAS thread).
    """
    if count is None:
        yield
        return
    import numba

    before = numba.get_num_threads()
    numba.set_num_threads(max(1, min(int(count), numba.config.NUMBA_NUM_THREADS)))
    try:
        yield
    finally:
        numba.set_num_threads(before)
