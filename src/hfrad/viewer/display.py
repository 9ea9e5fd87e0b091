"""Vertex colours for the browser: the same smoothing and tone mapping as ``hfrad render``.

The patch mesh is split along creases and material borders
(:func:`hfrad.render.corner_vertices`) and each vertex gets the value of the
linear fit through its smoothing set's patches that ``hfrad render`` gives that
corner (:func:`hfrad.render.corner_smoother`, the one helper both use:
sparse weights built once, so a new radiosity costs a few sparse products). Then:

- shaded: radiance ``B / pi`` exposed and sRGB-encoded to 8 bits by
  :func:`hfrad.render.tonemap.tonemap`, exactly as a rendered picture;
- false colour: :func:`hfrad.render.falsecolor.photometric` (W/m^2 or lux),
  scaled to :func:`~hfrad.render.falsecolor.nice_scale` of the brightest
  non-emitting vertex and mapped by :func:`~hfrad.render.falsecolor.colormap`,
  as ``hfrad render --falsecolor`` does per pixel.

The browser client (three.js in viser) applies ACES filmic tone mapping and
then the sRGB transfer function to everything it draws, so the 8-bit sRGB
target is decoded to linear and passed through the inverse of three.js's
ACES curve (:func:`precompensate_aces`): the screen shows the same 8-bit
values as the PNG. The browser interpolates these values linearly across each
triangle, where the renderer interpolates radiance: equal at the vertices,
slightly different inside a triangle where a colour is clipped.
"""

from __future__ import annotations

import json
import struct

import numpy as np

from ..render.falsecolor import colormap, falsecolor_image, nice_scale, photometric
from ..render.shading import CREASE_ANGLE, corner_smoother, corner_vertices
from ..render.tonemap import auto_exposure, srgb_decode, to_uint8, tonemap

# three.js ACESFilmicToneMapping (src/renderers/shaders/ShaderChunk/tonemapping_pars_fragment.glsl.js):
# color *= exposure / 0.6; color = IN @ color; color = RRTAndODTFit(color); color = OUT @ color; saturate.
_ACES_IN = np.array([[0.59719, 0.35458, 0.04823],
                     [0.07600, 0.90834, 0.01566],
                     [0.02840, 0.13383, 0.83777]])
_ACES_OUT = np.array([[1.60475, -0.53108, -0.07367],
                      [-0.10208, 1.10813, -0.00605],
                      [-0.00327, -0.07276, 1.07602]])
_ACES_IN_INV = np.linalg.inv(_ACES_IN)
_ACES_OUT_INV = np.linalg.inv(_ACES_OUT)
# Largest RRT output we aim at: the curve tends to 1/0.983729 = 1.0165 only at infinity.
_RRT_TOP = 1.0


def aces_filmic(linear: np.ndarray) -> np.ndarray:
    """(..., 3): three.js's ACES filmic tone mapping (exposure 1), before sRGB encoding."""
    v = np.asarray(linear, dtype=np.float64) / 0.6 @ _ACES_IN.T
    a = v * (v + 0.0245786) - 0.000090537
    b = v * (0.983729 * v + 0.4329510) + 0.238081
    return np.clip((a / b) @ _ACES_OUT.T, 0.0, 1.0)


def precompensate_aces(display: np.ndarray) -> np.ndarray:
    """(..., 3) float32: colours that :func:`aces_filmic` maps to ``display`` (linear, [0, 1]).

    ``OUT^-1`` has non-negative entries and unit row sums, so targets in the
    unit cube need RRT outputs ``u`` in [0, 1], each reached by the positive
    root of ``RRTAndODTFit(v) = u`` (a quadratic in v).
    """
    u = np.clip(np.asarray(display, dtype=np.float64) @ _ACES_OUT_INV.T, 0.0, _RRT_TOP)
    qa = 1.0 - 0.983729 * u
    qb = 0.0245786 - 0.4329510 * u
    qc = -(0.000090537 + 0.238081 * u)
    v = (-qb + np.sqrt(qb * qb - 4 * qa * qc)) / (2 * qa)
    return (0.6 * (v @ _ACES_IN_INV.T)).astype(np.float32)


