"""hfrad's illuminance on work planes side by side with Radiance (rtrace -I), and the time of both.

Radiance's binaries come from the PyPI package ``pyradiance`` (``pip install
-e ".[bench]"``; not a runtime dependency of hfrad). Each case converts the
hfrad scene, triangle for triangle, into Radiance (z-up: hfrad's (x, y, z) is
Radiance's (x, -z, y)):

- every reflectance is a Lambertian ``plastic`` with zero specularity and zero
  roughness (its RGB = the patch reflectance);
- every emitting patch is a ``light`` of radiance ``E / pi`` per channel, times
  683 / 179 so that Radiance's 179 lm/W white efficacy gives the lux of
  hfrad's 683 lm/W convention (``hfrad render --unit lux``);
- every luminaire goes through ``ies2rad -dm -c 1 1 1`` (metres, white) and
  ``xform -rz ROTATION -t X Y Z``.

The sensors (a work-plane grid) go to ``rtrace -h -I`` with converged settings
(``-ab 8 -ad 4096 -aa 0 -lw 1e-5 -ds 0.02 -dj 0 -dt 0 -dc 1``; ``--ad`` lowers
the divisions on a slow machine). Radiance's noise is estimated from the
sensors traced twice in one run (uncorrelated sampling, ``-u+``): the RMS of
the two runs' difference / sqrt(2), relative to the mean. Illuminance from
Radiance's RGB irradiance: 179 x the Rec. 709 luminance (hfrad's weights, so
coloured scenes compare like for like).

Cases:

- ``office``: examples/office with its 12 catalogue luminaires (layout.json,
  all at full output, background none), the 0.8 m work plane (floor outline,
  0.5 m border) at ``--office-spacing``; the ceiling cells under the six
  panels (material ``luminaire``) get reflectance 0 on both sides: they are the
  panels' faces, which Radiance's light polygons hide and which return 0 to
  its indirect rays;
- ``room``: a closed empty 4 x 2.8 x 3 m room (floor 0.2, walls 0.5,
  ceiling 0.7) with the office's IES downlight in the middle of the ceiling,
  the 0.8 m work plane at 0.5 m spacing (0.25 m border), factorized here;
- ``rad``: examples/buildings/office.rad, a Radiance file read by both: hfrad's
  reader (``hfrad.load_scene``, ``--rad-patches`` patches, its four ``light``
  panels as the scene's emitters, background scene) and Radiance's ``oconv``
  on the same file (its ``!genbox``/``!xform`` lines run by Radiance); the
  0.8 m work plane over the carpet (0.5 m border) at ``--office-spacing``. hfrad
  reads a ``light`` of radiance L as the exitance pi L 179/683, so both give
  the same lux;
- ``cornell``: ../shared/scenes/cornell-box/CornellBox-Original.obj (its own area
  light, background scene), a plane at 1.4 m over the box's floor (above both
  blocks) at ``--cornell-spacing``; the light's patches get reflectance 0 (a
  Radiance ``light`` does not reflect).

Timings: hfrad's precompute (factorization if not given, luminaires' direct
light, the batched solve, the gather operator) and one relighting, against
Radiance's oconv + rtrace for the one lighting state; with ``--rcontrib`` also
``rcontrib -I+`` with one modifier per luminaire (every luminaire's
contribution in one run, so any dimming is a weighted sum on Radiance's side
too), compared at five random dimmings; with ``--reflectance``
also a change Radiance must trace again for (walls at 60% of their
reflectance), hfrad by ``with_reflectance`` (no refactorization).

Usage::

    python benchmarks/bench_radiance.py --cases office,cornell [--hfr-office office.hfr] [--ad 4096]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import check_load, machine, machine_line, print_table, table, write_json  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
OFFICE = ROOT / "examples" / "office"
RAD_OFFICE = ROOT / "examples" / "buildings" / "office.rad"
CORNELL = ROOT.parent / "shared" / "scenes" / "cornell-box" / "CornellBox-Original.obj"
RADIANCE_EFFICACY = 179.0
Y709 = np.array([0.2126, 0.7152, 0.0722])


def _radiance():
    try:
        import pyradiance  # noqa: F401  (sets PATH and RAYPATH to its binaries and libraries)
    except ImportError as exc:
        raise SystemExit("this benchmark needs Radiance from PyPI: pip install pyradiance "
                         "(or pip install -e '.[bench]')") from exc
    return {name: shutil.which(name) for name in ("oconv", "rtrace", "ies2rad", "xform")}


def _zup(p: np.ndarray) -> np.ndarray:
    p = np.asarray(p, np.float64)
    return np.stack([p[..., 0], -p[..., 2], p[..., 1]], axis=-1)


def scene_to_rad(scene, path: Path, *, emit: bool, reflectance=None) -> dict:
    """Write the scene's triangles as Radiance polygons (``reflectance`` (n, 3) overrides the scene's)."""
    tri = _zup(np.asarray(scene.triangles))
    patch = np.asarray(scene.patch_of_triangle)
    rho = np.round(np.asarray(scene.reflectance if reflectance is None else reflectance), 6)[patch]
    E = np.asarray(scene.emission)[patch] if emit else np.zeros_like(rho)
    lines, mats = [], {}
    for i in range(len(tri)):
        if E[i].any():
            key = ("light",) + tuple(np.round(E[i], 9))
            if key not in mats:
                L = E[i] / math.pi * (683.0 / RADIANCE_EFFICACY)
                mats[key] = f"e{len(mats)}"
                lines.append(f"void light {mats[key]} 0 0 3 {L[0]:.9g} {L[1]:.9g} {L[2]:.9g}")
        else:
            key = ("plastic",) + tuple(rho[i])
            if key not in mats:
                mats[key] = f"m{len(mats)}"
                r = rho[i]
                lines.append(f"void plastic {mats[key]} 0 0 5 {r[0]:.6g} {r[1]:.6g} {r[2]:.6g} 0 0")
        v = tri[i].reshape(-1)
        lines.append(f"{mats[key]} polygon t{i} 0 0 9 " + " ".join(f"{x:.9g}" for x in v))
    path.write_text("\n".join(lines) + "\n")
    return {"polygons": len(tri), "materials": len(mats)}


def luminaires_to_rad(layout_path: Path, luminaires, work: Path, tools: dict) -> list[Path]:
    """ies2rad each photometric file once, then one xform'ed instance per luminaire."""
    raw = json.loads(layout_path.read_text())
    defaults = raw.get("defaults", {})
    files = [Path(layout_path.parent, {**defaults, **e}["photometry"]) for e in raw["luminaires"]]
    converted, out = {}, []
    for lum, f in zip(luminaires, files):
        if not np.allclose(lum.aim, [0, -1, 0]):
            raise SystemExit(f"{lum.name}: only luminaires aimed straight down are converted here")
        if f not in converted:
            root = f"lum{len(converted)}"
            subprocess.run([tools["ies2rad"], "-dm", "-c", "1", "1", "1", "-o", root, str(f)], cwd=work,
                           check=True, capture_output=True)
            converted[f] = work / f"{root}.rad"
        p = _zup(lum.position)
        inst = work / f"inst_{lum.name}.rad"
        with open(inst, "w") as fh:
            subprocess.run([tools["xform"], "-rz", f"{lum.rotation:g}", "-t", *(f"{x:.9g}" for x in p),
                            converted[f].name], cwd=work, check=True, stdout=fh)
        out.append(inst)
    return out


