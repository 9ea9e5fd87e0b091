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
- the direct sun (ASE counts it alone; the totals replace the spread sun's direct part by it, the
  five-phase method's step: two-phase year, less the direct-only coefficients of ``rfluxmtx -ab 1`` in a
  black room times gendaymtx's spread sun, plus the direct sun), with three sun models on Radiance's side,
  each ``rcontrib -I+ -ab 0`` against the black room (glass kept):

  ``hour`` (the reference): one 0.533 degree ``light`` sun per sun-up hour at Radiance's own position and
  radiance, ``gendaymtx -D suns.rad -M suns.mod`` (its time-step suns), each its own modifier, ``-V+``;
  ``spa``: the same with the sun along pvlib's SPA position, hfrad's sun (separates the sun's position
  from the transport: like for like); ``mf6``: the five-phase suns at the centres of the 5,186 Reinhart
  MF:6 patches (``reinhart.cal``) times ``gendaymtx -5 0.533 -d -m 6`` (the product in numpy), where
  gendaymtx moves each hour's sun to the nearest patch centre. hfrad's rays are also sent along Radiance's
  ``hour`` and ``mf6`` suns. Radiance's sun position (sun.c: a one-sine declination per day, a two-sine
  equation of time, no refraction) is compared with SPA hour by hour;