class MeshColors:
    """The split patch mesh and its vertex colours for a radiosity.

    Parameters
    ----------
    scene : Scene
    crease_angle : float, degrees
        See :func:`hfrad.render.shading.smooth_corners`.

    Attributes
    ----------
    vertices : (v, 3) float, metres
    faces : (t, 3) int, the scene's detail triangles in order
    """

    def __init__(self, scene, *, crease_angle: float = CREASE_ANGLE) -> None:
        self.scene = scene
        self.vertices, self.faces = corner_vertices(scene, crease_angle=crease_angle)
        corners = self.faces.reshape(-1)
        first = np.empty(len(self.vertices), np.int64)
        first[corners[::-1]] = np.arange(len(corners))[::-1]   # one corner per vertex (they agree)
        self._first_corner = first
        self._smooth = corner_smoother(scene, crease_angle=crease_angle)
        self._vertex_patch = scene.patch_of_triangle[first // 3]

    def radiosity(self, B: np.ndarray) -> np.ndarray:
        """(v, 3) float, W/m^2: smoothed radiosity at the vertices."""
        return self._smooth(B).reshape(-1, 3)[self._first_corner]

    def shaded(self, B: np.ndarray, E: np.ndarray, exposure: float | None = None) -> tuple[np.ndarray, float]:
        """Display colours of radiance ``B / pi``.

        Parameters
        ----------
        B, E : (n, 3) float, W/m^2
            Radiosity and the exitance that produced it.
        exposure : float, EV, optional
            Default: :func:`~hfrad.render.tonemap.auto_exposure` over the
            non-emitting patches (as ``hfrad solve`` exports do).

        Returns
        -------
        display : (v, 3) float in [0, 1]
            Linear values whose sRGB encoding is the 8-bit picture value.
        exposure : float, EV used
        """
        if exposure is None:
            exposure = auto_exposure(np.asarray(B) / np.pi, np.asarray(E).max(axis=1) <= 0)
        srgb8 = tonemap(self.radiosity(B) / np.pi, exposure=float(exposure))
        return srgb_decode(srgb8 / 255.0), float(exposure)

    def falsecolor(self, B: np.ndarray, E: np.ndarray, unit: str = "W/m2") -> tuple[np.ndarray, float]:
        """False-colour display values and the top of the scale (in ``unit``).

        The scale runs from 0 to the brightest vertex of a non-emitting patch,
        rounded up to a tick (:func:`~hfrad.render.falsecolor.nice_scale`);
        lights saturate at the top colour.
        """
        values = photometric(self.radiosity(B), unit)
        lit = np.asarray(E).max(axis=1)[self._vertex_patch] <= 0
        sel = values[lit] if lit.any() else values
        top, _ = nice_scale(float(sel.max()) if sel.size else 0.0)
        return srgb_decode(to_uint8(colormap(values / top)) / 255.0), top


def colorbar(unit: str, top: float, *, height: int = 220, width: int = 110) -> np.ndarray:
    """(height, w, 3) uint8: the false-colour scale from 0 to ``top``, labelled, as in rendered pictures."""
    return falsecolor_image(np.zeros((height, 0)), np.zeros((height, 0), bool), width=width,
                            unit=unit, vmax=top)


class MeshGLB:
    """Binary glTF of a fixed triangle mesh whose vertex colours change.

    The material is unlit (``KHR_materials_unlit``): the browser shows the
    vertex colours without lights. Back faces are culled, as in
    ``hfrad render``, so a camera outside a closed room looks in. The JSON
    chunk and the geometry are built once; :meth:`encode` only appends the
    colours.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray) -> None:
        v = np.ascontiguousarray(vertices, dtype=np.float32)
        f = np.ascontiguousarray(faces, dtype=np.uint32).reshape(-1)
        self.n_vertices = len(v)
        geometry = v.tobytes() + f.tobytes()          # both multiples of 4 bytes
        color_bytes = 12 * len(v)
        doc = {
            "asset": {"version": "2.0", "generator": "hfrad view"},
            "extensionsUsed": ["KHR_materials_unlit"],
            "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
            "materials": [{"pbrMetallicRoughness": {"baseColorFactor": [1, 1, 1, 1], "metallicFactor": 0.0,
                                                    "roughnessFactor": 1.0},
                           "extensions": {"KHR_materials_unlit": {}}, "doubleSided": False}],
            "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "COLOR_0": 2}, "indices": 1,
                                        "material": 0}]}],
            "buffers": [{"byteLength": len(geometry) + color_bytes}],
            "bufferViews": [
                {"buffer": 0, "byteOffset": 0, "byteLength": v.nbytes, "target": 34962},
                {"buffer": 0, "byteOffset": v.nbytes, "byteLength": f.nbytes, "target": 34963},
                {"buffer": 0, "byteOffset": len(geometry), "byteLength": color_bytes, "target": 34962}],
            "accessors": [
                {"bufferView": 0, "componentType": 5126, "count": len(v), "type": "VEC3",
                 "min": v.min(axis=0).tolist() if len(v) else [0, 0, 0],
                 "max": v.max(axis=0).tolist() if len(v) else [0, 0, 0]},
                {"bufferView": 1, "componentType": 5125, "count": len(f), "type": "SCALAR"},
                {"bufferView": 2, "componentType": 5126, "count": len(v), "type": "VEC3"}],
        }
        js = json.dumps(doc, separators=(",", ":")).encode()
        js += b" " * (-len(js) % 4)
        blob_len = len(geometry) + color_bytes
        total = 12 + 8 + len(js) + 8 + blob_len
        self._head = (struct.pack("<4sII", b"glTF", 2, total) + struct.pack("<I4s", len(js), b"JSON") + js
                      + struct.pack("<I4s", blob_len, b"BIN\0") + geometry)

    def encode(self, colors: np.ndarray) -> bytes:
        """The GLB with these (v, 3) float32 vertex colours (linear, before the browser's tone mapping)."""
        c = np.ascontiguousarray(colors, dtype=np.float32)
        if c.shape != (self.n_vertices, 3):
            raise ValueError(f"colors must have shape ({self.n_vertices}, 3), got {c.shape}")
        return self._head + c.tobytes()
