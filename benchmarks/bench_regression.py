"""Side by side: ``hfrad precompute`` of the current tree against an earlier commit, alternately.

The earlier commit (default ``d11fd0c``) is installed once into its own virtual
environment, ``/tmp/hfrad-venv-<sha>`` (``git archive`` of the commit, ``python3 -m venv
--system-site-packages`` so numpy, scipy, numba and embreex are the same ones, then
``pip install --no-deps``; offline without a build backend, the source on the venv's path
by a ``.pth`` file instead). Each case then runs the same ``precompute`` command line with
the old install and with this tree, alternating (old, new, old, new, ...) so that a
change of the machine's load hits both about equally; the best of ``--repeat`` runs of
each is compared. Stage times are read from the command's last lines (both versions
print ``rank K, ... time T s (form factors F s, factorization H s)``).

Cases (``--cases``, comma-separated):

* ``10k``: ``cornell --patches 10000 --eps 0.02`` (the issue's 10K command)
* ``sponza20k``: Sponza (``../shared/scenes/sponza-dabrovic/sponza.obj``) ``--area-light
  50,50,50 --patches 20000 --eps 0.05``
* ``40k``: ``cornell --patches 40000 --eps 0.02``
* ``40k-hierarchical``: ``cornell --patches 40000 --eps 0.05 --far-field hierarchical`` (the H-matrix path)

Each install first runs a 300-patch precompute so that numba's compile cache is warm.

Usage::

    python benchmarks/bench_regression.py                       # 10k, best of 3
    python benchmarks/bench_regression.py --cases 10k,sponza20k --repeat 1
    python benchmarks/bench_regression.py --commit abc1234 --name regression-abc

Writes ``benchmarks/results/<name>.json``: the machine (CPU model, cores, load
average before and after every run), the command lines, every run's stage times and
the best-of ratios (old / new: above 1 means the current tree is faster).
The machine may be shared: the load averages say how far to trust a ratio.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from common import SHARED_SCENES, check_load, machine, write_json

REPO = Path(__file__).resolve().parent.parent
SPONZA = SHARED_SCENES / "sponza-dabrovic" / "sponza.obj"

#: name -> precompute arguments (after the scene)
CASES: dict[str, list[str]] = {
    "10k": ["cornell", "--patches", "10000", "--eps", "0.02"],
    "sponza20k": [str(SPONZA), "--area-light", "50,50,50", "--patches", "20000", "--eps", "0.05"],
    "40k": ["cornell", "--patches", "40000", "--eps", "0.02"],
    "40k-hierarchical": ["cornell", "--patches", "40000", "--eps", "0.05", "--far-field", "hierarchical"],
}
WARMUP = ["cornell", "--patches", "300", "--eps", "0.05"]

_REPORT = re.compile(r"wrote .*?: ([\d,]+) patches, rank ([\d,]+), achieved error ([\d.eE+-]+)", re.S)
_TIMES = re.compile(r"time ([\d.]+) s \(form factors ([\d.]+) s, factorization ([\d.]+) s")
_SOLVER = re.compile(r"solver (.+?), time ")


def _git(*args: str) -> str:
    return subprocess.run(["git", *args], cwd=REPO, check=True, capture_output=True, text=True).stdout.strip()


def install_commit(commit: str, root: Path = Path(tempfile.gettempdir())) -> Path:
    """The python of a venv holding ``commit`` of this repository (made once, reused).

    Returns the venv's ``bin/python``; raises RuntimeError when the install fails.
    """
    sha = _git("rev-parse", "--verify", commit + "^{commit}")
    venv = root / f"hfrad-venv-{sha[:12]}"
    python = venv / "bin" / "python"
    marker = venv / "hfrad-commit"
    if python.exists() and marker.exists() and marker.read_text().strip() == sha:
        return python
    if venv.exists():
        shutil.rmtree(venv)
    src = Path(tempfile.mkdtemp(prefix=f"hfrad-src-{sha[:12]}-"))
    try:
        archive = subprocess.run(["git", "archive", sha], cwd=REPO, check=True, capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", str(src)], input=archive, check=True)
        subprocess.run([sys.executable, "-m", "venv", "--system-site-packages", str(venv)], check=True)
        done = subprocess.run([str(python), "-m", "pip", "install", "-q", "--no-deps", str(src)])
        if done.returncode != 0:
            # no build backend to be had (offline): the source itself on the venv's path, as an
            # editable install would put it
            kept = venv / "src"
            shutil.copytree(src, kept)
            site = subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                                  check=True, capture_output=True, text=True).stdout.strip()
            Path(site, "hfrad-under-test.pth").write_text(str(kept / "src") + "\n")
    finally:
        shutil.rmtree(src, ignore_errors=True)
    where = subprocess.run([str(python), "-c", "import hfrad; print(hfrad.__file__)"], check=True,
                           capture_output=True, text=True).stdout.strip()
    if not where.startswith(str(venv)):
        raise RuntimeError(f"the venv imports hfrad from {where}, not from its own install")
    marker.write_text(sha + "\n")
    return python


def _command(python: Path | str, args: list[str], output: Path) -> list[str]:
    return [str(python), "-m", "hfrad", "precompute", *args, "-o", str(output), "--quiet"]


def parse_report(text: str) -> dict:
    """Patches, rank, achieved error, total / form-factor / factorization seconds and solver of a precompute."""
    out: dict = {}
    m = _REPORT.search(text)
    if m:
        out.update(patches=int(m[1].replace(",", "")), rank=int(m[2].replace(",", "")), achieved_error=float(m[3]))
    m = _TIMES.search(text)
    if m:
        out.update(time=float(m[1]), time_formfactors=float(m[2]), time_factorization=float(m[3]))
    m = _SOLVER.search(text)
    out["solver"] = m[1] if m else "woodbury"   # d11fd0c had only Woodbury and did not print it
    return out


def hfr_timings(path: Path) -> dict:
    """The stage times a .hfr file records (``timings`` attribute, JSON; both versions write it)."""
    try:
        import h5py

        with h5py.File(path, "r") as fh:
            return json.loads(fh.attrs["timings"])
    except (OSError, KeyError, ValueError, ImportError):
        return {}


def run_once(python: Path | str, args: list[str], workdir: Path, timeout: float) -> dict:
    """One precompute; its parsed report plus wall seconds and the load average before and after."""
    output = workdir / "bench.hfr"
    for p in (output, output.with_name(output.name + ".partial")):
        p.unlink(missing_ok=True)
    cmd = _command(python, args, output)
    load0 = os.getloadavg()
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, cwd=workdir)
    except subprocess.TimeoutExpired:
        # a run that would take hours: its time is known to exceed the timeout (a bound on the ratio)
        return {"wall": time.perf_counter() - t0, "load_before": list(load0), "load_after": list(os.getloadavg()),
                "rc": None, "timed_out": True, "timeout": timeout}
    wall = time.perf_counter() - t0
    rec = {"wall": wall, "load_before": list(load0), "load_after": list(os.getloadavg()), "rc": proc.returncode}
    if proc.returncode != 0:
        rec["error"] = (proc.stdout + proc.stderr)[-2000:]
        return rec
    rec.update(parse_report(proc.stdout + proc.stderr))
    rec["timings"] = hfr_timings(output)
    _times_from_file(rec)
    output.unlink(missing_ok=True)
    return rec


def _times_from_file(rec: dict) -> None:
    """The stage times from the .hfr file's record where the command printed no time line (the
    hierarchical path's report has none): precompute, form factors (the H-matrix) and factorization."""
    t = rec.get("timings", {})
    if "time" not in rec and "time_precompute" in t:
        rec.update(time=t["time_precompute"], time_formfactors=t.get("time_formfactors", 0.0),
                   time_factorization=t.get("time_factorization", 0.0))