def run_radiance(scene, sensors, *, luminaires=(), layout=None, emit: bool, ad: int, ab: int, threads: int,
                 work: Path, tools: dict, reflectance=None, rad_file: Path | None = None) -> dict:
    """Illuminance (lux) at the sensors by rtrace -I; each sensor traced twice (noise).

    ``rad_file``: Radiance reads this scene file itself (oconv in its folder) instead of the
    scene's triangles."""
    t0 = time.perf_counter()
    if rad_file is not None:
        info = {"polygons": None, "materials": None, "rad_file": str(rad_file)}
        with open(work / "scene.oct", "wb") as fh:
            # -f: a frozen octree (the scene inside it), as rtrace runs in another folder
            subprocess.run([tools["oconv"], "-f", rad_file.name], cwd=rad_file.parent, check=True, stdout=fh)
    else:
        info = scene_to_rad(scene, work / "scene.rad", emit=emit, reflectance=reflectance)
        files = ["scene.rad"] + [p.name for p in (luminaires_to_rad(layout, luminaires, work, tools)
                                                   if luminaires else [])]
        with open(work / "scene.oct", "wb") as fh:
            subprocess.run([tools["oconv"], *files], cwd=work, check=True, stdout=fh)
    t_conv = time.perf_counter() - t0
    P, N = _zup(sensors.points), _zup(sensors.normals)
    text = "".join(" ".join(f"{v:.9g}" for v in row) + "\n" for row in np.hstack([P, N]))
    opts = ["-h", "-I", "-u+", "-ab", str(ab), "-ad", str(ad), "-aa", "0", "-as", "0", "-lw", "1e-5", "-lr", "-12",
            "-ds", "0.02", "-dj", "0", "-dt", "0", "-dc", "1", "-st", "0", "-n", str(threads)]
    t1 = time.perf_counter()
    res = subprocess.run([tools["rtrace"], *opts, "scene.oct"], cwd=work, input=text * 2, check=True,
                         capture_output=True, text=True)
    t_trace = time.perf_counter() - t1
    rgb = np.array([[float(x) for x in line.split()[:3]] for line in res.stdout.strip().splitlines()])
    lux = RADIANCE_EFFICACY * rgb @ Y709
    m = len(P)
    a, b = lux[:m], lux[m:]
    mean = 0.5 * (a + b)
    noise = float(np.sqrt(np.mean((a - b) ** 2) / 2) / max(mean.mean(), 1e-300))
    return {"lux": mean, "noise_rel_rms": noise / math.sqrt(2),    # of the mean of the two runs
            "convert_s": t_conv, "rtrace_s_two_runs": t_trace, "rtrace_s": t_trace / 2, "options": " ".join(opts),
            **info}


