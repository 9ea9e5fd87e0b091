"""Pictures of radiosity solutions: camera, primary rays, smooth shading, tone mapping.

Pixel values are radiance L = B / pi in W/(m^2 sr) (Lambertian patches of
radiosity B in W/m^2), exposed in EV and sRGB-encoded for 8-bit PNG.

>>> from hfrad.scene.builtin import cornell_box
>>> s = cornell_box()
>>> img = render_image(s, s.reflectance * 10 + s.emission, camera="front", width=16, height=16)
>>> img.shape
(16, 16, 3)
"""

from .camera import Camera
from .image import render_image, render_radiance, save_png
from .shading import corner_smoother, corner_vertices, corner_weights, smooth_corners
from .tonemap import auto_exposure, srgb_decode, srgb_encode, tonemap

__all__ = ["Camera", "render_image", "render_radiance", "save_png", "smooth_corners",
           "corner_weights", "corner_smoother", "corner_vertices", "tonemap", "auto_exposure", "srgb_encode", "srgb_decode"]
