"""Benchmark: `hfrad view`, time from an emission change to new colours sent, through the server's own path.

For each factorization a real :class:`hfrad.viewer.ViewerApp` (viser server on a free
local port) is started with one websocket client connected (a thread that reads every
message, as a browser tab would). Then, ``--repeat`` times, the light's intensity is
changed through ``app.set_emitter`` (what the page's slider callback calls) and we time

* ``solve``: radiosity for the new emission (superposition of the batched unit solves,
  or ``fac.solve(E)`` in ``--direct`` mode),
* ``colours``: smoothing to vertices, tone mapping, ACES pre-compensation, GLB encoding,
* ``sent``: from the change to the server's ``flush`` of the new mesh (the goal's figure),
* ``received``: from the change to the websocket client holding the new mesh,
* (superposition only) ``add_emitter_sent_ms``: a material made an emitter (one batched
  solve for all emitters, then the same path), and ``sent_4_emitters_ms``: slider changes
  with four emitters,

median and worst over the repeats, for both the default update path (``superposition``)
and the ``direct`` one, next to a bare ``fac.solve`` of one RGB emission (the baseline
the direct path adds to). Goals: sent <= 50 ms at 10K patches, <= 150 ms at 40K.

Run:  python benchmarks/bench_viewer.py FILE.hfr [FILE.hfr ...] [--repeat 20]
      (make the files with `hfrad precompute cornell --patches 10000 --eps 0.02 -o c10k.hfr`)
Writes benchmarks/results/viewer.json.
"""

from __future__ import annotations

import argparse
import socket
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

import common
import hfrad
from hfrad.viewer import ViewerApp

GOALS_MS = {10_000: 50.0, 40_000: 150.0}
#: A websocket message at least this long carries a new mesh (viser compresses it; the other
#: messages of an update, e.g. the readout text, are a few hundred bytes).
MESH_MESSAGE_BYTES = 2048


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Listener:
    """A websocket client in a thread: records when each large message (a new mesh) arrives."""

    def __init__(self, url: str, proto: str, min_bytes: int) -> None:
        from websockets.sync.client import connect

        self.ws = connect(url, subprotocols=[proto], open_timeout=30, max_size=None)
        self.min_bytes = min_bytes
        self.arrivals: list[float] = []
        self.cv = threading.Condition()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        try:
            for msg in self.ws:
                if len(msg) >= self.min_bytes:
                    with self.cv:
                        self.arrivals.append(time.perf_counter())
                        self.cv.notify_all()
        except Exception:
            pass

    def wait_after(self, t: float, timeout: float = 30.0) -> float:
        with self.cv:
            self.cv.wait_for(lambda: self.arrivals and self.arrivals[-1] > t, timeout)
            return self.arrivals[-1] if self.arrivals and self.arrivals[-1] > t else float("nan")

    def close(self) -> None:
        self.ws.close()


