"""Cleaning and clustering a real scene, side by side: the ``clean`` and ``cluster`` stages of
``hfrad precompute SCENE --area-light 50,50,50 --patches N`` for two source trees, alternating.

Issue 46 asked for the conference room's clean + cluster (6.7 s idle) in well under half the time
with the same output. Each run is a fresh process with ``PYTHONPATH=<tree>/src`` (numba caches,
imports and first calls counted, as in a precompute); it reads the scene, adds the area light,
then times ``drop_degenerate`` + ``merge_duplicates`` (clean) and ``cluster`` (cluster), and hashes
the cleaned scene (vertices, faces, materials, groups, colours, parents) and the clustered one
(vertices, faces, patch of each triangle, materials, parents). Equal hashes: the same triangles
and patches to the bit. The trees alternate run by run, so a busy phase of the machine hits both;
the 1-minute load is recorded with each run. The numba caches of each tree are warmed first.

    git worktree add --detach /tmp/old <rev>
    python benchmarks/bench_clean_cluster.py --trees /tmp/old,. --scenes conference,sponza,sibenik --runs 3

Prints a table and writes ``results/clean-cluster-<scenes>.json``. Needs ``../shared/scenes``.
Not collected by pytest; not in CI.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import common  # noqa: E402

SCENES = {
    "sponza": "sponza-dabrovic/sponza.obj",
    "sibenik": "sibenik/sibenik.obj",
    "conference": "conference/conference.ply",
}

# Run in the child: the stages of hfrad.scene.load.load_scene, timed one by one, and the hashes.
CHILD = r"""
import hashlib, json, sys, time
import numpy as np
from hfrad.scene import load as L
from hfrad.scene.cleanup import merge_duplicates
from hfrad.scene.cluster import cluster
from hfrad.scene.patches import drop_degenerate

def digest(*arrays):
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype}{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()[:16]

path, patches = sys.argv[1], int(sys.argv[2])
t0 = time.perf_counter()
raw = L.add_area_light(L._read(path, 0.5, False), (50, 50, 50))
t1 = time.perf_counter()
s = merge_duplicates(drop_degenerate(raw))
t2 = time.perf_counter()
c = cluster(s, patches=patches)
t3 = time.perf_counter()
print(json.dumps({"load_s": t1 - t0, "clean_s": t2 - t1, "cluster_s": t3 - t2, "faces": s.n_patches,
                  "patches": c.n_patches, "triangles": c.n_triangles,
                  "clean_hash": digest(s.vertices, s.faces, s.material, s.group, s.reflectance, s.emission, s.parent),
                  "cluster_hash": digest(c.vertices, c.faces, c.triangle_patch, c.material, c.parent)}))
"""


def run_once(tree: Path, scene: str, patches: int) -> dict:
    env = dict(os.environ, PYTHONPATH=str(tree.resolve() / "src"))
    load = os.getloadavg()[0]
    out = subprocess.run([sys.executable, "-c", CHILD, str(common.SHARED_SCENES / SCENES[scene]), str(patches)],
                         env=env, capture_output=True, text=True, check=True).stdout
    row = json.loads(out.strip().splitlines()[-1])
    return {"scene": scene, "tree": str(tree), "load_1min": load, **row}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--trees", default=".", help="comma-separated source trees (each with src/hfrad)")
    parser.add_argument("--scenes", default="conference", help=f"comma-separated, of {', '.join(SCENES)}")
    parser.add_argument("--patches", type=int, default=3000)
    parser.add_argument("--runs", type=int, default=3, help="runs of each tree on each scene")
    args = parser.parse_args()
    if not common.SHARED_SCENES.exists():
        print(f"skipped: {common.SHARED_SCENES} (the public scenes) is not here")
        return
    trees = [Path(t) for t in args.trees.split(",")]
    scenes = args.scenes.split(",")
    for tree in trees:  # numba caches compiled, not timed
        run_once(tree, "sponza" if "sponza" in scenes else scenes[0], args.patches)
    rows = []
    for scene in scenes:
        for _ in range(args.runs):
            for tree in trees:
                rows.append(run_once(tree, scene, args.patches))
                print(common.table([rows[-1]], ["scene", "tree", "load_1min", "clean_s", "cluster_s", "faces",
                                                "patches", "clean_hash", "cluster_hash"]), flush=True)
    common.print_table(f"clean + cluster, {args.patches} patches requested", rows,
                       ["scene", "tree", "load_1min", "load_s", "clean_s", "cluster_s", "patches", "clean_hash",
                        "cluster_hash"])
    path = common.write_json(f"clean-cluster-{'-'.join(scenes)}", {"machine": common.machine(), "rows": rows,
                                                                   "patches": args.patches})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
