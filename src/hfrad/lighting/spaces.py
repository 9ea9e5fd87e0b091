"""Work-plane grids from a building model's spaces (IFC ``IfcSpace``), with no hand-written layout.

Each space of an IFC model gives one grid: sensors facing up at ``height``
(0.8 m by default) above the space's floor, ``spacing`` apart, over the
space's own outline (:func:`hfrad.lighting.sensors.plan_grid`), named after
the space. ``hfrad lux`` and ``hfrad design`` lay them when the scene was read
from an IFC file (the factorization keeps the file's path as the scene's name)
or when given the file (``--spaces MODEL.ifc``; a design grid
``{"spaces": "MODEL.ifc"}``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from ..scene.ifc import read_spaces
from .sensors import SensorSet, plan_grid

__all__ = ["space_grids", "scene_ifc"]


def scene_ifc(scene, *, strict: bool = False) -> Path | None:
    """The IFC file a scene was read from (its ``name``), when that file still exists; else None.

    With ``strict``, a scene read from an IFC file that is not found (moved, or a relative path read
    from another folder) raises InputError instead of returning None.
    """
    path = Path(str(scene.name))
    if path.suffix.lower() != ".ifc":
        return None
    if path.is_file():
        return path
    if strict:
        raise InputError(f"the scene was read from {path}, which is not found from here: give --spaces MODEL.ifc "
                         "(its IfcSpace work planes), --floor MATERIAL or --sensors FILE")
    return None


def space_grids(source, *, height: float = 0.8, spacing: float = 0.25, margin: float = 0.0,
                unit_scale: float = 1.0, scene=None) -> list[SensorSet]:
    """One work-plane grid per ``IfcSpace`` of an IFC file.

    Parameters
    ----------
    source : str or Path
        The IFC file.
    height : float, metres
        Above each space's floor (its lowest point).
    spacing, margin : float, metres
        Cell size and the border left out (:func:`hfrad.lighting.floor_grid`).
    unit_scale : float
        The ``--unit-scale`` the scene was loaded with (IFC coordinates are
        already in metres: normally 1).
    scene : Scene, optional
        When given, every grid must lie within the scene's bounds (a scene
        loaded with another unit scale, or from another file, is refused).

    Returns
    -------
    list of SensorSet
        In the file's order; names are the spaces' names (``LongName``, else
        ``Name``, else ``#id``), made unique by the entity id when repeated.

    Raises
    ------
    InputError
        The file has no IfcSpace, a space too small for the spacing, or grids
        outside the scene.
    SceneError
        Not a readable IFC file, or a space without a bottom face (entity id named).
    """
    path = Path(source)
    spaces = read_spaces(path)
    if not spaces:
        raise InputError(f"{path}: no IfcSpace to lay work planes on; give --floor MATERIAL or --sensors FILE")
    names = [s.name for s in spaces]
    grids = []
    for s in spaces:
        name = s.name if names.count(s.name) == 1 else f"{s.name} ({s.entity.split()[0]})"
        grids.append(plan_grid(s.outline * unit_scale, s.floor * unit_scale + height, spacing, name=name,
                               margin=margin, what=f"the outline of {s.entity}"))
    if scene is not None:
        _check_inside(grids, scene, path)
    return grids


def _check_inside(grids: list[SensorSet], scene, path: Path) -> None:
    lo, hi = np.asarray(scene.bounds)
    slack = 1e-6 * float((hi - lo).max())
    for g in grids:
        out = ((g.points < lo - slack) | (g.points > hi + slack)).any(axis=1)
        if out.any():
            raise InputError(f"{path}: the work plane of space {g.name!r} lies outside the scene "
                             f"({int(out.sum())} of {len(g)} sensors); was the scene read from this file, "
                             "with the same --unit-scale?")
