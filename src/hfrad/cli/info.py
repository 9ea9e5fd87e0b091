"""``hfrad info SCENE``: what a scene holds, before any computation."""

from __future__ import annotations

import dataclasses
import json
from typing import List, Optional

import typer
from rich.console import Console
from rich.table import Table

from ..errors import InputError
from . import common
from .common import quote


def _numbers(text: str) -> tuple[float, ...]:
    """``'1,2,3'`` -> (1.0, 2.0, 3.0); () if any part is not a number."""
    try:
        return tuple(float(x) for x in text.split(","))
    except ValueError:
        return ()


def parse_emit(values: Optional[List[str]]) -> dict[str, tuple[float, float, float]]:
    """``['light=17,12,4', 'lamp=5']`` -> ``{'light': (17, 12, 4), 'lamp': (5, 5, 5)}``.

    Raises
    ------
    InputError
        An item that is not NAME=R,G,B or NAME=V (quoted, at most ~200 characters).
    """
    out = {}
    for item in values or []:
        name, sep, rgb = item.rpartition("=")
        numbers = _numbers(rgb)
        if not sep or not name or len(numbers) not in (1, 3):
            raise InputError(f"--emission: expected NAME=R,G,B or NAME=V (W/m^2, e.g. light=17,12,4), "
                             f"got {quote(item)}")
        out[name] = numbers * 3 if len(numbers) == 1 else numbers
    return out


def parse_rgb(value: Optional[str], option: str = "--area-light") -> Optional[tuple[float, ...]]:
    """``'1,2,3'`` -> (1, 2, 3), ``'5'`` -> (5, 5, 5); InputError naming ``option`` otherwise."""
    if value is None:
        return None
    numbers = _numbers(value)
    if len(numbers) not in (1, 3):
        raise InputError(f"{option}: expected R,G,B or V (W/m^2, e.g. 10,10,10), got {quote(value)}")
    return numbers * 3 if len(numbers) == 1 else numbers


def load_scene_from_options(scene: str, *, unit_scale: float = 1.0, emit=None, area_light=None,
                            default_reflectance: float = 0.7, allow_missing_materials: bool = False,
                            max_edge=None, patches=None, keep_duplicates: bool = False, need=None, on_stage=None):
    """Load a scene the way every command does, from its CLI options.

    ``need(n)``, if given, is called with the patch count the cut will make
    (:func:`hfrad.scene.load.estimate_patch_count`) before any cutting, so a
    command refuses a scene too large for its own memory (precompute,
    formfactors) at once rather than after minutes of meshing. ``on_stage(name)``: told when
    reading, cleaning and cutting start (:func:`hfrad.scene.load.load_scene`).
    """
    from ..scene.load import cut_patches, estimate_patch_count, load_scene

    lights = dict(emit=parse_emit(emit), area_light=parse_rgb(area_light))
    s = load_scene(scene, unit_scale=unit_scale, **lights, default_reflectance=default_reflectance,
                   allow_missing_materials=allow_missing_materials, keep_duplicates=keep_duplicates,
                   on_stage=on_stage)
    if need is not None:
        need(estimate_patch_count(s, max_edge=max_edge, patches=patches))
    return cut_patches(s, max_edge=max_edge, patches=patches, on_stage=on_stage)


