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
from .tonemap import expose, srgb_encode, to_uint8


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

#: Rays a pixel of a picture by default (:func:`render_image`): a stratified 2 x 2 grid, so edges
#: get intermediate values; 1 is one ray through each pixel's centre.
DEFAULT_SAMPLES = 4

#: Most rays a pixel (a 8 x 8 grid); memory and time grow with the count.
MAX_SAMPLES = 64

#: Memory a pixel needs per sample, bytes (its radiance and hit, kept until the exposure is known).
BYTES_PER_SAMPLE = 48

#: Smallest false-colour picture: the colour bar and its labels need this much beside the scene
#: (8 pixels high or less broke the drawing of the bar; 16 x 24 is the smallest drawn whole).
MIN_FALSECOLOR_SIZE = (16, 24)


def check_samples(samples: int) -> int:
    """``samples`` if it is a square number of rays a pixel from 1 to :data:`MAX_SAMPLES` (a k x k grid).

    Raises
    ------
    InputError
        Anything else, naming the allowed values.
    """
    ok = isinstance(samples, (int, np.integer)) and not isinstance(samples, bool) and 1 <= samples <= MAX_SAMPLES
    if not ok or round(np.sqrt(samples)) ** 2 != samples:
        raise InputError(f"samples must be a square number of rays a pixel from 1 to {MAX_SAMPLES} "
                         f"(1, 4, 9, 16, ...: a k x k grid), got {samples!r}")
    return int(samples)


def _offsets(samples: int) -> list[tuple[float, float]]:
    """Sub-pixel positions of a stratified k x k grid (cell centres), pixel units."""
    k = int(round(np.sqrt(samples)))
    c = (np.arange(k) + 0.5) / k
    return [(float(x), float(y)) for y in c for x in c]


def check_size(width: int, height: int, *, falsecolor: bool = False, samples: int = 1) -> None:
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
    per_pixel = BYTES_PER_PIXEL + BYTES_PER_SAMPLE * (check_samples(samples) if samples != 1 else 0)
    require(per_pixel * float(width) * float(height), f"rendering {int(width):,} x {int(height):,} pixels",
            "use a smaller width and height")


_check_size = check_size


def _radiance_samples(scene, B, cam: Camera, width: int, height: int, samples: int, flat: bool,
                      crease_angle: float, caster) -> tuple[np.ndarray, np.ndarray]:
    """(s, h, w, 3) radiance and (s, h, w) patch (-1: background) of each sub-pixel sample."""
    corners = None if flat else smooth_corners(scene, B, crease_angle=crease_angle)
    radiance = np.zeros((samples, height, width, 3))
    face = np.full((samples, height, width), -1, np.int64)
    for i, offset in enumerate(_offsets(samples) if samples > 1 else [(0.5, 0.5)]):
        tri, _, uv = trace_camera(scene, cam, width, height, caster=caster, offset=offset)
        hit = tri >= 0
        face[i][hit] = scene.patch_of_triangle[tri[hit]]
        if hit.any():
            radiance[i][hit] = B[face[i][hit]] if flat else interpolate(corners, tri[hit], uv[hit])
    return radiance / np.pi, face


def _first_hit(face: np.ndarray) -> np.ndarray:
    """(h, w): each pixel's patch from its first sample that hit one (-1 where none did)."""
    out = face[0].copy()
    for f in face[1:]:
        out = np.where(out >= 0, out, f)
    return out


