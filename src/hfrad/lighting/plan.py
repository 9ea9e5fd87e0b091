"""What a plan shows beside the false colour: metre axes, the grid's extent, desks and luminaires.

A plan is the scene seen from above (hfrad's scenes are y-up): x runs to the
right, z downwards, one pixel per ``metres_per_pixel``. :class:`PlanFrame`
maps metres to pixels; the drawing functions put on a PIL image

- metre ticks and labels along the top and the left (every 1, 2 or 5 m, or
  tenths when the room is small);
- the grid's extent, a white rectangle around its cells;
- desks and other work surfaces: the outlines of upward faces of the scene
  near the work plane's height (:func:`desk_outlines`), light grey;
- luminaires: a dot of :data:`LUMINAIRE_COLOR` at each position and the
  outline of its luminous opening (length along C0, width along C90, or a
  circle), with its name and, where it is dimmed, its dimming in percent (a
  luminaire that is off gets a hollow ring instead of the dot).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

#: Colour of luminaire markers and outlines (magenta: not in the viridis scale under it).
LUMINAIRE_COLOR = (255, 60, 200)
#: Colour of desk and work-surface outlines.
DESK_COLOR = (210, 210, 210)
#: Upward faces within this height band around the work plane (m below, m above) are drawn as desks.
DESK_BAND = (0.6, 0.4)
#: Margins of the plan, pixels: left (z labels), top (x labels, under the title lines) and bottom
#: (room for the names of luminaires on the last row).
LEFT, TOP, BOTTOM = 42, 18, 14
#: Border of metres around everything drawn, so a marker at the edge is whole.
PAD_M = 0.25
#: Luminaires and desks wholly farther than this from the grid's extent, metres, are left off the
#: plan (the next room's, in a storey's layout): the plan shows the room of its grid.
NEAR_M = 0.5


@dataclasses.dataclass(frozen=True)
class PlanFrame:
    """Metres (x, z) to pixels (column, row) of a plan.

    Attributes
    ----------
    x0, z0 : float, metres
        The point at the plan's top-left corner (below the header and margins).
    metres_per_pixel : float
    left, top : int, pixels
        Where that corner is in the picture.
    """

    x0: float
    z0: float
    metres_per_pixel: float
    left: int
    top: int

    def pixel(self, x, z) -> tuple[np.ndarray, np.ndarray]:
        """(column, row) float pixel positions of points (x, z) in metres."""
        return (self.left + (np.asarray(x, np.float64) - self.x0) / self.metres_per_pixel,
                self.top + (np.asarray(z, np.float64) - self.z0) / self.metres_per_pixel)


def luminaire_outline(luminaire, points: int = 24) -> np.ndarray:
    """(k, 2) float, metres: the luminous opening's outline projected on (x, z).

    A rectangle length x width along the luminaire's C0 and C90 axes, or a
    circle where the file gives a negative length (its diameter); a point
    source (size 0) gives a 0.2 m square so it can still be seen.
    """
    length, width, _ = luminaire.photometry.size
    frame = luminaire.frame
    c0, c90 = frame[:, 0], frame[:, 1]
    if length < 0:
        t = np.linspace(0, 2 * math.pi, points, endpoint=False)
        r = -length / 2
        pts = luminaire.position + r * (np.cos(t)[:, None] * c0 + np.sin(t)[:, None] * c90)
    else:
        length, width = (length or 0.2), (width or length or 0.2)
        corners = [(-1, -1), (1, -1), (1, 1), (-1, 1)]
        pts = np.array([luminaire.position + a * length / 2 * c0 + b * width / 2 * c90 for a, b in corners])
    return pts[:, [0, 2]]


def desk_outlines(scene, height: float) -> list[np.ndarray]:
    """Outlines of the scene's upward surfaces near ``height`` (y, m): one (k, 2, 2) array of edges
    (two (x, z) ends in metres each) per connected surface (a desk top).

    Faces whose normal is within ~18 degrees of +y and whose centroid lies in
    :data:`DESK_BAND` around the work plane (desk tops, counters, sills); an
    edge shared by two such faces is inside a surface and left out.
    """
    if scene is None or scene.n_triangles == 0:
        return []
    tri = scene.vertices[scene.faces]
    y = tri[:, :, 1].mean(axis=1)
    up = (scene.triangle_normals[:, 1] > 0.95) & (y > height - DESK_BAND[0]) & (y < height + DESK_BAND[1])
    if not up.any():
        return []
    from ..scene.weld import weld

    pairs = [[0, 1], [1, 2], [2, 0]]
    vid = weld(scene.vertices, scene.faces)[up]
    edges = np.sort(np.stack([vid[:, p] for p in pairs], axis=1).reshape(-1, 2), axis=1)
    pos = np.stack([tri[up][:, p] for p in pairs], axis=1).reshape(-1, 2, 3)      # (3m, 2, 3) metres
    _, inverse, count = np.unique(edges, axis=0, return_inverse=True, return_counts=True)
    border = count[inverse.reshape(-1)] == 1
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    ends = edges[border]
    n = int(vid.max()) + 1
    _, label = connected_components(coo_matrix((np.ones(len(ends)), (ends[:, 0], ends[:, 1])), shape=(n, n)),
                                    directed=False)
    surface = label[ends[:, 0]]
    flat = pos[border][:, :, [0, 2]]
    return [flat[surface == k] for k in np.unique(surface)]


def near(grid_rect, points: np.ndarray) -> bool:
    """Whether any of the (k, 2) points (x, z, metres) lies within :data:`NEAR_M` of the grid's extent."""
    x0, z0, x1, z1 = grid_rect
    return bool(((points[:, 0] > x0 - NEAR_M) & (points[:, 0] < x1 + NEAR_M)
                 & (points[:, 1] > z0 - NEAR_M) & (points[:, 1] < z1 + NEAR_M)).any())


