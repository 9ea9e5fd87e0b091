"""Pictures of a radiosity solution: shaded (tone-mapped) or false-colour.

Each pixel shows the patch its primary ray reaches first from the front (see
:mod:`hfrad.render.raycast`); its value is the radiosity interpolated at the
hit point (:mod:`hfrad.render.shading`), divided by pi to give radiance:

    L = B / pi    [W/(m^2 sr)],  B in W/m^2,

the radiance of a Lambertian surface of radiosity B. Exposure and sRGB
encoding are in :mod:`hfrad.render.tonemap`.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..atomic import atomic_path
from ..errors import InputError
from ..memory import require
from ..validation import check_finite, object_first

from .camera import Camera
from .falsecolor import check_unit, colorbar_width, falsecolor_image, photometric
from .raycast import trace_camera
from .shading import CREASE_ANGLE, interpolate, smooth_corners
from .tonemap import auto_exposure as _auto_exposure
from .tonemap import tonemap


def _check_radiosity(scene, radiosity) -> np.ndarray:
    B = check_finite(radiosity, "radiosity")  # real numbers (no complex, strings, bools), no NaN/inf
    n = scene.n_patches
    if B.shape == (n,):
        B = np.repeat(B[:, None], 3, axis=1)
    if B.shape != (n, 3):
        raise InputError(f"radiosity must have shape ({n}, 3) or ({n},) for a scene of {n} patches, "
                         f"got {B.shape}")
    return B


#: Largest picture side, pixels: larger pictures are refused before any work.
MAX_SIDE = 16384

#: Peak memory of :func:`render_image` per pixel, bytes: an upper bound of what a pixel holds at
#: once (its ray, hit, barycentrics and radiance in float64, the tone-mapped picture and the PNG
#: copy); the memory check refuses ``BYTES_PER_PIXEL * width * height`` above 80% of what is free.
BYTES_PER_PIXEL = 256

#: Smallest false-colour picture: the colour bar and its labels need this much beside the scene
#: (8 pixels high or less broke the drawing of the bar; 16 x 24 is the smallest drawn whole).
MIN_FALSECOLOR_SIZE = (16, 24)


def check_size(width: int, height: int, *, falsecolor: bool = False) -> None:
    """Refuse a picture size before any work: whole numbers of pixels, 1 to :data:`MAX_SIDE` a side,
    within the available memory (:data:`BYTES_PER_PIXEL`), and room for a colour bar in false colour.

    Raises
    ------
    InputError
        A size that is not a whole number, below 1 (or the false-colour minimum) or above MAX_SIDE.
    MemoryLimitError
        ``BYTES_PER_PIXEL * width * height`` exceeds 80% of the available memory.
    """
    for name, v in (("width", width), ("height", height)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer, float)) or not float(v).is_integer() or v < 1:
            raise InputError(f"{name} must be a positive whole number of pixels, got {v!r}")
        if v > MAX_SIDE:
            raise InputError(f"{name} must be at most {MAX_SIDE:,} pixels, got {int(v):,}")
    if falsecolor and (width < MIN_FALSECOLOR_SIZE[0] or height < MIN_FALSECOLOR_SIZE[1]):
        raise InputError(f"a false-colour picture needs at least {MIN_FALSECOLOR_SIZE[0]} x {MIN_FALSECOLOR_SIZE[1]} "
                         f"pixels (the colour bar and its labels sit beside the scene); got {int(width)} x {int(height)}")
    require(BYTES_PER_PIXEL * float(width) * float(height), f"rendering {int(width):,} x {int(height):,} pixels",
            "use a smaller width and height")


_check_size = check_size


def render_radiance(scene, radiosity, camera: "Camera | str" = "auto", *, width: int = 512,
                    height: int = 512, flat: bool = False, crease_angle: float = CREASE_ANGLE,
                    caster=None) -> tuple[np.ndarray, np.ndarray]:
    """Linear picture of radiance.

    Parameters
    ----------
    scene : Scene
    radiosity : (n, 3) or (n,) float, W/m^2
    camera : Camera or {'auto', 'front', 'x,y,z:tx,ty,tz[:fov]'}
    width, height : int, pixels
    flat : bool
        One value per patch instead of smooth interpolation.
    crease_angle : float, degrees
        See :func:`~hfrad.render.shading.smooth_corners`.
    caster : RayCaster, optional
        Over the patches (:func:`~hfrad.render.raycast.patch_caster`), to reuse.

    Returns
    -------
    radiance : (height, width, 3) float, W/(m^2 sr)
        ``B / pi`` at each pixel's surface point; 0 for background.
    face : (height, width) int
        Patch seen by each pixel, -1 for background.
    """
    B = _check_radiosity(scene, radiosity)
    _check_size(width, height)
    cam = Camera.parse(camera, scene.bounds, aspect=width / height, scene=scene)
    tri, _, uv = trace_camera(scene, cam, width, height, caster=caster)
    radiance = np.zeros((height, width, 3))
    hit = tri >= 0
    face = np.full_like(tri, -1)
    face[hit] = scene.patch_of_triangle[tri[hit]]
    if hit.any():
        if flat:
            radiance[hit] = B[face[hit]]
        else:
            radiance[hit] = interpolate(smooth_corners(scene, B, crease_angle=crease_angle), tri[hit], uv[hit])
    radiance /= np.pi
    return radiance, face


def render_image(scene, radiosity, *, camera: "Camera | str" = "auto", width: int = 512,
                 height: int = 512, exposure: float | None = None, auto_exposure: bool = True,
                 flat: bool = False, falsecolor: bool = False, unit: str = "W/m2",
                 crease_angle: float = CREASE_ANGLE, caster=None) -> np.ndarray:
    """An 8-bit sRGB picture of a radiosity solution.

    Parameters
    ----------
    scene : Scene
    radiosity : (n, 3) or (n,) float, W/m^2
        Per-patch radiosity, e.g. ``fac.solve(E)``.
    camera : Camera or str
        ``'auto'`` (three-quarter view of the bounding box), ``'front'``
        (straight in along -z; the classic Cornell box view) or
        ``'x,y,z:tx,ty,tz[:fov]'`` (position, target, vertical fov in degrees).
    width, height : int, pixels
    exposure : float, EV, optional
        Display value = clip(radiance * 2**exposure, 0, 1) before sRGB encoding.
        Overrides ``auto_exposure``.
    auto_exposure : bool
        When ``exposure`` is None: map the 99th percentile of luminance of the
        pixels that show non-emitting patches to 0.8 (EV 0 if False).
    flat : bool
        Constant colour per patch (shows the patches) instead of smooth shading.
    falsecolor : bool
        Map luminance-weighted radiosity to colours, with a colour bar on the
        right (the scene takes the rest of the width).
    unit : {'W/m2', 'lux'}
        Unit of the false-colour scale (see :mod:`hfrad.render.falsecolor`).

    Returns
    -------
    (height, width, 3) uint8
        sRGB-encoded pixels; background is black.

    Raises
    ------
    InputError (a ValueError)
        Wrong radiosity shape, bad size, camera string, exposure or unit.

    Notes
    -----
    Cost: one Embree ray per pixel and per back face passed, plus
    O(n) for the per-corner smoothing.

    Examples
    --------
    >>> from hfrad.scene.builtin import cornell_box
    >>> s = cornell_box()
    >>> img = render_image(s, s.reflectance * 10 + s.emission, camera="front", width=32, height=32)
    >>> img.shape, img.dtype
    ((32, 32, 3), dtype('uint8'))
    """
    if falsecolor:
        check_unit(unit)
        check_size(width, height, falsecolor=True)
        w = width - colorbar_width(width)
        B = _check_radiosity(scene, radiosity)
        radiance, face = render_radiance(scene, B, camera, width=w, height=height, flat=flat,
                                         crease_angle=crease_angle, caster=caster)
        hit = face >= 0
        lit = np.zeros_like(hit)
        lit[hit] = ~scene.emitters[face[hit]]
        values = photometric(radiance * np.pi, unit)  # back to radiosity
        return falsecolor_image(values, hit, width=width, unit=unit, scale_mask=lit)
    radiance, face = render_radiance(scene, radiosity, camera, width=width, height=height, flat=flat,
                                     crease_angle=crease_angle, caster=caster)
    if exposure is None:
        if auto_exposure:
            hit = face >= 0
            lit = np.zeros_like(hit)
            lit[hit] = ~scene.emitters[face[hit]]
            exposure = _auto_exposure(radiance, lit if lit.any() else hit)
        else:
            exposure = 0.0
    return tonemap(radiance, exposure=float(exposure))


def save_png(image: np.ndarray, path: "str | os.PathLike") -> Path:
    """Write an (h, w, 3) or (h, w) uint8 picture as PNG, atomically.

    The file is written under a temporary name in the same folder and renamed,
    so a reader never sees half a file and a failure leaves no file behind.
    """
    from PIL import Image

    image, path = object_first(image, path, "save_png(image, path)")
    path = Path(path)
    arr = np.asarray(image)
    if arr.dtype != np.uint8 or arr.ndim not in (2, 3):
        raise InputError(f"image must be an (h, w, 3) or (h, w) uint8 array, got {arr.dtype} {arr.shape}")
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        Image.fromarray(arr).save(fh, format="PNG")
    return path
