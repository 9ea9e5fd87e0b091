"""IFC building models made with ``ifcopenshell.api`` for the tests, the benchmark and the example.

``build_building(path, storeys=1, rooms=(2, 1))`` writes an IFC4 file of
storeys of ``nx x ny`` rooms: a floor slab per storey (no style: hfrad's
floor and ceiling defaults), a ceiling covering per room (no style), walls
(styled "Wall paint", reflectance 0.6) around and between the rooms, one window
per room in the south wall, and in the north wall for a second row of rooms,
(styled "Glazing", transparency 0.8) in an opening,
a door (no style) in each wall between rooms along x, one ``IfcSpace`` per room and,
optionally, desks (styled "Desk", 0.45). Coordinates are Z-up metres; the
rooms' interiors are ``room`` (w, d) apart by ``WALL`` thick walls.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

WALL = 0.2       # wall thickness, m
SLAB = 0.2       # floor slab thickness, m
CEILING = 0.02   # ceiling covering thickness, m


class _Builder:
    def __init__(self) -> None:
        import ifcopenshell.api.aggregate
        import ifcopenshell.api.context
        import ifcopenshell.api.project
        import ifcopenshell.api.root
        import ifcopenshell.api.unit

        api = ifcopenshell.api
        self.api = api
        self.f = api.project.create_file(version="IFC4")
        project = api.root.create_entity(self.f, ifc_class="IfcProject", name="hfrad test building")
        api.unit.assign_unit(self.f)
        model = api.context.add_context(self.f, context_type="Model")
        self.body = api.context.add_context(self.f, context_type="Model", context_identifier="Body",
                                            target_view="MODEL_VIEW", parent=model)
        site = api.root.create_entity(self.f, ifc_class="IfcSite", name="Site")
        self.building = api.root.create_entity(self.f, ifc_class="IfcBuilding", name="Building")
        api.aggregate.assign_object(self.f, relating_object=project, products=[site])
        api.aggregate.assign_object(self.f, relating_object=site, products=[self.building])
        self.styles = {}

    def style(self, name: str, rgb, transparency: float = 0.0):
        import ifcopenshell.api.style

        if name not in self.styles:
            s = self.api.style.add_style(self.f, name=name)
            colour = {"Name": None, "Red": rgb[0], "Green": rgb[1], "Blue": rgb[2]}
            self.api.style.add_surface_style(self.f, style=s, ifc_class="IfcSurfaceStyleShading",
                                             attributes={"SurfaceColour": colour, "Transparency": transparency})
            self.styles[name] = s
        return self.styles[name]

    def box(self, ifc_class: str, name: str, origin, size, *, rot: float = 0.0, style=None, container=None,
            predefined: str | None = None):
        """An element whose body is a box of ``size`` (length along its x, thickness along y, height z)."""
        import ifcopenshell.api.geometry
        import ifcopenshell.api.spatial

        kw = {"predefined_type": predefined} if predefined else {}
        el = self.api.root.create_entity(self.f, ifc_class=ifc_class, name=name, **kw)
        rep = self.api.geometry.add_wall_representation(self.f, context=self.body, length=size[0],
                                                        thickness=size[1], height=size[2])
        self.api.geometry.assign_representation(self.f, product=el, representation=rep)
        self.place(el, origin, rot)
        if style is not None:
            self.api.style.assign_representation_styles(self.f, shape_representation=rep, styles=[style])
        if container is not None and ifc_class != "IfcOpeningElement":
            self.api.spatial.assign_container(self.f, relating_structure=container, products=[el])
        return el

    def place(self, el, origin, rot: float = 0.0) -> None:
        import ifcopenshell.api.geometry

        m = np.eye(4)
        c, s = np.cos(np.radians(rot)), np.sin(np.radians(rot))
        m[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
        m[:3, 3] = origin
        self.api.geometry.edit_object_placement(self.f, product=el, matrix=m)

    def plate(self, ifc_class: str, name: str, polygon, z: float, depth: float, *, container, aggregate=False,
              predefined: str | None = None):
        """An element whose body is the plan ``polygon`` extruded up by ``depth`` from height ``z``."""
        import ifcopenshell.api.aggregate
        import ifcopenshell.api.geometry
        import ifcopenshell.api.spatial

        kw = {"predefined_type": predefined} if predefined else {}
        el = self.api.root.create_entity(self.f, ifc_class=ifc_class, name=name, **kw)
        rep = self.api.geometry.add_slab_representation(self.f, context=self.body, depth=depth,
                                                        polyline=list(polygon) + [polygon[0]])
        self.api.geometry.assign_representation(self.f, product=el, representation=rep)
        self.place(el, (0.0, 0.0, z))
        if aggregate:
            self.api.aggregate.assign_object(self.f, relating_object=container, products=[el])
        else:
            self.api.spatial.assign_container(self.f, relating_structure=container, products=[el])
        return el

    def filled_opening(self, wall, filler_class: str, name: str, origin, size, rot: float, container,
                       style=None, panel: float = 0.02):
        """Cut an opening of ``size`` (width, height) through ``wall`` at ``origin`` and fill it with a panel."""
        import ifcopenshell.api.feature

        w, h = size
        c, s = np.cos(np.radians(rot)), np.sin(np.radians(rot))
        normal = np.array([-s, c, 0.0])   # the wall's local +y (its thickness) in the world
        o = np.asarray(origin, float)
        opening = self.box("IfcOpeningElement", f"{name} opening", o - 0.1 * normal, (w, WALL + 0.2, h), rot=rot)
        self.api.feature.add_feature(self.f, feature=opening, element=wall)
        filler = self.box(filler_class, name, o + (WALL - panel) / 2 * normal, (w, panel, h), rot=rot,
                          style=style, container=container)
        self.api.feature.add_filling(self.f, opening=opening, element=filler)
        return filler


def build_building(path, *, storeys: int = 1, rooms: tuple[int, int] = (2, 1), room: tuple[float, float] = (4.0, 3.0),
                   height: float = 2.8, desks: int = 0, styles: bool = True) -> Path:
    """Write the building (module docstring) to ``path``; returns the path.

    Room (i, j) of storey k has its interior over x in [x_i, x_i + w], y in
    [y_j, y_j + d], z in [k H, k H + height] with x_i = WALL + i (w + WALL),
    y_j = WALL + j (d + WALL) and H = height + CEILING + SLAB.
    """
    import ifcopenshell.api.root

    b = _Builder()
    nx, ny = rooms
    w, d = room
    storey_h = height + CEILING + SLAB
    xs = [WALL + i * (w + WALL) for i in range(nx)]
    ys = [WALL + j * (d + WALL) for j in range(ny)]
    total_x, total_y = WALL + nx * (w + WALL), WALL + ny * (d + WALL)
    paint = b.style("Wall paint", (0.6, 0.6, 0.6)) if styles else None
    glass = b.style("Glazing", (0.3, 0.5, 0.6), transparency=0.8) if styles else None
    desk_style = b.style("Desk", (0.45, 0.4, 0.35)) if styles else None
    for k in range(storeys):
        z = k * storey_h
        st = ifcopenshell.api.root.create_entity(b.f, ifc_class="IfcBuildingStorey", name=f"Level {k}")
        b.api.aggregate.assign_object(b.f, relating_object=b.building, products=[st])
        outline = [(0.0, 0.0), (total_x, 0.0), (total_x, total_y), (0.0, total_y)]
        b.plate("IfcSlab", f"Slab {k}", outline, z - SLAB, SLAB, container=st, predefined="FLOOR")
        south = b.box("IfcWall", f"Wall S{k}", (0.0, 0.0, z), (total_x, WALL, height), style=paint, container=st)
        north = b.box("IfcWall", f"Wall N{k}", (0.0, total_y - WALL, z), (total_x, WALL, height), style=paint,
                      container=st)
        for i in range(nx + 1):          # walls along y, between the south and north walls
            x = i * (w + WALL)
            wall = b.box("IfcWall", f"Wall X{k}.{i}", (x + WALL, WALL, z), (total_y - 2 * WALL, WALL, height),
                         rot=90, style=paint, container=st)
            if 0 < i < nx:               # a door between rooms i-1 and i, in the first row
                b.filled_opening(wall, "IfcDoor", f"Door {k}.{i}", (x + WALL, ys[0] + 0.5 * d - 0.45, z), (0.9, 2.1),
                                 90, st, panel=0.04)
        for j in range(1, ny):           # walls along x between rows
            b.box("IfcWall", f"Wall Y{k}.{j}", (WALL, j * (d + WALL), z), (total_x - 2 * WALL, WALL, height),
                  style=paint, container=st)
        for i, x0 in enumerate(xs):
            b.filled_opening(south, "IfcWindow", f"Window {k}.{i}", (x0 + 0.5 * w - 0.75, 0.0, z + 0.9), (1.5, 1.2),
                             0, st, style=glass)
            if ny > 1:                   # the north row's windows
                b.filled_opening(north, "IfcWindow", f"Window N{k}.{i}", (x0 + 0.5 * w - 0.75, total_y - WALL, z + 0.9),
                                 (1.5, 1.2), 0, st, style=glass)
            for j, y0 in enumerate(ys):
                poly = [(x0, y0), (x0 + w, y0), (x0 + w, y0 + d), (x0, y0 + d)]
                b.plate("IfcCovering", f"Ceiling {k}.{i}.{j}", poly, z + height, CEILING, container=st,
                        predefined="CEILING")
                b.plate("IfcSpace", f"Room {k}.{i}.{j}", poly, z, height, container=st, aggregate=True)
                for m in range(desks):
                    b.box("IfcFurniture", f"Desk {k}.{i}.{j}.{m}",
                          (x0 + 0.4 + m * (w - 0.8) / max(desks, 1), y0 + 0.6, z), ((w - 0.8) / max(desks, 1) - 0.2,
                                                                                  0.8, 0.74),
                          style=desk_style, container=st)
    path = Path(path)
    b.f.write(str(path))
    return path