def _best(runs: list[dict]) -> dict | None:
    ok = [r for r in runs if r.get("rc") == 0 and "time" in r]
    return min(ok, key=lambda r: r["time"]) if ok else None


def _ratio(old: dict | None, new: dict | None, key: str) -> float | None:
    if not old or not new or not new.get(key):
        return None
    return old[key] / new[key]


def _ratio_at_least(old_runs: list[dict], new: dict | None) -> float | None:
    """Old / new when every old run timed out: at least the timeout over the new wall time (both walls)."""
    if new is None or not old_runs or not all(r.get("timed_out") for r in old_runs):
        return None
    return min(r["timeout"] for r in old_runs) / new["wall"]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--commit", default="d11fd0c", help="earlier commit to compare with (default d11fd0c)")
    ap.add_argument("--cases", default="10k", help=f"comma-separated, of {', '.join(CASES)} (default 10k)")
    ap.add_argument("--repeat", type=int, default=3, help="runs of each version per case; best counts (default 3)")
    ap.add_argument("--name", default=None, help="results/NAME.json (default regression-<cases>)")
    ap.add_argument("--timeout", type=float, default=3600.0, help="seconds per run before it is killed")
    ap.add_argument("--new-first", action="store_true", help="start each pair with the current tree")
    a = ap.parse_args(argv)
    cases = [c.strip() for c in a.cases.split(",") if c.strip()]
    unknown = [c for c in cases if c not in CASES]
    if unknown:
        ap.error(f"unknown case(s) {unknown}; known: {list(CASES)}")
    if "sponza20k" in cases and not SPONZA.exists():
        ap.error(f"{SPONZA} not found (set HFRAD_SHARED_SCENES)")

    old_sha = _git("rev-parse", "--short=12", a.commit)
    head = _git("rev-parse", "--short=12", "HEAD")
    dirty = bool(_git("status", "--porcelain", "--untracked-files=no", "--", "src"))
    print(f"installing {a.commit} ({old_sha}) ...", flush=True)
    old_python = install_commit(a.commit)
    versions = {"old": old_python, "new": Path(sys.executable)}
    check_load()
    start = machine()
    workdir = Path(tempfile.mkdtemp(prefix="hfrad-bench-regression-"))
    results: dict = {}
    try:
        for tag, py in versions.items():   # numba's cache of each install, compiled once
            run_once(py, WARMUP, workdir, a.timeout)
        for case in cases:
            runs: dict[str, list[dict]] = {"old": [], "new": []}
            order = ["new", "old"] if a.new_first else ["old", "new"]
            for i in range(a.repeat):
                for tag in order:
                    rec = run_once(versions[tag], CASES[case], workdir, a.timeout)
                    runs[tag].append(rec)
                    print(f"{case} {tag} run {i + 1}: " + (
                        f"{rec['time']:.1f} s (ff {rec['time_formfactors']:.1f}, HF {rec['time_factorization']:.1f}), "
                        f"rank {rec['rank']}, load {rec['load_before'][0]:.2f} -> {rec['load_after'][0]:.2f}"
                        if "time" in rec else f"TIMED OUT after {rec['wall']:.0f} s" if rec.get("timed_out")
                        else f"FAILED rc {rec['rc']}: {rec.get('error', '')[-300:]}"), flush=True)
            best = {tag: _best(r) for tag, r in runs.items()}
            results[case] = {"args": CASES[case], "runs": runs, "best": best,
                             "ratio": {k: _ratio(best["old"], best["new"], k)
                                       for k in ("time", "time_formfactors", "time_factorization")},
                             "ratio_at_least": _ratio_at_least(runs["old"], best["new"])}
    finally:
        shutil.rmtree(workdir, ignore_errors=True)

    print(f"\n{'case':<10} {'version':<14} {'total s':>8} {'ff s':>7} {'HF s':>7} {'rank':>6}  solver")
    for case, r in results.items():
        for tag, label in (("old", old_sha), ("new", head + ("+" if dirty else ""))):
            b = r["best"][tag]
            if b is None:
                print(f"{case:<10} {label:<14} {'failed':>8}")
                continue
            print(f"{case:<10} {label:<14} {b['time']:8.1f} {b['time_formfactors']:7.1f} "
                  f"{b['time_factorization']:7.1f} {b['rank']:6d}  {b['solver']}")
        rt = r["ratio"]
        if r["ratio_at_least"] is not None:
            print(f"{case:<10} {'old / new':<14} > {r['ratio_at_least']:.2f}x (every {old_sha} run timed out)")
        if rt["time"] is not None:
            print(f"{case:<10} {'old / new':<14} {rt['time']:7.2f}x {rt['time_formfactors']:6.2f}x "
                  f"{rt['time_factorization']:6.2f}x")
    data = {"old_commit": old_sha, "new_commit": head, "new_tree_modified": dirty, "repeat": a.repeat,
            "machine_before": start, "loadavg_after": list(os.getloadavg()), "cases": results}
    path = write_json(a.name or "regression-" + "-".join(cases), data)
    print(f"\nwrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
