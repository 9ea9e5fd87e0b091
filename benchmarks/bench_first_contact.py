"""First contact, side by side: ``hfrad precompute SCENE --area-light 50,50,50 --patches N`` with
every other option at its default, for two source trees, back to back.

What a new user runs first on a real scene (issue 46's goal: <= 25 s at 3,000 patches on two idle
cores). Each run is a fresh ``python -m hfrad precompute`` process with ``PYTHONPATH=<tree>/src``,
timed from outside (wall, CPU of the process and its children, peak RSS from ``wait4``); the
precompute's own summary gives its stages (form factors, HF, ...) and the rank. The trees
alternate scene by scene, so a slow phase of the machine hits both. The numba caches of each tree
are warmed first (one small run each, not timed).

    git worktree add --detach /tmp/old <rev>
    python benchmarks/bench_first_contact.py --trees /tmp/old,. --scenes sponza,sibenik,conference

Prints a table and writes ``results/first-contact-<scenes>.json`` with the machine. Needs
``../shared/scenes`` (skipped with a message otherwise). Not collected by pytest; not in CI.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import common  # noqa: E402

SCENES = {
    "sponza": "sponza-dabrovic/sponza.obj",
    "sibenik": "sibenik/sibenik.obj",
    "conference": "conference/conference.ply",
}


def _stages(summary: str) -> dict:
    """{stage: seconds} of the precompute's summary line ("... time: load 0.6 s + clean 0.6 s + ... = 29.0 s")."""
    body = summary.split("time:", 1)[-1].split(" = ")[0]
    out = {}
    for part in body.split(" + "):
        name, _, seconds = part.strip().rpartition(" ")[0].rpartition(" ")
        if name:
            out[name] = float(seconds)
    return out


def run_once(tree: Path, scene: str, patches: int, out_dir: Path) -> dict:
    """One precompute of ``scene`` with the hfrad of ``tree``: wall, CPU, peak RSS, stages, rank."""
    env = dict(os.environ, PYTHONPATH=str(tree.resolve() / "src"))
    output = out_dir / f"{scene}-{patches}.hfr"
    cmd = [sys.executable, "-m", "hfrad", "precompute", str(common.SHARED_SCENES / SCENES[scene]),
           "--area-light", "50,50,50", "--patches", str(patches), "-o", str(output)]
    load = os.getloadavg()[0]
    output.unlink(missing_ok=True)
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    text = proc.stdout.read()
    _, status, usage = os.wait4(proc.pid, 0)          # this process's own CPU and peak RSS
    wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode:
        raise SystemExit(f"{tree}: {' '.join(cmd)} failed (exit {proc.returncode}):\n{text[-2000:]}")
    summary = next((line for line in text.splitlines() if line.startswith("solver ")), "")
    stages = _stages(summary)
    rank = re.search(r"rank ([\d,]+), achieved error", text)
    patches_made = re.search(r"wrote .*?: ([\d,]+) patches", text)
    output.unlink(missing_ok=True)
    commit = subprocess.run(["git", "-C", str(tree), "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True).stdout.strip()
    return {"tree": str(tree), "commit": commit, "scene": scene, "wall_s": wall, "cpu_s": usage.ru_utime + usage.ru_stime,
            "peak_rss_gb": usage.ru_maxrss / 1e6, "load_before": load,
            "rank": int(rank.group(1).replace(",", "")) if rank else None,
            "patches": int(patches_made.group(1).replace(",", "")) if patches_made else None,
            "form_factors_s": stages.get("form factors"), "hf_s": stages.get("HF"), "stages": stages}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--trees", default=".", help="comma-separated source trees (each with src/hfrad)")
    p.add_argument("--scenes", default="sponza,sibenik,conference")
    p.add_argument("--patches", type=int, default=3000)
    p.add_argument("--no-warm", action="store_true", help="skip the warm-up runs (numba caches already warm)")
    args = p.parse_args()
    if not common.SHARED_SCENES.exists():
        print(f"skipped: {common.SHARED_SCENES} (the public scenes) is not here")
        return
    trees = [Path(t) for t in args.trees.split(",")]
    scenes = [s for s in args.scenes.split(",") if s]
    for s in scenes:
        if s not in SCENES:
            raise SystemExit(f"unknown scene {s!r}; choose from {', '.join(SCENES)}")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        out_dir = Path(tmp)
        if not args.no_warm:
            for tree in trees:
                run_once(tree, scenes[0], 300, out_dir)
        for scene in scenes:
            for tree in trees:
                row = run_once(tree, scene, args.patches, out_dir)
                rows.append(row)
                print(common.table([row], ["scene", "tree", "patches", "wall_s", "cpu_s", "form_factors_s", "hf_s",
                                           "rank", "peak_rss_gb", "load_before"]), flush=True)
    common.print_table(f"first contact, {args.patches} patches requested", rows,
                       ["scene", "tree", "patches", "wall_s", "cpu_s", "form_factors_s", "hf_s", "rank",
                        "peak_rss_gb", "load_before"])
    path = common.write_json(f"first-contact-{'-'.join(scenes)}", {"machine": common.machine(), "rows": rows,
                                                                   "patches": args.patches})
    print(path)


if __name__ == "__main__":
    main()