- ``two_phase``: both sides with the sun spread over 4 MF:1 patches (ASE from that spread sun's direct part);
- the sensors: the work plane 0.8 m over the floor at ``--spacing`` (``--margin``
  border), facing up.

Converged Radiance settings for daylight coefficients (rfluxmtx's manual and the
two-phase tutorials: ``-lw`` at most ``1 / -ad``): ``-ab 12 -ad 50000 -lw 1e-5``
(``--ad``, ``--ab`` to change; ``-lw`` follows ``0.5 / ad``). Radiance's noise is
estimated by tracing every sensor twice in one run (``-u+``, ``--noise``; it doubles rfluxmtx's time).
``--radiance-cache DIR`` keeps rfluxmtx's matrices (keyed by the options, scene and rays) for a rerun;
``--radiance-json`` takes Radiance's summaries from an earlier run's JSON.

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
import hashlib
import json
import math
import os
import re
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


def read_matrix(data: bytes, dtype=np.float64) -> np.ndarray:
    """A Radiance matrix (header, ``FORMAT=float``, 3 components) as (rows, cols, 3) ``dtype``."""
    end = data.find(b"\n\n")
    head = data[:end].decode(errors="replace")
    fields = dict(line.strip().split("=", 1) for line in head.splitlines() if "=" in line)
    if fields.get("FORMAT") != "float":
        raise RuntimeError(f"expected a float matrix, got FORMAT={fields.get('FORMAT')}")
    cols = int(fields["NCOLS"])                        # NROWS is absent where the rows came from stdin
    order = ">f4" if fields.get("BigEndian", "0") == "1" else "<f4"
    return np.frombuffer(data[end + 2:], dtype=order).reshape(-1, cols, 3).astype(dtype)


def run(cmd, *, cwd: Path, data: bytes | None = None, out: Path | None = None) -> bytes:
    """A bundled binary with an argument list (no shell); stdout to ``out`` when given."""
    if out is not None:
        with open(out, "wb") as fh:
            subprocess.run(cmd, cwd=cwd, input=data, stdout=fh, check=True, stderr=subprocess.PIPE)
        return b""
    return subprocess.run(cmd, cwd=cwd, input=data, capture_output=True, check=True).stdout


def cached_run(cmd, *, cwd: Path, out: Path, data: bytes | None = None, inputs=(), cache: Path | None = None) -> float:
    """:func:`run` to ``out``, reused from ``cache`` when the same command ran on the same inputs and rays.

    The key is a hash of the argument list, the input files' contents and the rays, so a changed scene,
    sensor grid or option traces again. Returns the run's wall seconds (a cached result: those measured when
    it was made, kept beside it; NaN if not kept)."""
    key = hashlib.sha256("\0".join(map(str, cmd[1:])).encode())
    for f in inputs:
        key.update((cwd / f).read_bytes())
    key.update(data or b"")
    hit = cache / f"{key.hexdigest()[:24]}.mtx" if cache is not None else None
    if hit is not None and hit.is_file():
        shutil.copyfile(hit, out)
        seconds = hit.with_suffix(".seconds")
        return float(seconds.read_text()) if seconds.is_file() else float("nan")
    t0 = time.perf_counter()
    run(cmd, cwd=cwd, data=data, out=out)
    elapsed = time.perf_counter() - t0
    if hit is not None:
        hit.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(out, hit.with_suffix(".tmp"))
        hit.with_suffix(".seconds").write_text(f"{elapsed:.3f}\n")
        os.replace(hit.with_suffix(".tmp"), hit)
    return elapsed


def sensor_rays(sensors, index=slice(None)) -> bytes:
    P, N = zup(sensors.points[index]), zup(sensors.normals[index])
    return "".join(" ".join(f"{v:.9g}" for v in row) + "\n" for row in np.hstack([P, N])).encode()


def rflux_options(ab: int, ad: int, threads: int) -> list:
    """rfluxmtx's options for the daylight coefficients (``-lw`` 0.5 / ``ad``, uncorrelated sampling)."""
    return ["-I+", "-ab", str(ab), "-ad", str(ad), "-lw", f"{0.5 / ad:.3g}", "-dc", "1", "-dt", "0", "-dj", "0",
            "-ds", "0.02", "-st", "0", "-u+", "-n", str(threads), "-faf"]


def radiance_year(scene, sensors, weather, *, ab: int, ad: int, threads: int, work: Path, t: dict, ground: float,
                  repeat: int = 1, cache: Path | None = None) -> dict:
    """Two-phase: rfluxmtx daylight coefficients x gendaymtx (sky + spread sun) by dctimestep; the direct sun
    by the three sun models of the module's docstring. Returns lux (repeat m, h): ``lux`` (two-phase),
    ``totals`` and ``direct`` of each sun model, ``spread_direct`` (two-phase's direct sun), the seconds of
    each step. rfluxmtx's matrices are kept in (and taken from) ``cache`` when given.

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
    opts = rflux_options(ab, ad, threads)
    times["rfluxmtx_s"] = cached_run([t["rfluxmtx"], *opts, "-", "sky.rad", "room.rad"], cwd=work, data=rays,
                                     out=work / "dc.mtx", inputs=("sky.rad", "room.rad"), cache=cache)
    t0 = time.perf_counter()
    smx = pr.gendaymtx(weather.wea().encode(), header=True, outform="f", mfactor=1, ground_color=[ground] * 3)
    (work / "sky.smx").write_bytes(smx)
    times["gendaymtx_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    ill = read_matrix(run([t["dctimestep"], "-of", "dc.mtx", "sky.smx"], cwd=work))
    times["dctimestep_s"] = time.perf_counter() - t0
    lux = (ill @ RADIANCE_Y).astype(np.float32)                      # (m, h)
    # the direct-only coefficients (black room, -ab 1) of the same sky bins: the five-phase total below
    dopts = [*opts[:2], "1", *opts[3:]]
    times["direct_coefficients_s"] = cached_run([t["rfluxmtx"], *dopts, "-", "sky.rad", "black.rad"], cwd=work,
                                                data=rays, out=work / "dd.mtx", inputs=("sky.rad", "black.rad"),
                                                cache=cache)
    dd = read_matrix((work / "dd.mtx").read_bytes())
    # five-phase direct sun: suns at the MF:6 patch centres, a black room, -ab 0; the year's product in numpy
    # (dctimestep took 280-330 s on this 5,186 x 8,760 matrix, numpy a few seconds: the same sums)
    t0 = time.perf_counter()
    run([t["oconv"], "black.rad", "suns.rad"], cwd=work, out=work / "suns.oct")
    sopts = ["-I+", "-ab", "0", "-dc", "1", "-dt", "0", "-dj", "0", "-st", "0", "-lw", "1e-9", "-n", str(threads), "-faf",
             "-e", "MF:6", "-f", "reinhart.cal", "-b", "rbin", "-bn", "Nrbins", "-m", "solar", "suns.oct"]
    run([t["rcontrib"], *sopts], cwd=work, data=rays, out=work / "sun.mtx")
    times["sun_coefficients_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    run([t["gendaymtx"], "-5", f"{SUN_DIAMETER}", "-d", "-m", "6", "-of", "-g", *(f"{ground}",) * 3, "wea.wea"],
        cwd=work, out=work / "sun.smx")
    C = read_matrix((work / "sun.mtx").read_bytes(), np.float32)                      # (m, 5186, 3)
    S = read_matrix((work / "sun.smx").read_bytes(), np.float32)                      # (5186, h, 3)
    sun_mf6 = sum(RADIANCE_Y[c] * (C[:, :, c] @ S[:, :, c]) for c in range(3)).astype(np.float32)
    del C, S
    times["sun_year_s"] = time.perf_counter() - t0
    # one sun per hour at Radiance's own position (gendaymtx -D: the time-step suns of its manual, 0.533 degree
    # ``light`` sources of the hour's direct radiance), each its own modifier; rcontrib -V+ gives contributions
    t0 = time.perf_counter()
    run([t["gendaymtx"], "-D", "hour_suns.rad", "-M", "hour_suns.mod", "-n", "-d", "wea.wea"], cwd=work)
    hs = parse_suns((work / "hour_suns.rad").read_text(), weather)
    sun_hour = sun_year(work, t, rays, "hour_suns.rad", "hour_suns.mod", hs["hour"], len(weather.hour), threads)
    times["hour_suns_s"] = time.perf_counter() - t0
    # the same transport along pvlib's (SPA) suns, hfrad's: separates the sun's position from the tracing
    d_sun = read_matrix(pr.gendaymtx(weather.wea().encode(), header=True, outform="f", mfactor=1, sun_only=True,
                                     ground_color=[ground] * 3)).transpose(0, 2, 1).copy()     # (146, 3, h)
    d_sun[0] = 0.0      # gendaymtx -d writes the whole ground glow too: dropped (the two-phase year has it)
    spa = spa_suns(weather, d_sun)
    (work / "spa_suns.rad").write_text(spa["rad"])
    (work / "spa_suns.mod").write_text(spa["mod"])
    sun_spa = sun_year(work, t, rays, "spa_suns.rad", "spa_suns.mod", spa["hour"], len(weather.hour), threads)
    # five-phase-style totals: the two-phase year less the spread sun's direct part, plus the direct sun
    spread = np.einsum("mpc,pch->mh", dd * RADIANCE_Y, d_sun)
    base = lux - spread
    totals = {k: (base + v).astype(np.float32) for k, v in (("hour", sun_hour), ("mf6", sun_mf6), ("spa", sun_spa))}
    return {"lux": lux, "totals": totals, "direct": {"hour": sun_hour, "mf6": sun_mf6, "spa": sun_spa},
            "spread_direct": spread.astype(np.float32),
            "hour_suns": hs, "timings": times, "options": " ".join(opts), "sun_options": " ".join(sopts)}


def parse_suns(text: str, weather) -> dict:
    """gendaymtx ``-D`` suns: hour index (s,), direction (s, 3) z-up, radiance (s, 3) W/(sr m^2).

    Each sun is named by gendaymtx's solar minute, ``1440 (julian day - 1) + round(60 hour)``."""
    found = re.findall(r"void light solar(\d+)\s+0\s+0\s+3 (\S+) (\S+) (\S+)\s+solar\d+ source sun\d+\s+0\s+0\s+"
                       r"4 (\S+) (\S+) (\S+) \S+", text)
    minute = 1440 * weather.day_of_year + np.floor(weather.hour * 60 + 0.5).astype(int)
    index = {int(m): i for i, m in enumerate(minute)}
    vals = np.array([[float(v) for v in f[1:]] for f in found])
    return {"hour": np.array([index[int(f[0])] for f in found]), "radiance": vals[:, :3], "direction": vals[:, 3:]}


def spa_suns(weather, d_sun) -> dict:
    """Radiance ``light`` suns along pvlib's (SPA) sun of each hour with hfrad's direct-normal irradiance.

    The hours and magnitudes of :meth:`DaylightModel.direct_sun`: altitude above 0, the sun matrix's
    per-hour sum ``sum_p sun_p Omega_p`` (``d_sun`` (146, 3, h), MF:1)."""
    from hfrad.daylight.sky import direction, sky_patches

    normal = np.einsum("pch,p->hc", d_sun, sky_patches(1).solid_angle)                    # (h, 3)
    alt, azi = weather.sun()
    hours = np.flatnonzero((alt > 0) & (normal.max(axis=1) > 0))
    d = zup(direction(np.radians(alt[hours]), np.radians(azi[hours])))
    radiance = normal[hours] / (np.pi * np.radians(SUN_DIAMETER / 2) ** 2)              # gendaymtx's disc
    rad = [f"void light spa{h}\n0\n0\n3 {r[0]:.6e} {r[1]:.6e} {r[2]:.6e}\n"
           f"spa{h} source sun{h}\n0\n0\n4 {v[0]:.7f} {v[1]:.7f} {v[2]:.7f} {SUN_DIAMETER}\n"
           for h, r, v in zip(hours, radiance, d)]
    return {"hour": hours, "rad": "\n".join(rad), "mod": "".join(f"spa{h}\n" for h in hours)}


def sun_year(work: Path, t: dict, rays: bytes, suns: str, mods: str, hour: np.ndarray, n_hours: int,
             threads: int) -> np.ndarray:
    """(m, h) lux: rcontrib ``-ab 0 -V+`` in the black room (glass kept), one modifier per hour's sun."""
    run([t["oconv"], "black.rad", suns], cwd=work, out=work / "hsun.oct")
    run([t["rcontrib"], "-I+", "-ab", "0", "-dc", "1", "-dt", "0", "-dj", "0", "-st", "0", "-lw", "1e-9", "-V+",
         "-n", str(threads), "-faf", "-M", mods, "hsun.oct"], cwd=work, data=rays, out=work / "hsun.mtx")
    E = read_matrix((work / "hsun.mtx").read_bytes(), np.float32) @ RADIANCE_Y.astype(np.float32)   # (m, s)
    out = np.zeros((E.shape[0], n_hours), np.float32)
    out[:, hour] = E
    return out


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
    spread = np.einsum("mcp,pch->mh", dc.direct * RADIANCE_Y[None, :, None], sun)   # its direct part
    return {"lux": res.illuminance, "lux_two_phase": two, "direct_sun": res.direct_sun, "timings": times,
            "spread_direct": spread.astype(np.float32),
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


def hfrad_along(tracer, sensors, direction: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """(m, s) lux: hfrad's direct-sun rays along Radiance z-up ``direction`` (s, 3), direct-normal illuminance
    ``normal`` (s,) lux: one ray per sensor and sun through hfrad's glazing, as DaylightModel.direct_sun."""
    d = np.stack([direction[:, 0], direction[:, 2], -direction[:, 1]], axis=1)           # hfrad y-up
    cos = sensors.normals @ d.T                                                          # (m, s)
    qi, pi = np.nonzero(cos > 0)
    T = tracer.transmittance(sensors.points[qi], d[pi]).max(axis=1)                     # grey glass
    C = np.zeros(cos.shape)
    C[qi, pi] = cos[qi, pi] * T
    return (C * normal).astype(np.float32)


def hfrad_on_radiance_suns(tracer, sensors, weather, work: Path, t: dict, ground: float) -> dict:
    """(m, h) lux of hfrad's direct-sun rays along Radiance's suns: ``hour`` gendaymtx ``-D``'s sun of each
    hour, ``mf6`` the five-phase suns (MF:6 patch centres and gendaymtx ``-5``'s matrix). With Radiance's
    totals on the same suns, separates the sun's position from the ray tracing and the glazing."""
    (work / "wea.wea").write_text(weather.wea())
    disc = np.pi * np.radians(SUN_DIAMETER / 2) ** 2
    run([t["gendaymtx"], "-D", "hour_suns.rad", "-M", "hour_suns.mod", "-n", "-d", "wea.wea"], cwd=work)
    hs = parse_suns((work / "hour_suns.rad").read_text(), weather)
    hour = np.zeros((len(sensors), len(weather.hour)), np.float32)
    hour[:, hs["hour"]] = hfrad_along(tracer, sensors, hs["direction"], disc * hs["radiance"] @ RADIANCE_Y)
    run([t["gendaymtx"], "-5", f"{SUN_DIAMETER}", "-d", "-m", "6", "-of", "-g", *(f"{ground}",) * 3, "wea.wea"],
        cwd=work, out=work / "sun.smx")
    lum = read_matrix((work / "sun.smx").read_bytes(), np.float32) @ RADIANCE_Y.astype(np.float32)   # (5186, h)
    C = hfrad_along(tracer, sensors, reinhart_centres(6), np.full(5185, 2 * np.pi * (1 - np.cos(np.radians(
        SUN_DIAMETER / 2)))))
    return {"hour": hour, "mf6": (C @ lum[1:]).astype(np.float32), "hour_suns": hs}


def sun_positions(weather, hs: dict) -> dict:
    """Radiance's sun of each hour (gendaymtx, Radiance's sun.c) against pvlib's SPA sun: the angle between
    them, degrees, and its parts: altitude, declination (Radiance's one-sine formula against Spencer's series,
    per day), equation of time (minutes) and refraction (SPA's apparent minus true altitude)."""
    import pandas as pd
    import pvlib

    h = hs["hour"]
    lit = hs["radiance"].max(axis=1) > 0
    alt, azi = weather.sun()
    a, z = np.radians(alt[h]), np.radians(azi[h])
    p = np.stack([np.cos(a) * np.sin(z), np.cos(a) * np.cos(z), np.sin(a)], axis=1)
    ang = np.degrees(np.arccos(np.clip((p * hs["direction"]).sum(axis=1), -1, 1)))[lit]
    ralt = np.degrees(np.arcsin(hs["direction"][:, 2]))
    dalt = (alt[h] - ralt)[lit]
    jd = weather.day_of_year[h][lit] + 1
    dec_rad = np.degrees(0.4093 * np.sin(2 * np.pi / 368 * (jd - 81)))
    dec_ref = np.degrees(pvlib.solarposition.declination_spencer71(jd))
    eot_rad = 60 * (0.170 * np.sin(4 * np.pi / 373 * (jd - 80)) - 0.129 * np.sin(2 * np.pi / 355 * (jd - 8)))
    eot_ref = pvlib.solarposition.equation_of_time_spencer71(jd)
    minutes = np.round(weather.hour[h][lit] * 60).astype(int)
    times = (pd.to_datetime({"year": np.full(len(minutes), 2001), "month": weather.month[h][lit],
                             "day": weather.day[h][lit]}) + pd.to_timedelta(minutes, unit="min"))
    tz = pd.Timedelta(hours=weather.timezone)
    pos = pvlib.solarposition.get_solarposition(pd.DatetimeIndex(times - tz).tz_localize("UTC"), weather.latitude,
                                                weather.longitude, altitude=weather.elevation)
    refr = np.asarray(pos["apparent_elevation"] - pos["elevation"])
    bands = {}
    for lo, hi in ((0, 10), (10, 30), (30, 90)):
        k = (ralt[lit] >= lo) & (ralt[lit] < hi)
        bands[f"{lo}-{hi}"] = {"hours": int(k.sum()), "angle_mean_deg": float(ang[k].mean()),
                               "altitude_diff_mean_deg": float(dalt[k].mean())}
    return {"sunlit_hours": int(lit.sum()), "angle_mean_deg": float(ang.mean()),
            "angle_p95_deg": float(np.percentile(ang, 95)), "angle_max_deg": float(ang.max()),
            "altitude_diff_mean_deg": float(dalt.mean()), "altitude_diff_max_deg": float(np.abs(dalt).max()),
            "declination_diff_max_deg": float(np.abs(dec_ref - dec_rad).max()),
            "declination_diff_mean_deg": float((dec_ref - dec_rad).mean()),
            "equation_of_time_diff_max_min": float(np.abs(eot_ref - eot_rad).max()),
            "refraction_mean_deg": float(refr.mean()), "by_altitude": bands}


def radiance_noise(scene, sensors, index, weather, args, t) -> dict:
    """Radiance's scatter at sensors ``index``: rfluxmtx (two-phase settings) traces each ``args.noise_repeats``
    times in one run (``-u+``: uncorrelated); the annual mean over the occupied hours of each trace.

    Returns each sensor's mean of the traces (lux) and the traces' relative standard deviation."""
    import pyradiance as pr

    rays, opts = sensor_rays(sensors, index), rflux_options(args.ab, args.ad, args.threads)
    with tempfile.TemporaryDirectory(prefix="dl-noise-") as tmp:
        work = Path(tmp)
        (work / "room.rad").write_text(scene_rad(scene))
        (work / "sky.rad").write_text(SKY_RECEIVER)
        t0 = time.perf_counter()
        run([t["rfluxmtx"], *opts, "-", "sky.rad", "room.rad"], cwd=work, data=rays * args.noise_repeats,
            out=work / "dc.mtx")
        seconds = time.perf_counter() - t0
        dc = read_matrix((work / "dc.mtx").read_bytes())                                     # (k r, 146, 3)
    smx = read_matrix(pr.gendaymtx(weather.wea().encode(), header=True, outform="f", mfactor=1,
                                   ground_color=[args.ground] * 3))                         # (146, h, 3)
    occ = weather_occupied(weather.hour)
    mean_sky = smx[:, occ].mean(axis=1)                                                     # (146, 3)
    means = np.einsum("rpc,pc->r", dc, mean_sky * RADIANCE_Y).reshape(args.noise_repeats, len(index))
    return {"sensors": [int(i) for i in index], "repeats": args.noise_repeats, "seconds": seconds,
            "mean_lux": means.mean(axis=0), "rel_std": means.std(axis=0, ddof=1) / means.mean(axis=0)}


#: Radiance's sun models: the per-hour sun at Radiance's position (the reference), the per-hour sun at pvlib's
#: (SPA) position (hfrad's: like for like), the five-phase MF:6 suns, and two-phase (the sun spread over MF:1)
VARIANTS = ("hour", "spa", "mf6", "two_phase")


def radiance_side(scene, sensors, weather, args, t):
    """Radiance's year summarised like hfrad's, for each sun model of :data:`VARIANTS`."""
    repeat = 2 if args.noise else 1
    with tempfile.TemporaryDirectory(prefix="dl-radiance-") as tmp:
        r = radiance_year(scene, sensors, weather, ab=args.ab, ad=args.ad, threads=args.threads, work=Path(tmp), t=t,
                          ground=args.ground, repeat=repeat,
                          cache=Path(args.radiance_cache) if args.radiance_cache else None)
    tr = r["timings"]
    print(f"  Radiance: rfluxmtx {tr['rfluxmtx_s']:.1f} s (x{repeat} sensors), suns per hour {tr['hour_suns_s']:.1f} s",
          flush=True)
    m, hour = len(sensors), weather.hour
    out = {v: summary(r["totals"][v][:m], r["direct"][v][:m], hour) for v in VARIANTS[:3]}
    out["two_phase"] = summary(r["lux"][:m], r["spread_direct"][:m], hour)
    info = {"timings": r["timings"], "options": r["options"], "sun_options": r["sun_options"]}
    if repeat == 2:
        m2 = r["lux"][m:, weather_occupied(hour)].mean(axis=1)
        m1 = out["two_phase"]["mean_lux"]
        d = (m1 - m2) / (0.5 * (m1 + m2))
        info["noise_mean_lux_rel_rms"] = float(np.sqrt(np.mean(d ** 2)) / math.sqrt(2))
    return out, info


def _reuse(path, name, sensors):
    """Radiance's summaries of case ``name`` from an earlier run's JSON (the same sensors), or None."""
    if not path:
        return None
    for r in json.loads(Path(path).read_text())["results"]:
        if r["case"] == name and np.allclose(r["points"], sensors.points):
            R = r["radiance"]
            if "variants" not in R:
                raise SystemExit(f"{path}: case '{name}' has Radiance's results of an earlier version (MF:6 suns "
                                 "only); run without --radiance-json (--radiance-cache keeps rfluxmtx's matrices)")
            out = {v: {k: np.asarray(x) if isinstance(x, list) else x for k, x in R["variants"][v].items()}
                   for v in VARIANTS}
            return out, {**R["info"], "reused_from": str(path)}
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
        R, rinfo = radiance_side(scene, sensors, weather, args, t)
    else:
        R, rinfo = reused
        print(f"  Radiance: reused from {args.radiance_json}", flush=True)
    with tempfile.TemporaryDirectory(prefix="dl-suns-") as tmp:
        along = hfrad_on_radiance_suns(h["tracer"], sensors, weather, Path(tmp), t, args.ground)
    noise = None
    if args.noise_at:            # Radiance's scatter where the two-phase years differ most
        rel = summary(h["lux_two_phase"], h["spread_direct"], hour)["mean_lux"] / R["two_phase"]["mean_lux"] - 1
        noise = radiance_noise(scene, sensors, np.argsort(-np.abs(rel))[:args.noise_at], weather, args, t)
        noise["hfrad_rel_to_mean"] = (summary(h["lux_two_phase"], h["spread_direct"], hour)["mean_lux"][
            noise["sensors"]] / noise["mean_lux"] - 1)
        noise["first_run_rel"] = rel[noise["sensors"]]
        print(f"  Radiance noise at {args.noise_at} sensors x {args.noise_repeats}: relative std "
              f"{', '.join(f'{100 * x:.1f}%' for x in noise['rel_std'])}; hfrad against their mean "
              f"{', '.join(f'{100 * x:+.1f}%' for x in noise['hfrad_rel_to_mean'])} (first run "
              f"{', '.join(f'{100 * x:+.1f}%' for x in noise['first_run_rel'])})", flush=True)
    base = h["lux"] - h["direct_sun"]
    H = {"exact": summary(h["lux"], h["direct_sun"], hour),
         "two_phase": summary(h["lux_two_phase"], h["spread_direct"], hour),
         "on_hour_suns": summary(base + along["hour"], along["hour"], hour),
         "on_mf6_suns": summary(base + along["mf6"], along["mf6"], hour)}
    pairs = {"hour": ("exact", "hour"), "spa": ("exact", "spa"), "mf6": ("exact", "mf6"),
             "two_phase": ("two_phase", "two_phase"), "same_suns_hour": ("on_hour_suns", "hour"),
             "same_suns_mf6": ("on_mf6_suns", "mf6")}
    return {"case": name, "room": CASES[name], "materials": MATERIALS, "patches": h["patches"], "rank": h["rank"],
            "sensors": len(sensors), "spacing_m": args.spacing,
            "hfrad": {**H, "timings": h["timings"]},
            "radiance": {"variants": R, "info": rinfo},
            "compare": {k: compare(H[a], R[b]) for k, (a, b) in pairs.items()},
            "sun_positions": sun_positions(weather, along["hour_suns"]),
            "radiance_noise": noise,
            "points": sensors.points}


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
    p.add_argument("--noise-at", type=int, default=0,
                   help="trace the N sensors where the two-phase years differ most again in Radiance, "
                        "--noise-repeats times each, for Radiance's scatter there")
    p.add_argument("--noise-repeats", type=int, default=8)
    p.add_argument("--radiance-json", default=None,
                   help="reuse Radiance's results of the same case and sensors from an earlier run's JSON")
    p.add_argument("--radiance-cache", default=None,
                   help="folder keeping Radiance's daylight coefficient matrices (rfluxmtx), reused when the "
                        "scene, sensors and options are the same")
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
    names = {"hour": "per hour, Radiance's position", "spa": "per hour, pvlib's (SPA) position",
             "mf6": "five-phase MF:6 patch centres", "two_phase": "two-phase (spread over MF:1)"}
    rows, trows = [], []
    for r in results:
        H, R, C = r["hfrad"], r["radiance"]["variants"], r["compare"]
        for v in VARIANTS:
            h = H["two_phase" if v == "two_phase" else "exact"]
            same = {"hour": "on_hour_suns", "mf6": "on_mf6_suns"}.get(v)
            rows.append({"case": r["case"], "Radiance's sun": names[v],
                         "mean lx hfrad": float(h["mean_lux"].mean()),
                         "mean lx Radiance": float(R[v]["mean_lux"].mean()),
                         "sensor max |rel|": C[v]["mean_lux_rel_max_abs"], "sensor RMS rel": C[v]["mean_lux_rel_rms"],
                         "sDA hfrad %": 100 * h["sDA"], "sDA Radiance %": 100 * R[v]["sDA"],
                         "ASE hfrad %": 100 * h["ASE"], "ASE Radiance %": 100 * R[v]["ASE"],
                         "ASE hfrad on Radiance's suns %": 100 * H[same]["ASE"] if same else float("nan")})
        ht, rt = H["timings"], r["radiance"]["info"]["timings"]
        trows.append({"case": r["case"], "sensors": r["sensors"], "patches": r["patches"],
                      "hfrad precompute s": ht["precompute_s"], "hfrad year s": ht["year_s"],
                      "Radiance 2-phase s": rt["convert_s"] + rt["rfluxmtx_s"] + rt["gendaymtx_s"] + rt["dctimestep_s"],
                      "Radiance suns per hour s": rt["hour_suns_s"],
                      "Radiance 5-phase MF:6 s": rt["direct_coefficients_s"] + rt["sun_coefficients_s"]
                      + rt["sun_year_s"]})
        sp = r["sun_positions"]
        print(f"{r['case']}: Radiance's sun vs pvlib SPA over {sp['sunlit_hours']} sunlit hours: "
              f"{sp['angle_mean_deg']:.2f} deg mean, {sp['angle_p95_deg']:.2f} p95, {sp['angle_max_deg']:.2f} max; "
              f"altitude {sp['altitude_diff_mean_deg']:+.2f} deg mean (SPA higher)")
    for title, rr in ((f"hfrad vs Radiance (rfluxmtx -ab {args.ab} -ad {args.ad}), Greensboro TMY3", rows),
                      ("timings, s", trows)):
        cols = list(rr[0].keys())
        print_table(title, rr, cols)
        print(table(rr, cols, markdown=True))
    path = write_json(args.name, {"machine": m, "args": vars(args), "results": results, "table": rows,
                                  "timings": trows})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
