"""hfrad's daylight year side by side with Radiance's two-phase method (rfluxmtx + gendaymtx + dctimestep).

Radiance's binaries come from the PyPI package ``pyradiance`` (the ``daylight``
extra); gendaymtx runs through its Python API, the others as its bundled
binaries with argument lists (no shell). The same diffuse-only model on both
sides (hfrad y-up, Radiance z-up: hfrad's (x, y, z) is Radiance's (x, -z, y),
so hfrad's north, ``-z``, is Radiance's ``+y``):

- the room of :func:`hfrad.daylight.sidelit_room`, the same triangles: opaque
  faces a Lambertian ``plastic`` (zero specularity, zero roughness), the window
  a ``glass`` whose normal-incidence transmittance is hfrad's (Radiance's
  transmissivity ``tn`` from Radiance's own conversion formula). Radiance's
  ``glass`` is one pane of index 1.52 with Fresnel reflection and absorption
  along the refracted path, the model of hfrad's :func:`angular_factor`, so
  hfrad's angular glazing stays on. Radiance's glass reflects specularly
  (~8%); hfrad's pane reflects its 0.08 diffusely;
- the sky: the same ``.wea`` (pvlib's Greensboro TMY3, mid-hour), Reinhart MF:1,
  ground 0.2; hfrad: gendaymtx ``-s`` and ``-d`` separately plus the direct sun
  along pvlib's sun by one ray per sensor and hour; Radiance (two-phase): the
  daylight coefficients of 145 sky bins and the ground (``rfluxmtx -I+``
  receivers ``h=u`` and ``h=r1``) times gendaymtx's whole matrix (sun spread
  over 4 patches) by ``dctimestep``;
- ASE needs the direct sun alone: on Radiance's side the five-phase direct-sun
  step, 0.533 degree ``light`` suns at the centres of the 5,186 Reinhart MF:6
  patches, ``rcontrib -I+ -ab 0`` binned with ``reinhart.cal`` against a black
  room (glass kept), times ``gendaymtx -5 0.533 -d -m 6``; the same is done for
  hfrad with its own direct-sun rays;
- the sensors: the work plane 0.8 m over the floor at ``--spacing`` (``--margin``
  border), facing up.

Converged Radiance settings for daylight coefficients (rfluxmtx's manual and the
two-phase tutorials: ``-lw`` at most ``1 / -ad``): ``-ab 12 -ad 50000 -lw 2e-5``
(``--ad``, ``--ab`` to change; ``-lw`` follows ``0.5 / ad``). Radiance's noise is
estimated by tracing every sensor twice in one run (``-u+``, ``--noise``; it doubles rfluxmtx's time).

Metrics (hfrad.daylight.daylight_metrics on both results): per-sensor mean
illuminance over the occupied hours, sDA300/50%, ASE1000,250h, mean DA300 and
UDI. Timings: hfrad's precompute (factorization, sky-patch first hits and the
batched solve, sensor coefficients) and year (sky matrices, direct sun,
products) against Radiance's octree + rfluxmtx + gendaymtx + dctimestep (and
the direct-sun step for ASE, reported on its own).

Usage::

    python benchmarks/bench_daylight_radiance.py [--cases office,deep] [--spacing 0.5] [--ad 50000]
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
from bench_radiance import _zup as zup  # noqa: E402  (hfrad's y-up to Radiance's z-up)
from common import check_load, machine, machine_line, print_table, table, write_json  # noqa: E402

RADIANCE_Y = 179.0 * np.array([0.265, 0.670, 0.065])      # Radiance's lux per RGB W/(m^2) (its primaries)
SUN_DIAMETER = 0.533                                     # degrees
#: the rooms: sidelit_room arguments; reflectances and glazing as examples/daylight/make_office.py
CASES = {
    "office": dict(width=4.5, depth=7.0, height=3.0, sill=0.9, head=2.6, margin=0.5),
    "deep": dict(width=6.0, depth=12.0, height=3.0, sill=0.9, head=2.7, margin=0.5),
}
MATERIALS = dict(wall=0.5, floor=0.2, ceiling=0.8, glazing=(0.08, 0.7))


def tools() -> dict:
    try:
        import pyradiance  # noqa: F401  (puts its bundled binaries on PATH, its .cal files on RAYPATH)
    except ImportError as exc:
        raise SystemExit("this benchmark needs Radiance from PyPI: pip install pyradiance") from exc
    found = {n: shutil.which(n) for n in ("oconv", "rfluxmtx", "rcontrib", "dctimestep", "gendaymtx")}
    missing = [n for n, p in found.items() if p is None]
    if missing:
        raise SystemExit(f"pyradiance's binaries are missing: {', '.join(missing)}")
    return found


def glass_transmissivity(tau: float) -> float:
    """Radiance's ``glass`` transmissivity for a normal-incidence transmittance ``tau`` (its reference manual)."""
    return (math.sqrt(0.8402528435 + 0.0072522239 * tau * tau) - 0.9166530661) / 0.0036261119 / tau