def bench_file(path: Path, direct: bool, repeat: int) -> dict:
    import viser

    fac = hfrad.load(path)
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        app = ViewerApp(fac, port=free_port(), save_dir=tmp, direct=direct)
        t_start = time.perf_counter() - t0
        name = app.state.emitters[0].name
        # fixed exposure: under auto exposure a brighter light gives the same colours, and viser
        # sends nothing for an unchanged mesh
        app.state.auto_exposure, app.state.exposure = False, app._shown[2]
        base = app.state.emitters[0].intensity
        listener = Listener(app.url.replace("http", "ws"), f"viser-v{viser.__version__}",
                            min_bytes=MESH_MESSAGE_BYTES)
        time.sleep(1.0)                                  # initial scene sent
        done = threading.Event()
        stats = []
        app.add_listener(lambda s: (stats.append(s), done.set()))
        received = []
        for r in range(repeat + 2):                      # the first two warm up
            done.clear()
            t = app.set_emitter(name, intensity=base * (1.0 + 0.5 * ((r % 2) - 0.5)))
            done.wait(60)
            arrival = listener.wait_after(t)
            if r >= 2:
                received.append(arrival - t)
            time.sleep(0.05)
        slider = list(stats[2:])                        # the listener keeps appending to `stats`
        extra = {}
        if not direct:
            # a material made an emitter: one batched solve for all emitters, then the same path
            others = [m for m in fac.scene.material_names if m != name][:3]
            for i, other in enumerate(others):
                done.clear()
                t = app.add_emitter(other, intensity=base / 4)
                done.wait(120)
                listener.wait_after(t)
                if i == 0:
                    extra["add_emitter_sent_ms"] = 1e3 * app.last.sent
                    extra["add_emitter_basis_ms"] = 1e3 * app.lighting.basis_seconds
            sent = []
            for r in range(max(5, repeat // 2)):
                done.clear()
                app.set_emitter(name, intensity=base * (1.0 + 0.5 * ((r % 2) - 0.5)))
                done.wait(60)
                sent.append(app.last.sent)
                time.sleep(0.05)
            extra[f"sent_{len(app.state.emitters)}_emitters_ms"] = 1e3 * statistics.median(sent)
        listener.close()
        app.close()
    row = {"file": str(path), "n": fac.n_patches, "k": fac.rank, "mode": "direct" if direct else "superposition",
           "emitters": len(app.state.emitters), "mesh_mb": slider[-1].bytes / 1e6, "startup_s": t_start,
           "repeats": len(slider)}
    for key, values in (("solve", [s.solve for s in slider]), ("colours", [s.colors for s in slider]),
                        ("sent", [s.sent for s in slider]), ("received", received)):
        ok = [v for v in values if v == v]           # NaN: the client saw no new mesh within 30 s
        row[f"{key}_ms"] = 1e3 * statistics.median(ok) if ok else float("nan")
        row[f"{key}_max_ms"] = 1e3 * max(ok) if ok else float("nan")
        if len(ok) < len(values):
            row[f"{key}_missed"] = len(values) - len(ok)
    goal = min((g for n, g in GOALS_MS.items() if fac.n_patches <= n * 1.1), default=None)
    row["goal_ms"] = goal
    row["meets_goal"] = None if goal is None else row["sent_ms"] <= goal
    E = app.lighting.exitance(app.state.emitters)
    fac.solve(E)
    t = common.best_of(lambda: fac.solve(E), 10, max_seconds=10)
    row["bare_fac_solve_ms"] = 1e3 * t.best
    row.update(extra)
    row["loadavg"] = common.check_load()
    return row


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("files", nargs="+", type=Path, help="factorizations (.hfr) to serve")
    p.add_argument("--repeat", type=int, default=20)
    p.add_argument("--no-direct", action="store_true", help="skip the direct-solve mode")
    p.add_argument("--name", default="viewer", help="results/NAME.json")
    common.add_blas_arg(p)
    args = p.parse_args()
    m = common.header("hfrad view: emission change -> new colours sent", args.blas_threads)
    rows = []
    for path in args.files:
        for direct in (False,) if args.no_direct else (False, True):
            print(f"[{path} {'direct' if direct else 'superposition'}]", file=sys.stderr, flush=True)
            rows.append(bench_file(path, direct, args.repeat))
    common.print_table("change -> colours (median over repeats; max in JSON)", rows,
                       ["n", "k", "mode", ("solve_ms", "solve ms"), ("colours_ms", "colours ms"),
                        ("sent_ms", "sent ms"), ("received_ms", "received ms"), ("sent_max_ms", "sent max"),
                        ("bare_fac_solve_ms", "fac.solve ms"), ("add_emitter_sent_ms", "add emitter ms"),
                        ("sent_4_emitters_ms", "sent, 4 emitters"), ("mesh_mb", "MB"), ("goal_ms", "goal ms"),
                        ("meets_goal", "ok"), "loadavg"])
    out = common.write_json(args.name, {"machine": m, "rows": rows, "goals_ms": GOALS_MS})
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