def render_radiance(scene, radiosity, camera: "Camera | str" = "auto", *, width: int = 512,
                    height: int = 512, flat: bool = False, crease_angle: float = CREASE_ANGLE,
                    caster=None, samples: int = 1) -> tuple[np.ndarray, np.ndarray]:
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
    samples : int
        Rays a pixel, a stratified k x k grid (1, 4, 9, ...); the radiance is
        their mean (background counts 0). 1: one ray through the centre, the
        radiance at one surface point.

    Returns
    -------
    radiance : (height, width, 3) float, W/(m^2 sr)
        ``B / pi`` at each pixel's surface point(s); 0 for background.
    face : (height, width) int
        Patch seen by each pixel (its first sample that hit one), -1 for background.
    """
    B = _check_radiosity(scene, radiosity)
    samples = check_samples(samples)
    _check_size(width, height, samples=samples)
    cam = Camera.parse(camera, scene.bounds, aspect=width / height, scene=scene)
    radiance, face = _radiance_samples(scene, B, cam, width, height, samples, flat, crease_angle, caster)
    return radiance.mean(axis=0), _first_hit(face)


def render_image(scene, radiosity, *, camera: "Camera | str" = "auto", width: int = 512,
                 height: int = 512, exposure: float | None = None, auto_exposure: bool = True,
                 flat: bool = False, falsecolor: bool = False, unit: str = "W/m2",
                 crease_angle: float = CREASE_ANGLE, caster=None, samples: int = DEFAULT_SAMPLES) -> np.ndarray:
    """An 8-bit sRGB picture of a radiosity solution, anti-aliased.

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
    samples : int
        Rays a pixel, a stratified k x k grid (default :data:`DEFAULT_SAMPLES`);
        the pixel is the mean of its samples' clipped display values (so a
        light's edge blends too), sRGB-encoded after averaging. In false colour
        a pixel takes the mean value of its samples that see a surface, and
        fades to black with the share that see background. 1 turns it off.

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
    Cost: ``samples`` Embree rays per pixel and per back face passed, plus
    O(n) for the per-corner smoothing.

    Examples
    --------
    >>> from hfrad.scene.builtin import cornell_box
    >>> s = cornell_box()
    >>> img = render_image(s, s.reflectance * 10 + s.emission, camera="front", width=32, height=32)
    >>> img.shape, img.dtype
    ((32, 32, 3), dtype('uint8'))
    """
    B = _check_radiosity(scene, radiosity)
    samples = check_samples(samples)
    full_width = width
    if falsecolor:
        check_unit(unit)
        check_size(width, height, falsecolor=True, samples=samples)
        width = width - colorbar_width(width)       # the scene's part; the bar takes the rest
    else:
        check_size(width, height, samples=samples)
    cam = Camera.parse(camera, scene.bounds, aspect=width / height, scene=scene)
    radiance, face = _radiance_samples(scene, B, cam, width, height, samples, flat, crease_angle, caster)
    hit = face >= 0
    lit = np.zeros_like(hit)
    lit[hit] = ~scene.emitters[face[hit]]
    if falsecolor:
        return _falsecolor(radiance, hit, lit, full_width, unit)
    if exposure is None:
        exposure = _auto_exposure(radiance, lit if lit.any() else hit) if auto_exposure else 0.0
    display = expose(radiance, exposure=float(exposure)).mean(axis=0)
    return to_uint8(srgb_encode(display))


def _falsecolor(radiance: np.ndarray, hit: np.ndarray, lit: np.ndarray, width: int, unit: str) -> np.ndarray:
    """False-colour picture from per-sample radiance (s, h, w, 3): mean over the samples that hit, faded by coverage."""
    count = hit.sum(axis=0)
    values = (photometric(radiance * np.pi, unit) * hit).sum(axis=0) / np.maximum(count, 1)   # back to radiosity
    # the scale tops at the brightest pixel none of whose samples sees a light (an edge pixel that
    # averages a light in would set it at a share of the light's own level)
    no_light = lit.any(axis=0) & ~(hit & ~lit).any(axis=0)
    img = np.array(falsecolor_image(values, count > 0, width=width, unit=unit, scale_mask=no_light))
    w = values.shape[1]
    coverage = count / hit.shape[0]
    img[:, :w] = np.rint(img[:, :w] * coverage[..., None]).astype(np.uint8)
    return img


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