def scene_rad(scene, *, black: bool = False) -> str:
    """The scene's triangles as Radiance polygons: opaque ``plastic``, glazing ``glass`` (``black``: opaque 0)."""
    tri = zup(scene.triangles)
    mat = np.asarray(scene.material)[np.asarray(scene.patch_of_triangle)]
    lines = []
    for i, m in enumerate(scene.materials):
        tau = max(m.transmittance)
        if tau > 0:
            tn = glass_transmissivity(tau)
            lines.append(f"void glass m{i} 0 0 3 {tn:.6f} {tn:.6f} {tn:.6f}")
        else:
            r = (0.0, 0.0, 0.0) if black else m.reflectance
            lines.append(f"void plastic m{i} 0 0 5 {r[0]:.6g} {r[1]:.6g} {r[2]:.6g} 0 0")
    for k, (t, m) in enumerate(zip(tri, mat)):
        lines.append(f"m{m} polygon t{k} 0 0 9 " + " ".join(f"{x:.9g}" for x in t.reshape(-1)))
    return "\n".join(lines) + "\n"


SKY_RECEIVER = """#@rfluxmtx h=u u=Y
void glow groundglow 0 0 4 1 1 1 0
groundglow source ground 0 0 4 0 0 -1 180

#@rfluxmtx h=r1 u=Y
void glow skyglow 0 0 4 1 1 1 0
skyglow source skydome 0 0 4 0 0 1 180
"""