def run_rcontrib(scene, sensors, luminaires, layout: Path, *, ad: int, ab: int, threads: int, work: Path,
                 tools: dict, reflectance=None) -> dict:
    """Each luminaire's contribution (lux at dimming 1) at the sensors in one rcontrib run (one modifier each;
    -V+: contributions, not coefficients)."""
    t0 = time.perf_counter()
    scene_to_rad(scene, work / "scene.rad", emit=False, reflectance=reflectance)
    raw = json.loads(layout.read_text())
    defaults = raw.get("defaults", {})
    files = [Path(layout.parent, {**defaults, **e}["photometry"]) for e in raw["luminaires"]]
    names = []
    for k, (lum, f) in enumerate(zip(luminaires, files)):
        root = f"lum{k}"                                   # a separate ies2rad output: its own modifier
        subprocess.run([shutil.which("ies2rad"), "-dm", "-c", "1", "1", "1", "-o", root, str(f)], cwd=work,
                       check=True, capture_output=True)
        with open(work / f"inst{k}.rad", "w") as fh:
            subprocess.run([tools["xform"], "-rz", f"{lum.rotation:g}", "-t", *(f"{x:.9g}" for x in _zup(lum.position)),
                            f"{root}.rad"], cwd=work, check=True, stdout=fh)
        names.append(f"{root}_light")
    with open(work / "scene.oct", "wb") as fh:
        subprocess.run([tools["oconv"], "scene.rad", *(f"inst{k}.rad" for k in range(len(names)))], cwd=work,
                       check=True, stdout=fh)
    P, N = _zup(sensors.points), _zup(sensors.normals)
    text = "".join(" ".join(f"{v:.9g}" for v in row) + "\n" for row in np.hstack([P, N]))
    opts = ["-h", "-I+", "-V+", "-ab", str(ab), "-ad", str(ad), "-aa", "0", "-lw", "1e-5", "-lr", "-12", "-ds", "0.02",
            "-dj", "0", "-dt", "0", "-dc", "1", "-st", "0", "-n", str(threads)]
    mods = [x for m in names for x in ("-m", m)]
    t1 = time.perf_counter()
    res = subprocess.run([shutil.which("rcontrib"), *opts, *mods, "scene.oct"], cwd=work, input=text, check=True,
                         capture_output=True, text=True)
    t_run = time.perf_counter() - t1
    vals = np.array([[float(x) for x in line.split()] for line in res.stdout.strip().splitlines()])
    rgb = vals.reshape(len(P), len(names), 3)
    return {"lux": RADIANCE_EFFICACY * rgb @ Y709, "rcontrib_s": t_run, "convert_s": t1 - t0,
            "options": " ".join(opts)}