def register(app: typer.Typer) -> None:
    @app.command()
    @common.scene_options
    def info(
        scene: str = typer.Argument(..., help="Scene file (.obj, .ply, .gltf, .glb, .rad, .ifc) or built-in name "
                                    "(cornell, furnace, ...)."),
        scene_options: common.SceneOptions = None,
        as_json: bool = typer.Option(False, "--json", help="Print JSON instead of tables."),
    ) -> None:
        """Patch count, area, bounds, materials, emitters and warnings of a scene.

        Memory: about 1 KB per patch (no form factors are computed).
        """
        from ..render.camera import Camera
        from ..scene.cleanup import clean_faces
        from ..scene.summary import scene_summary

        keep_duplicates = scene_options.keep_duplicates
        with common.user_errors():
            s = load_scene_from_options(scene, **dataclasses.asdict(scene_options))
            # the input faces as read (duplicates kept, not cut), for the structured report of broken faces
            as_read = dataclasses.replace(scene_options, max_edge=None, patches=None, keep_duplicates=True)
            faces = load_scene_from_options(scene, **dataclasses.asdict(as_read))
        summary = scene_summary(s)
        report = clean_faces(faces, keep_duplicates=keep_duplicates)[1]
        summary["face_problems"] = {**report.summary(faces), "merged": not keep_duplicates}
        inside = Camera.inside(s)  # a first picture that looks at the inside of a building
        summary["camera_inside"] = inside.spec() if inside is not None else None
        if as_json:
            typer.echo(json.dumps(summary, indent=2))
            return
        _print_summary(summary)


def _print_summary(summary: dict) -> None:
    out = Console()
    out.print(f"[bold]{summary['scene']}[/]: {summary['patches']:,} patches from {summary['input_faces']:,} faces, "
              f"{summary['vertices']:,} vertices, area {summary['total_area_m2']:.4g} m^2")
    c = summary["clustering"]
    if c["clustered"]:
        per = c["triangles_per_patch"]
        out.print(f"clustered: {summary['patches']:,} patches of {c['triangles']:,} triangles "
                  f"({per['mean']:.1f} per patch on average, median {per['median']:g}, at most {per['max']:,}); "
                  f"patch area spread (std/mean) {c['area_cv']:.2f}; worst non-flatness {c['worst_non_flatness']:.3f} "
                  "(1 - |mean normal|; 0 = flat); compactness diameter^2/area median "
                  f"{c['compactness']['median']:.1f}, 99th percentile {c['compactness']['p99']:.1f}, worst "
                  f"{c['compactness']['max']:.0f} (disk 1.3, square 2-4, strip ~ length/width)", highlight=False)
    lo, hi = summary["bounds_min"], summary["bounds_max"]
    out.print("bounds: min (" + ", ".join(f"{x:.4g}" for x in lo) + ")  max (" + ", ".join(f"{x:.4g}" for x in hi) + ")")
    glazing = summary["glazing"]
    table = Table("material", "reflectance (R,G,B)", "emission W/m^2", *(["transmittance"] if glazing["patches"]
                                                                         else []), "patches", "area m^2")
    for m in summary["materials"]:
        tau = [", ".join(f"{x:.3g}" for x in m["transmittance"])] if glazing["patches"] else []
        table.add_row(m["name"], ", ".join(f"{x:.3g}" for x in m["reflectance"]),
                      ", ".join(f"{x:.3g}" for x in m["emission"]), *tau, f"{m['patches']:,}", f"{m['area']:.4g}")
    out.print(table)
    if glazing["materials"]:
        out.print(f"windows: {glazing['patches']:,} patches ({', '.join(glazing['materials'])}), area "
                  f"{glazing['area']:.4g} m^2; {glazing['treatment']}", highlight=False)
    out.print(f"emitters: {summary['emitter_patches']:,} patches ({', '.join(summary['emitter_materials']) or 'none'}), "
              f"power (W) " + ", ".join(f"{x:.4g}" for x in summary["emitted_power_w"]))
    faces = summary.get("face_problems")
    if faces:
        r = faces["overlaps"].get("resolved")
        cut = f" (cut {r['cut']} faces, dropped {r['dropped']})" if r else ""
        out.print(f"faces: {faces['duplicates']['count']} duplicates ({'merged' if faces['merged'] else 'kept'}), "
                  f"{faces['overlaps']['count']} coplanar overlapping pairs{cut}, "
                  f"{faces['facing']['count']} pairs touching face to face")
    if summary.get("camera_inside"):
        out.print(f"camera from inside (largest enclosed space): --camera {summary['camera_inside']}",
                  highlight=False, soft_wrap=True)
    for w in summary["warnings"]:
        out.print(f"[yellow]warning:[/] {w}", highlight=False)