def reinhart_centres(mf: int) -> np.ndarray:
    """(p, 3) Radiance z-up unit vectors at the centres of Reinhart MF:mf sky patches (no ground), bin order."""
    alpha = (np.pi / 2) / (7 * mf + 0.5)
    out = []
    for i in range(7 * mf):
        n = (30, 30, 24, 24, 18, 12, 6)[i // mf] * mf
        alt = alpha * (i + 0.5)
        az = 2 * np.pi * np.arange(n) / n              # first patch centred due north (+y), then toward east (+x)
        out.append(np.stack([np.cos(alt) * np.sin(az), np.cos(alt) * np.cos(az), np.full(n, np.sin(alt))], 1))
    out.append(np.array([[0.0, 0.0, 1.0]]))
    return np.vstack(out)


def sun_sources(mf: int = 6) -> str:
    d = reinhart_centres(mf)
    lines = ["void light solar 0 0 3 1e6 1e6 1e6"]
    lines += [f"solar source sun{k} 0 0 4 {x:.7f} {y:.7f} {z:.7f} {SUN_DIAMETER}" for k, (x, y, z) in enumerate(d)]
    return "\n".join(lines) + "\n"


def read_matrix(data: bytes) -> np.ndarray:
    """A Radiance matrix (header, ``FORMAT=float``, 3 components) as (rows, cols, 3) float64."""
    end = data.find(b"\n\n")
    head = data[:end].decode(errors="replace")
    fields = dict(line.strip().split("=", 1) for line in head.splitlines() if "=" in line)
    if fields.get("FORMAT") != "float":
        raise RuntimeError(f"expected a float matrix, got FORMAT={fields.get('FORMAT')}")
    cols = int(fields["NCOLS"])                        # NROWS is absent where the rows came from stdin
    order = ">f4" if fields.get("BigEndian", "0") == "1" else "<f4"
    return np.frombuffer(data[end + 2:], dtype=order).reshape(-1, cols, 3).astype(np.float64)


def run(cmd, *, cwd: Path, data: bytes | None = None, out: Path | None = None) -> bytes:
    """A bundled binary with an argument list (no shell); stdout to ``out`` when given."""
    if out is not None:
        with open(out, "wb") as fh:
            subprocess.run(cmd, cwd=cwd, input=data, stdout=fh, check=True, stderr=subprocess.PIPE)
        return b""
    return subprocess.run(cmd, cwd=cwd, input=data, capture_output=True, check=True).stdout


def sensor_rays(sensors) -> bytes:
    P, N = zup(sensors.points), zup(sensors.normals)
    return "".join(" ".join(f"{v:.9g}" for v in row) + "\n" for row in np.hstack([P, N])).encode()


def radiance_year(scene, sensors, weather, *, ab: int, ad: int, threads: int, work: Path, t: dict, ground: float,
                  repeat: int = 1) -> dict:
    """Two-phase: rfluxmtx daylight coefficients x gendaymtx (sky + spread sun) by dctimestep; plus the
    five-phase direct-sun step for ASE. Returns lux (repeat m, h) of both and the seconds of each step.

    ``repeat``: each sensor traced that many times in the one run (``-u+``: uncorrelated), for the noise."""
    import pyradiance as pr

    times = {}
    t0 = time.perf_counter()
    (work / "room.rad").write_text(scene_rad(scene))
    (work / "black.rad").write_text(scene_rad(scene, black=True))
    (work / "sky.rad").write_text(SKY_RECEIVER)
    (work / "suns.rad").write_text(sun_sources(6))
    (work / "wea.wea").write_text(weather.wea())
    times["convert_s"] = time.perf_counter() - t0
    rays = sensor_rays(sensors) * repeat
    lw = 0.5 / ad
    opts = ["-I+", "-ab", str(ab), "-ad", str(ad), "-lw", f"{lw:.3g}", "-dc", "1", "-dt", "0", "-dj", "0", "-ds", "0.02",
            "-st", "0", "-u+", "-n", str(threads), "-faf"]
    t0 = time.perf_counter()
    run([t["rfluxmtx"], *opts, "-", "sky.rad", "room.rad"], cwd=work, data=rays, out=work / "dc.mtx")
    times["rfluxmtx_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    smx = pr.gendaymtx(weather.wea().encode(), header=True, outform="f", mfactor=1, ground_color=[ground] * 3)
    (work / "sky.smx").write_bytes(smx)
    times["gendaymtx_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    ill = read_matrix(run([t["dctimestep"], "-of", "dc.mtx", "sky.smx"], cwd=work))
    times["dctimestep_s"] = time.perf_counter() - t0
    lux = (ill @ RADIANCE_Y).astype(np.float32)                      # (m, h)
    # the direct-only coefficients (black room, -ab 1) of the same sky bins: the five-phase total below
    t0 = time.perf_counter()
    dopts = [*opts[:2], "1", *opts[3:]]
    dd = read_matrix(run([t["rfluxmtx"], *dopts, "-", "sky.rad", "black.rad"], cwd=work, data=rays))
    times["direct_coefficients_s"] = time.perf_counter() - t0
    # five-phase direct sun (ASE): suns at MF:6 patch centres, a black room, -ab 0
    t0 = time.perf_counter()
    run([t["oconv"], "black.rad", "suns.rad"], cwd=work, out=work / "suns.oct")
    sopts = ["-I+", "-ab", "0", "-dc", "1", "-dt", "0", "-dj", "0", "-st", "0", "-lw", "1e-9", "-n", str(threads), "-faf",
             "-e", "MF:6", "-f", "reinhart.cal", "-b", "rbin", "-bn", "Nrbins", "-m", "solar", "suns.oct"]
    run([t["rcontrib"], *sopts], cwd=work, data=rays, out=work / "sun.mtx")
    times["sun_coefficients_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    run([t["gendaymtx"], "-5", f"{SUN_DIAMETER}", "-d", "-m", "6", "-of", "-g", *(f"{ground}",) * 3, "wea.wea"],
        cwd=work, out=work / "sun.smx")
    sun = read_matrix(run([t["dctimestep"], "-of", "sun.mtx", "sun.smx"], cwd=work))
    times["sun_year_s"] = time.perf_counter() - t0
    direct_sun = (sun @ RADIANCE_Y).astype(np.float32)
    # five-phase total: the two-phase year less the spread sun's direct part, plus the sun coefficients' year;
    # gendaymtx -d writes the whole ground glow too: dropped, so that the ground's direct view stays
    d_sun = read_matrix(pr.gendaymtx(weather.wea().encode(), header=True, outform="f", mfactor=1, sun_only=True,
                                     ground_color=[ground] * 3)).transpose(0, 2, 1).copy()     # (146, 3, h)
    d_sun[0] = 0.0
    spread = np.einsum("mpc,pch->mh", dd * RADIANCE_Y, d_sun)
    five = (lux - spread + direct_sun).astype(np.float32)
    return {"lux": lux, "lux_five_phase": five, "direct_sun": direct_sun, "timings": times,
            "options": " ".join(opts), "sun_options": " ".join(sopts)}


def hfrad_year(scene, sensors, weather, *, eps: float, ground: float) -> dict:
    import hfrad
    from hfrad.daylight import DaylightModel
    from hfrad.daylight.sky import sky_matrices

    from hfrad.daylight import sidelit_room

    hfrad.factorize(sidelit_room(max_edge=3.0), eps=eps)          # numba's compilation, not timed
    times = {}
    t0 = time.perf_counter()
    fac = hfrad.factorize(scene, eps=eps)
    times["factorize_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    model = DaylightModel(fac)
    times["sky_patches_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    dc = model.sensors(sensors)
    times["sensor_coefficients_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    matrices = sky_matrices(weather, 1, ground=ground)
    res = model.year(sensors, weather, coefficients=dc, matrices=matrices)
    times["year_s"] = time.perf_counter() - t0
    times.update({f"year_{k}": v for k, v in res.timings.items()})
    times["precompute_s"] = times["factorize_s"] + times["sky_patches_s"] + times["sensor_coefficients_s"]
    sky, sun = matrices
    two = dc.illuminance(sky + sun)          # the two-phase year: the sun spread over patches, no sun rays
    return {"lux": res.illuminance, "lux_two_phase": two, "direct_sun": res.direct_sun, "timings": times,
            "tracer": model.tracer,
            "patches": fac.n_patches,
            "rank": fac.rank}


def summary(lux, sun, hour) -> dict:
    from hfrad.daylight import daylight_metrics

    m = daylight_metrics(lux, sun, hour)
    return {"sDA": m["sDA"], "ASE": m["ASE"], "mean_DA": float(m["DA"].mean()),
            "mean_UDI_useful": float(m["UDI_useful"].mean()), "mean_lux": m["mean_lux"], "DA": m["DA"],
            "sun_hours": m["sun_hours"]}


def weather_occupied(hour):
    from hfrad.daylight import occupied_hours

    return occupied_hours(hour)


def compare(h: dict, r: dict) -> dict:
    """Per-sensor mean illuminance over the occupied hours (relative to Radiance), sDA and ASE (points)."""
    rel = h["mean_lux"] / r["mean_lux"] - 1
    return {"mean_lux_rel_max_abs": float(np.abs(rel).max()), "mean_lux_rel_rms": float(np.sqrt(np.mean(rel ** 2))),
            "mean_lux_rel_mean": float(rel.mean()), "worst_sensor": int(np.argmax(np.abs(rel))),
            "within_5pct": float((np.abs(rel) <= 0.05).mean()),
            "grid_mean_rel": float(h["mean_lux"].mean() / r["mean_lux"].mean() - 1),
            "sDA_pp": 100 * (h["sDA"] - r["sDA"]), "ASE_pp": 100 * (h["ASE"] - r["ASE"])}


def sun_on_radiance_suns(tracer, sensors, weather, work: Path, t: dict, ground: float) -> np.ndarray:
    """(m, h) lux: hfrad's direct sun by its own rays, but along Radiance's five-phase suns (the centres of
    the MF:6 patches, gendaymtx's sun positions and ``-5`` matrix): separates the sun's position from the
    ray tracing and the glazing in an ASE difference."""
    (work / "wea.wea").write_text(weather.wea())
    run([t["gendaymtx"], "-5", f"{SUN_DIAMETER}", "-d", "-m", "6", "-of", "-g", *(f"{ground}",) * 3, "wea.wea"],
        cwd=work, out=work / "sun.smx")
    data = (work / "sun.smx").read_bytes()
    end = data.find(b"\n\n")
    cols = int(dict(x.split("=", 1) for x in data[:end].decode().splitlines() if "=" in x)["NCOLS"])
    lum = np.frombuffer(data[end + 2:], "<f4").reshape(-1, cols, 3) @ RADIANCE_Y.astype(np.float32)  # (5186, h)
    d = reinhart_centres(6)                                                    # Radiance z-up
    d = np.stack([d[:, 0], d[:, 2], -d[:, 1]], axis=1)                        # hfrad y-up
    cos = sensors.normals @ d.T                                               # (m, 5185)
    qi, pi = np.nonzero(cos > 0)
    T = tracer.transmittance(sensors.points[qi], d[pi]).max(axis=1)          # grey glass
    C = np.zeros(cos.shape)
    C[qi, pi] = cos[qi, pi] * T * 2 * np.pi * (1 - np.cos(np.radians(SUN_DIAMETER / 2)))
    return (C @ lum[1:]).astype(np.float32)


def radiance_side(scene, sensors, weather, args, t):
    """Radiance's year (two-phase and five-phase totals, direct sun) summarised like hfrad's."""
    repeat = 2 if args.noise else 1
    with tempfile.TemporaryDirectory(prefix="dl-radiance-") as tmp:
        r = radiance_year(scene, sensors, weather, ab=args.ab, ad=args.ad, threads=args.threads, work=Path(tmp), t=t,
                          ground=args.ground, repeat=repeat)
    tr = r["timings"]
    print(f"  Radiance: rfluxmtx {tr['rfluxmtx_s']:.1f} s (x{repeat} sensors), direct sun {tr['sun_coefficients_s']:.1f} s",
          flush=True)
    m, hour = len(sensors), weather.hour
    second = r["lux"][m:]
    for k in ("lux", "lux_five_phase", "direct_sun"):
        r[k] = r[k][:m]
    rs = summary(r["lux_five_phase"], r["direct_sun"], hour)
    r2 = summary(r["lux"], r["direct_sun"], hour)
    info = {"timings": r["timings"], "options": r["options"], "sun_options": r["sun_options"],
            "two_phase_mean_lux": r2["mean_lux"], "two_phase_sDA": r2["sDA"]}
    if repeat == 2:
        m2 = second[:, weather_occupied(hour)].mean(axis=1)
        d = (r2["mean_lux"] - m2) / (0.5 * (r2["mean_lux"] + m2))
        info["noise_mean_lux_rel_rms"] = float(np.sqrt(np.mean(d ** 2)) / math.sqrt(2))
    return rs, r2, info


def _reuse(path, name, sensors):
    """Radiance's summary of case ``name`` from an earlier run's JSON (the same sensors), or None."""
    if not path:
        return None
    for r in json.loads(Path(path).read_text())["results"]:
        if r["case"] == name and np.allclose(r["points"], sensors.points):
            R = dict(r["radiance"])
            rs = {k: np.asarray(R.pop(k)) if k in ("mean_lux", "DA", "sun_hours") else R.pop(k)
                  for k in ("sDA", "ASE", "mean_DA", "mean_UDI_useful", "mean_lux", "DA", "sun_hours")}
            two = r["two_phase"]
            r2 = {"mean_lux": np.asarray(two["radiance_mean_lux"]), "sDA": two["radiance_sDA"], "ASE": rs["ASE"]}
            R.update({"two_phase_mean_lux": r2["mean_lux"], "two_phase_sDA": r2["sDA"], "reused_from": str(path)})
            return rs, r2, R
    return None


def run_case(name: str, args, t: dict, weather) -> dict:
    from hfrad.daylight import sidelit_room
    from hfrad.lighting import floor_grid

    scene = sidelit_room(**CASES[name], wall=MATERIALS["wall"], floor=MATERIALS["floor"],
                         ceiling=MATERIALS["ceiling"], glazing=MATERIALS["glazing"], max_edge=args.max_edge)
    sensors = floor_grid(scene, 0.8, args.spacing, margin=args.margin)
    print(f"{name}: {scene.n_patches} patches, {len(sensors)} sensors", flush=True)
    h = hfrad_year(scene, sensors, weather, eps=args.eps, ground=args.ground)
    print(f"  hfrad: precompute {h['timings']['precompute_s']:.1f} s, year {h['timings']['year_s']:.1f} s", flush=True)
    hour = weather.hour
    reused = _reuse(args.radiance_json, name, sensors)
    if reused is None:
        rs, r2, rinfo = radiance_side(scene, sensors, weather, args, t)
    else:
        rs, r2, rinfo = reused
        print(f"  Radiance: reused from {args.radiance_json}", flush=True)
    hs, h2 = summary(h["lux"], h["direct_sun"], hour), summary(h["lux_two_phase"], h["direct_sun"], hour)
    with tempfile.TemporaryDirectory(prefix="dl-suns-") as tmp:
        h5 = summary(h["lux"], sun_on_radiance_suns(h["tracer"], sensors, weather, Path(tmp), t, args.ground), hour)
    out = {"case": name, "room": CASES[name], "materials": MATERIALS, "patches": h["patches"], "rank": h["rank"],
           "sensors": len(sensors), "spacing_m": args.spacing,
           "hfrad": {**hs, "timings": h["timings"]},
           "radiance": {**rs, **rinfo},
           "compare": compare(hs, rs),
           "two_phase": {"hfrad_mean_lux": h2["mean_lux"], "radiance_mean_lux": r2["mean_lux"],
                         "hfrad_sDA": h2["sDA"], "radiance_sDA": r2["sDA"], "compare": compare(h2, r2)},
           "sun_hours_rel": float(hs["sun_hours"].sum() / max(rs["sun_hours"].sum(), 1) - 1),
           "hfrad_on_radiance_suns": {"ASE": h5["ASE"], "sun_hours": h5["sun_hours"],
                                      "ASE_pp": 100 * (h5["ASE"] - rs["ASE"]),
                                      "sun_hours_rel": float(h5["sun_hours"].sum() / max(rs["sun_hours"].sum(), 1) - 1)},
           "points": sensors.points}
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--cases", default="office,deep")
    p.add_argument("--spacing", type=float, default=0.5)
    p.add_argument("--margin", type=float, default=0.25)
    p.add_argument("--max-edge", type=float, default=0.5, help="hfrad patch size, m")
    p.add_argument("--eps", type=float, default=0.01)
    p.add_argument("--ground", type=float, default=0.2)
    p.add_argument("--ab", type=int, default=12)
    p.add_argument("--ad", type=int, default=50000)
    p.add_argument("--threads", type=int, default=len(os.sched_getaffinity(0)))
    p.add_argument("--noise", action="store_true", help="trace each sensor twice in Radiance (-u+) for its noise")
    p.add_argument("--radiance-json", default=None,
                   help="reuse Radiance's results of the same case and sensors from an earlier run's JSON")
    p.add_argument("--weather", default=None, help="TMY3/EPW (default: pvlib's Greensboro TMY3)")
    p.add_argument("--name", default="daylight-radiance")
    args = p.parse_args()
    t = tools()
    import pvlib

    from hfrad.daylight import read_weather

    weather = read_weather(args.weather or Path(pvlib.__file__).parent / "data" / "723170TYA.CSV")
    check_load()
    m = machine()
    print(machine_line(m))
    results = [run_case(c.strip(), args, t, weather) for c in args.cases.split(",")]
    rows = []
    for r in results:
        H, R, C, T = r["hfrad"], r["radiance"], r["compare"], r["two_phase"]
        rt = R["timings"]
        rows.append({"case": r["case"], "sensors": r["sensors"], "patches": r["patches"],
                     "mean lx hfrad": float(H["mean_lux"].mean()), "mean lx Radiance": float(R["mean_lux"].mean()),
                     "sensor max |rel|": C["mean_lux_rel_max_abs"], "sensor RMS rel": C["mean_lux_rel_rms"],
                     "2-phase max |rel|": T["compare"]["mean_lux_rel_max_abs"],
                     "2-phase RMS rel": T["compare"]["mean_lux_rel_rms"],
                     "sDA hfrad %": 100 * H["sDA"], "sDA Radiance %": 100 * R["sDA"],
                     "ASE hfrad %": 100 * H["ASE"], "ASE Radiance %": 100 * R["ASE"],
                     "ASE hfrad, Radiance's suns %": 100 * r["hfrad_on_radiance_suns"]["ASE"],
                     "hfrad precompute s": H["timings"]["precompute_s"], "hfrad year s": H["timings"]["year_s"],
                     "Radiance 2-phase s": rt["convert_s"] + rt["rfluxmtx_s"] + rt["gendaymtx_s"] + rt["dctimestep_s"],
                     "Radiance 5-phase extra s": rt["direct_coefficients_s"] + rt["sun_coefficients_s"]
                     + rt["sun_year_s"]})
    cols = list(rows[0].keys())
    print_table(f"hfrad vs Radiance two-phase (rfluxmtx -ab {args.ab} -ad {args.ad}), Greensboro TMY3", rows, cols)
    print(table(rows, cols, markdown=True))
    path = write_json(args.name, {"machine": m, "args": vars(args), "results": results, "table": rows})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