def compare(h: np.ndarray, r: np.ndarray) -> dict:
    d = h - r
    return {"rms_rel": float(np.sqrt(np.mean((d / np.maximum(r, 1e-9)) ** 2))),
            "rms_over_mean": float(np.sqrt(np.mean(d ** 2)) / r.mean()),
            "mean_rel": float(h.mean() / r.mean() - 1), "max_abs_rel": float(np.max(np.abs(d) / np.maximum(r, 1e-9)))}


def _closed_room(folder: Path) -> Path:
    """A closed empty 4 x 2.8 x 3 m room (y up, faces inward): floor 0.2, walls 0.5, ceiling 0.7."""
    X, Y, Z = 4.0, 2.8, 3.0
    v = [(x, y, z) for x in (0, X) for y in (0, Y) for z in (0, Z)]
    idx = {p: i + 1 for i, p in enumerate(v)}
    quads = {"floor": [(0, 0, 0), (X, 0, 0), (X, 0, Z), (0, 0, Z)],
             "ceiling": [(0, Y, 0), (0, Y, Z), (X, Y, Z), (X, Y, 0)],
             "wall": [[(0, 0, 0), (0, 0, Z), (0, Y, Z), (0, Y, 0)], [(X, 0, 0), (X, Y, 0), (X, Y, Z), (X, 0, Z)],
                      [(0, 0, 0), (0, Y, 0), (X, Y, 0), (X, 0, 0)], [(0, 0, Z), (X, 0, Z), (X, Y, Z), (0, Y, Z)]]}
    lines = ["mtllib room.mtl"] + [f"v {x} {y} {z}" for x, y, z in v]
    for mat, q in quads.items():
        lines.append(f"usemtl {mat}")
        for quad in (q if mat == "wall" else [q]):
            lines.append("f " + " ".join(str(idx[p]) for p in quad[::-1]))      # counter-clockwise from inside
    (folder / "room.obj").write_text("\n".join(lines) + "\n")
    (folder / "room.mtl").write_text("newmtl floor\nKd 0.2 0.2 0.2\nnewmtl wall\nKd 0.5 0.5 0.5\n"
                                     "newmtl ceiling\nKd 0.7 0.7 0.7\n")
    return folder / "room.obj"