def extent(grid_rect, luminaires=(), desks=()) -> tuple[float, float, float, float]:
    """(x0, z0, x1, z1) metres holding the grid, every luminaire outline and desk, plus :data:`PAD_M`."""
    xs = [grid_rect[0], grid_rect[2]]
    zs = [grid_rect[1], grid_rect[3]]
    for pts in [luminaire_outline(l) for l in luminaires] + [d.reshape(-1, 2) for d in desks]:
        xs += [float(pts[:, 0].min()), float(pts[:, 0].max())]
        zs += [float(pts[:, 1].min()), float(pts[:, 1].max())]
    return min(xs) - PAD_M, min(zs) - PAD_M, max(xs) + PAD_M, max(zs) + PAD_M


def tick_step(span: float) -> float:
    """Metres between ticks: 0.1, 0.2, 0.5, 1, 2, 5, ... giving 3 to about 12 ticks over ``span``."""
    for step in (0.1, 0.2, 0.5, 1.0, 2.0, 5.0, 10.0, 20.0, 50.0, 100.0):
        if span / step <= 12:
            return step
    return 10 ** math.ceil(math.log10(span / 10))


def draw_axes(draw, frame: PlanFrame, box: tuple[float, float, float, float], font) -> None:
    """Metre ticks and labels along the top (x) and the left (z) of the plan."""
    x0, z0, x1, z1 = box
    grey = (200, 200, 200)
    step = tick_step(max(x1 - x0, z1 - z0))
    digits = 0 if step >= 1 else 1
    for x in np.arange(math.ceil(x0 / step) * step, x1 + 1e-9, step):
        c, r = frame.pixel(x, z0)
        draw.line([c, r - 5, c, r], fill=grey)
        draw.text((c - 8, r - 16), f"{x:.{digits}f}", fill=grey, font=font)
    for z in np.arange(math.ceil(z0 / step) * step, z1 + 1e-9, step):
        c, r = frame.pixel(x0, z)
        draw.line([c - 5, r, c, r], fill=grey)
        draw.text((2, r - 6), f"{z:.{digits}f}", fill=grey, font=font)
    draw.text((2, frame.top - 16), "m", fill=grey, font=font)     # the unit of both axes


def draw_overlay(draw, frame: PlanFrame, grid_rect, luminaires, desks, font) -> None:
    """The grid's extent, desk outlines and luminaires (outline, dot, name) on the plan."""
    for seg in (e for desk in desks for e in desk):
        c, r = frame.pixel(seg[:, 0], seg[:, 1])
        draw.line(list(zip(c.tolist(), r.tolist())), fill=DESK_COLOR, width=1)
    (c0, c1), (r0, r1) = frame.pixel([grid_rect[0], grid_rect[2]], [grid_rect[1], grid_rect[3]])
    draw.rectangle([c0, r0, c1, r1], outline=(255, 255, 255))
    for lum in luminaires:
        pts = luminaire_outline(lum)
        c, r = frame.pixel(pts[:, 0], pts[:, 1])
        draw.polygon(list(zip(c.tolist(), r.tolist())), outline=LUMINAIRE_COLOR)
        cx, cy = frame.pixel(lum.position[0], lum.position[2])
        on = lum.dimming > 0
        draw.ellipse([cx - 3, cy - 3, cx + 3, cy + 3], fill=LUMINAIRE_COLOR if on else None, outline=LUMINAIRE_COLOR)
        label = lum.name if lum.dimming == 1.0 else f"{lum.name}: {100 * lum.dimming:.0f}%"
        box = draw.textbbox((cx + 5, cy + 3), label, font=font)
        draw.rectangle([box[0] - 1, box[1] - 1, box[2] + 1, box[3] + 1], fill=(0, 0, 0))   # legible on any colour
        draw.text((cx + 5, cy + 3), label, fill=LUMINAIRE_COLOR, font=font)
