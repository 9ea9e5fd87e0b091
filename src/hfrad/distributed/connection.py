"""Connecting to a Dask cluster: an existing scheduler, a LocalCluster, or a Client the caller made."""

from __future__ import annotations

import contextlib
import importlib.util
import logging
from dataclasses import dataclass
from typing import Iterator

from ..errors import InputError
from ..resources import blas_threads, cores


def default_connect_timeout() -> float:
    """Dask's own connect timeout (``distributed.comm.timeouts.connect``, 30 s unless configured,
    e.g. ``DASK_DISTRIBUTED__COMM__TIMEOUTS__CONNECT=5s``), in seconds."""
    import dask
    from dask.utils import parse_timedelta

    return float(parse_timedelta(dask.config.get("distributed.comm.timeouts.connect"), default="s"))


class SchedulerUnreachableError(ConnectionError):
    """The Dask scheduler could not be reached, or has no workers; the message names the address."""


class WorkerLostError(RuntimeError):
    """A task kept killing its workers (Dask's ``KilledWorker``), usually for lack of memory."""


@dataclass
class Cluster:
    """A connected Dask client and what the precompute needs to know about its cluster.

    Attributes
    ----------
    client : distributed.Client
    address : str
        The scheduler's address (``tcp://host:port``, or ``inproc://...``).
    n_workers : int
        Workers connected when the run started.
    dashboard : str or None
        The Dask dashboard's address, when the scheduler serves one.
    kind : {"local", "scheduler", "client"}
        A LocalCluster started here, an existing scheduler, or a Client passed in.
    task_threads : int or None
        Numba threads per task: the cores of this machine shared among the
        workers of a LocalCluster; None (the worker's own setting) elsewhere.
    """

    client: object
    address: str
    n_workers: int
    dashboard: str | None
    kind: str
    task_threads: int | None

    def worker_memory_limits(self) -> list[int]:
        """Each worker's memory limit in bytes (0 where the worker has none)."""
        workers = self.client.scheduler_info()["workers"].values()
        return [int(w.get("memory_limit") or 0) for w in workers]


def _dashboard(client, served: bool) -> str | None:
    if not served:
        return None
    try:
        return client.dashboard_link if "dashboard" in client.scheduler_info()["services"] else None
    except (KeyError, AttributeError):
        return None


def _check_address(address: str) -> str:
    address = address.strip()
    if not address or any(c.isspace() for c in address):
        raise InputError(f"scheduler address must look like tcp://HOST:PORT; got {address!r}")
    return address if "://" in address else f"tcp://{address}"


@contextlib.contextmanager
def connect(scheduler=None, *, workers: int | None = None, timeout: float | None = None,
            processes: bool = True) -> Iterator[Cluster]:
    """Connect to a Dask cluster for the duration of a ``with`` block.

    Parameters
    ----------
    scheduler : str or distributed.Client, optional
        ``tcp://HOST:PORT`` of a running ``dask scheduler``, or a Client the
        caller owns (left open on exit).
    workers : int, optional
        Start a LocalCluster of this many worker processes on this machine
        (one thread each), closed on exit. Exactly one of ``scheduler`` and
        ``workers`` must be given.
    timeout : float, seconds, optional
        How long to try to reach the scheduler and to wait for its first worker
        (default: Dask's ``distributed.comm.timeouts.connect``).
    processes : bool
        LocalCluster only: worker processes (default) or threads of this process.

    Yields
    ------
    Cluster

    Raises
    ------
    SchedulerUnreachableError
        The scheduler did not answer within ``timeout`` or has no workers.
    ValueError
        Both or neither of ``scheduler`` / ``workers``; a malformed address; workers < 1.
    """
    try:
        from distributed import Client, LocalCluster
    except ImportError as exc:  # pragma: no cover - a dependency of hfrad
        raise ImportError("the cluster backend needs dask.distributed: pip install 'dask[distributed]'") from exc
    if (scheduler is None) == (workers is None):
        raise InputError("give either a scheduler address (tcp://HOST:PORT) or a number of local workers, not "
                         f"{'both' if scheduler is not None else 'neither'}")
    if isinstance(scheduler, Client):
        yield Cluster(scheduler, scheduler.scheduler.address, len(scheduler.nthreads()),
                      _dashboard(scheduler, True), "client", None)
        return
    if workers is not None:
        if int(workers) != workers or workers < 1:
            raise InputError(f"workers must be a positive integer; got {workers}")
        workers = int(workers)
        bokeh = importlib.util.find_spec("bokeh") is not None  # the dashboard needs it
        # ":0": any free port for the scheduler's HTTP server (8787 may belong to another cluster)
        with LocalCluster(n_workers=workers, threads_per_worker=1, processes=processes,
                          dashboard_address=":0", silence_logs=logging.ERROR) as lc, \
                Client(lc) as client, blas_threads(None if processes else 1):
            # Worker processes share this machine's cores; threads of this process share its BLAS pool
            # (one BLAS thread while in-process workers run).
            yield Cluster(client, lc.scheduler_address, workers, _dashboard(client, bokeh), "local",
                          max(1, cores() // workers) if processes else None)
        return
    address = _check_address(str(scheduler))
    timeout = default_connect_timeout() if timeout is None else float(timeout)
    try:
        client = Client(address, timeout=timeout)
    except (OSError, TimeoutError) as exc:
        raise SchedulerUnreachableError(
            f"cannot reach the Dask scheduler at {address} within {timeout:g} s ({exc}); "
            "is `dask scheduler` running there, and is the port open from this machine?") from None
    try:
        try:
            client.wait_for_workers(1, timeout=timeout)
        except (OSError, TimeoutError):
            raise SchedulerUnreachableError(
                f"the Dask scheduler at {address} has no workers after {timeout:g} s; "
                f"start some with `dask worker {address}`") from None
        yield Cluster(client, address, len(client.nthreads()), _dashboard(client, True),
                      "scheduler", None)
    finally:
        client.close()