def _dense_check(fac, model, resp, ab: int) -> dict:
    """The same sensors with the exact dense F: all bounces (LU), and truncated after ``ab`` (as rtrace -ab)."""
    from hfrad.formfactors.blocks import form_factor_matrix
    from hfrad.render.falsecolor import LUMINOUS_EFFICACY

    t0 = time.perf_counter()
    F = form_factor_matrix(fac.scene)
    seconds = time.perf_counter() - t0
    rho = np.asarray(fac.reflectance)
    w = model.dimming
    colours = np.array([l.color for l in model.luminaires]).reshape(-1, 3)
    E1 = rho * ((model.patch_direct @ np.diag(w) / LUMINOUS_EFFICACY) @ colours) if len(w) else 0 * rho
    E0 = np.asarray(fac.scene.emission) if model.background == "scene" else 0 * rho
    exact = np.empty_like(rho)
    trunc = np.empty_like(rho)
    n = len(rho)
    for c in range(3):
        A = np.eye(n) - rho[:, c:c + 1] * F
        exact[:, c] = np.linalg.solve(A, E1[:, c] + E0[:, c])
        # rtrace -ab N: N diffuse bounces after the direct light: sum_{i<N} (RF)^i E1 + sum_{i<=N} (RF)^i E0
        term1, term0 = E1[:, c].copy(), E0[:, c].copy()
        acc = term1 + term0
        for i in range(1, ab + 1):
            term0 = rho[:, c] * (F @ term0)
            acc += term0
            if i < ab:
                term1 = rho[:, c] * (F @ term1)
                acc += term1
        trunc[:, c] = acc
    D = resp.direct @ w if len(w) else 0.0
    lux = lambda B: D + LUMINOUS_EFFICACY * (resp.gather.apply(B) @ Y709)  # noqa: E731
    return {"exact": lux(exact), "bounces": lux(trunc), "seconds": seconds}


def run_case(name: str, args, tools: dict) -> dict:
    import hfrad
    from hfrad.lighting import LightingModel, floor_grid, grid_stats, read_layout, rectangle_grid

    t0 = time.perf_counter()
    if name == "office":
        fac = hfrad.load(args.hfr_office) if args.hfr_office else hfrad.factorize(
            hfrad.load_scene(OFFICE / "office.obj", patches=args.patches), eps=args.eps)
        layout = OFFICE / "layout.json"
        lums = read_layout(layout)
        # the ceiling cells under the six panels are the panels' own faces: Radiance's light polygons
        # (1 cm below them) hide them and return 0 to indirect rays, so they do not reflect here either
        rho = np.array(fac.reflectance)
        rho[fac.scene.material == fac.scene.material_names.index("luminaire")] = 0.0
        fac = fac.with_reflectance(rho)
        background, emit = "none", False
        sensors = floor_grid(fac.scene, 0.8, args.office_spacing, margin=0.5)
    elif name == "room":
        work = Path(tempfile.mkdtemp(prefix="hfrad-room-"))
        obj = _closed_room(work)
        fac = hfrad.factorize(hfrad.load_scene(obj, patches=args.room_patches), eps=args.eps)
        layout = work / "layout.json"
        layout.write_text(json.dumps({"luminaires": [{"name": "downlight", "position": [2.0, 2.79, 1.5],
                                                      "photometry": str(OFFICE / "luminaires" / "downlight-150.ies")}]}))
        lums = read_layout(layout)
        background, emit = "none", False
        sensors = floor_grid(fac.scene, 0.8, 0.5, margin=0.25)
    elif name == "rad":
        fac = hfrad.factorize(hfrad.load_scene(RAD_OFFICE, patches=args.rad_patches), eps=args.eps)
        layout, lums = None, []
        background, emit = "scene", True
        sensors = floor_grid(fac.scene, 0.8, args.office_spacing, material="carpet", margin=0.5)
    else:
        if not CORNELL.is_file():
            raise SystemExit(f"{CORNELL} is missing (the shared scenes folder)")
        fac = hfrad.load(args.hfr_cornell) if args.hfr_cornell else hfrad.factorize(
            hfrad.load_scene(CORNELL, patches=args.patches), eps=args.eps)
        layout, lums = None, []
        background, emit = "scene", True
        sensors = rectangle_grid((-0.95, 0.95), (-0.95, 0.9), 1.4, args.cornell_spacing, name="plane_1.4m")
    if emit:
        # emitting patches become Radiance `light`s, which do not reflect: no reflectance on hfrad's side either
        rho = np.array(fac.reflectance)
        rho[np.asarray(fac.scene.emission).max(axis=1) > 0] = 0.0
        fac = fac.with_reflectance(rho)
    t_fac = time.perf_counter() - t0
    t1 = time.perf_counter()
    model = LightingModel(fac, lums, background=background)
    resp = model.sensors(sensors)
    t_pre = time.perf_counter() - t1
    w = model.dimming
    reps, t2 = 1000, time.perf_counter()
    for _ in range(reps):
        lux_h = resp.illuminance(w)
    t_relight = (time.perf_counter() - t2) / reps
    dense = _dense_check(fac, model, resp, args.ab) if args.dense else None
    with tempfile.TemporaryDirectory(prefix=f"rad-{name}-") as tmp:
        rad = run_radiance(fac.scene, sensors, luminaires=lums, layout=layout, emit=emit, ad=args.ad, ab=args.ab,
                           threads=args.threads, work=Path(tmp), tools=tools, reflectance=fac.reflectance,
                           rad_file=RAD_OFFICE if name == "rad" else None)
    out = {"case": name, "patches": fac.n_patches, "rank": fac.rank, "eps": fac.eps, "sensors": len(sensors),
           "spacing_m": sensors.spacing, "luminaires": len(lums),
           "hfrad": {**grid_stats(lux_h), "factorization_s": t_fac if not (args.hfr_office or args.hfr_cornell) else
                     None, "loaded_s": t_fac, "precompute_s": t_pre, "timings": model.timings,
                     "gather_s": resp.seconds["gather_s"], "relight_s": t_relight},
           "radiance": {**grid_stats(rad["lux"]), **{k: v for k, v in rad.items() if k != "lux"}},
           "compare": compare(lux_h, rad["lux"]),
           "dense": None if dense is None else {
               "form_factors_s": dense["seconds"],
               "hfrad_vs_exact": compare(lux_h, dense["exact"]),
               f"exact_{args.ab}_bounces_vs_radiance": compare(dense["bounces"], rad["lux"]),
               f"exact_vs_exact_{args.ab}_bounces": compare(dense["exact"], dense["bounces"]),
               "exact_average": float(dense["exact"].mean()), "bounces_average": float(dense["bounces"].mean())},
           "lux": {"hfrad": lux_h.tolist(), "radiance": rad["lux"].tolist(),
                   "points": sensors.points.tolist()}}
    if args.rcontrib and lums:
        with tempfile.TemporaryDirectory(prefix=f"rad-{name}-rcontrib-") as tmp:
            rc = run_rcontrib(fac.scene, sensors, lums, layout, ad=args.ad, ab=args.ab, threads=args.threads,
                              work=Path(tmp), tools=tools, reflectance=fac.reflectance)
        rng = np.random.default_rng(0)
        dims = rng.uniform(0, 1, (5, len(lums)))                     # five random dimmings, both ways
        out["rcontrib"] = {"rcontrib_s": rc["rcontrib_s"], "convert_s": rc["convert_s"],
                           "all_on_vs_rtrace": compare(rc["lux"].sum(axis=1), rad["lux"]),
                           "random_dimmings_vs_hfrad": [compare(resp.illuminance(d), rc["lux"] @ d) for d in dims],
                           "options": rc["options"]}
    if args.reflectance:
        rho = np.array(fac.reflectance)
        walls = [i for i, m in enumerate(fac.scene.material_names) if "wall" in m.lower()]
        sel = np.isin(fac.scene.material, walls)
        rho[sel] *= 0.6
        t3 = time.perf_counter()
        model2 = model.with_reflectance(rho)
        lux2 = model2.sensors(sensors, gather=resp.gather).illuminance(w)
        t_h2 = time.perf_counter() - t3
        with tempfile.TemporaryDirectory(prefix=f"rad-{name}-walls-") as tmp:
            rad2 = run_radiance(fac.scene, sensors, reflectance=rho, luminaires=lums, layout=layout, emit=emit, ad=args.ad, ab=args.ab,
                                threads=args.threads, work=Path(tmp), tools=tools)
        out["walls_60pct"] = {"hfrad_s": t_h2, "radiance_s": rad2["convert_s"] + rad2["rtrace_s"],
                              "hfrad_average": float(lux2.mean()), "radiance_average": float(rad2["lux"].mean()),
                              "radiance_noise_rel_rms": rad2["noise_rel_rms"], "compare": compare(lux2, rad2["lux"])}
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--cases", default="office,cornell")
    p.add_argument("--hfr-office", default=None, help="a kept office .hfr (else factorized here)")
    p.add_argument("--hfr-cornell", default=None)
    p.add_argument("--patches", type=int, default=3000)
    p.add_argument("--room-patches", type=int, default=1500)
    p.add_argument("--rad-patches", type=int, default=2000, help="patches of examples/buildings/office.rad (--cases rad)")
    p.add_argument("--eps", type=float, default=0.01)
    p.add_argument("--office-spacing", type=float, default=0.25)
    p.add_argument("--cornell-spacing", type=float, default=0.2)
    p.add_argument("--ad", type=int, default=4096)
    p.add_argument("--ab", type=int, default=8)
    p.add_argument("--threads", type=int, default=len(os.sched_getaffinity(0)))
    p.add_argument("--reflectance", action="store_true", help="also the walls at 60%% reflectance")
    p.add_argument("--dense", action="store_true", help="also the exact dense F: all bounces and --ab bounces")
    p.add_argument("--rcontrib", action="store_true", help="also rcontrib, one modifier per luminaire (any dimming)")
    p.add_argument("--name", default="radiance")
    args = p.parse_args()
    tools = _radiance()
    check_load()
    m = machine()
    print(machine_line(m))
    results = []
    for case in args.cases.split(","):
        r = run_case(case.strip(), args, tools)
        results.append(r)
        print(f"{case}: hfrad avg {r['hfrad']['average']:.1f} lx, Radiance avg {r['radiance']['average']:.1f} lx, "
              f"RMS rel {r['compare']['rms_rel']:.4f}, Radiance noise {r['radiance']['noise_rel_rms']:.4f}",
              flush=True)
        if r["dense"]:
            print(f"  dense F ({r['dense']['form_factors_s']:.1f} s): " + json.dumps(
                {k: v for k, v in r["dense"].items() if k != "form_factors_s"}), flush=True)
    rows = [{"case": r["case"], "patches": r["patches"], "sensors": r["sensors"],
             "hfrad avg lx": r["hfrad"]["average"], "Radiance avg lx": r["radiance"]["average"],
             "hfrad U0": r["hfrad"]["U0"], "Radiance U0": r["radiance"]["U0"],
             "RMS rel": r["compare"]["rms_rel"], "RMS/mean": r["compare"]["rms_over_mean"],
             "Radiance noise": r["radiance"]["noise_rel_rms"],
             "hfrad precompute s": r["hfrad"]["precompute_s"], "hfrad relight ms": 1e3 * r["hfrad"]["relight_s"],
             "Radiance s": r["radiance"]["convert_s"] + r["radiance"]["rtrace_s"]} for r in results]
    cols = list(rows[0].keys())
    print_table(f"hfrad vs Radiance (rtrace -I -ab {args.ab} -ad {args.ad} -aa 0)", rows, cols)
    print(table(rows, cols, markdown=True))
    path = write_json(args.name, {"machine": m, "args": vars(args), "results": results})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
