"""Ray casting with Intel Embree (through ``embreex``), batched.

Occlusion queries go to Embree in packets of 16, 8 or 4 rays (``rtcOccluded16/8/4``,
the widest this CPU runs natively: Embree's ``RTC_DEVICE_PROPERTY_NATIVE_RAY*_SUPPORTED``;
``rtcOccluded16`` on a CPU without AVX-512 corrupts the heap) from a
numba loop that holds no GIL, on an Embree scene of our own built with the
Embree library that ``embreex`` ships: ``embreex``'s ``run`` offers only one ray
at a time (``rtcOccluded1``), and the rays of the form factors come in coherent
runs (the segments of one patch pair, the probes of one row against
neighbouring columns), which packets trace faster (benchmarks/bench_rays.py).
The scene is built exactly as ``embreex`` builds its own (one triangle geometry,
unshared vertices in 16-byte records, ``RTC_SCENE_FLAG_ROBUST``, a one-thread
build), so every answer is the same as ``embreex``'s, bit for bit
(tests/test_raycast_packets.py). Where the library cannot be loaded,
``embreex``'s ``run`` answers instead. First hits (``intersect``) go through
``embreex``. ``embreex`` is imported at first use so that a missing
install gives a clear message with the pip command, not an import failure of
hfrad itself.

Embree works in float32 and silently misses every hit when coordinates are
very large or very small (a 2-unit triangle is hit up to coordinates of
1e12 and missed from 1e13 on, and missed below 1e-20), and
float32 cannot resolve a 1 m room 1e13 m from the origin at all. So the
caster works in its own frame: the triangles are moved to the centre of their
bounding box and divided by its size (metres per unit) before they reach
Embree; the ray origins and lengths of each query are mapped the same way in
float64, and the distances of hits mapped back. Directions are unchanged.
"""

from __future__ import annotations

import ctypes
import glob
import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from numba import njit, types

from ..resources import cores

_MIN_CHUNK = 65536  # below this, thread hand-off costs more than it saves


def _embree():
    try:
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise ImportError("ray casting needs Intel Embree's Python binding: "
                          "pip install embreex") from exc
    return rtcore_scene, TriangleMesh


#: Embree's scene flag that embreex's scenes carry (rtcore_scene.h: RTC_SCENE_FLAG_ROBUST); with it
#: our scene answers exactly as embreex's does.
_SCENE_FLAG_ROBUST = 1 << 2
_GEOMETRY_TRIANGLE, _BUFFER_INDEX, _BUFFER_VERTEX = 0, 0, 1
_FORMAT_UINT3, _FORMAT_FLOAT3 = 0x5003, 0x9003

# rtcOccludedK(const int* valid, RTCScene scene, RTCRayK* rays, RTCOccludedArguments* args), pointers
# passed as integers (the same registers on every 64-bit ABI); resolved by name, so cached code keeps working
_SIGNATURE = types.void(types.intp, types.intp, types.intp, types.intp)
_occluded16 = types.ExternalFunction("rtcOccluded16", _SIGNATURE)
_occluded8 = types.ExternalFunction("rtcOccluded8", _SIGNATURE)
_occluded4 = types.ExternalFunction("rtcOccluded4", _SIGNATURE)
#: rtcGetDeviceProperty's RTC_DEVICE_PROPERTY_NATIVE_RAY{4,8,16}_SUPPORTED (embree4/rtcore_device.h): Embree
#: runs a packet size only where the CPU has its ISA (16: AVX-512; 8: AVX/AVX2); the widest of them is used
_NATIVE_PACKETS = ((16, 34), (8, 33), (4, 32))

_LIB: list = []  # [ctypes library] once loaded, [None] when it cannot be


def _embree_library():
    """The Embree library that embreex ships, loaded for ctypes and for numba; None if unavailable."""
    if _LIB:
        return _LIB[0]
    lib = None
    try:
        import embreex
        from llvmlite import binding

        base = os.path.dirname(os.path.abspath(embreex.__file__))
        found = sorted(glob.glob(os.path.join(base, "..", "embreex.libs", "*embree4*"))
                       + glob.glob(os.path.join(base, "*embree4*.dll")))
        if found:
            binding.load_library_permanently(found[0])  # numba's code finds rtcOccluded16 by name
            lib = ctypes.CDLL(found[0])
            u64 = ctypes.c_uint64
            for name, res, args in (("rtcNewDevice", u64, [ctypes.c_char_p]), ("rtcNewScene", u64, [u64]),
                                    ("rtcSetSceneFlags", None, [u64, ctypes.c_int]),
                                    ("rtcNewGeometry", u64, [u64, ctypes.c_int]),
                                    ("rtcSetNewGeometryBuffer", u64, [u64, ctypes.c_int, ctypes.c_uint, ctypes.c_int,
                                                                      ctypes.c_size_t, ctypes.c_size_t]),
                                    ("rtcCommitGeometry", None, [u64]), ("rtcAttachGeometry", ctypes.c_uint, [u64, u64]),
                                    ("rtcReleaseGeometry", None, [u64]), ("rtcCommitScene", None, [u64]),
                                    ("rtcGetDeviceError", ctypes.c_int, [u64]), ("rtcReleaseScene", None, [u64]),
                                    ("rtcReleaseDevice", None, [u64]),
                                    ("rtcGetDeviceProperty", ctypes.c_ssize_t, [u64, ctypes.c_int])):
                f = getattr(lib, name)
                f.restype, f.argtypes = res, args
    except (ImportError, OSError, AttributeError):  # pragma: no cover - depends on the install
        lib = None
    _LIB.append(lib)
    return lib


class _PacketScene:
    """An Embree scene over float32 triangles, built as embreex builds its own; queried by :func:`_occluded`."""

    def __init__(self, lib, triangles: np.ndarray) -> None:
        self._lib = lib
        # a one-thread build, as embreex's: the BVH of Sponza's 66K triangles built by several
        # threads misses 59 of 28 M hits that embreex's finds (measured at 10K patches)
        self.device = lib.rtcNewDevice(b"threads=1")
        self.scene = 0
        if not self.device:
            raise OSError("rtcNewDevice failed")
        #: rays a packet: the widest size this CPU runs natively
        self.width = next((k for k, prop in _NATIVE_PACKETS if lib.rtcGetDeviceProperty(self.device, prop) > 0), 0)
        if not self.width:
            self.release()
            raise OSError("Embree runs no ray packets natively on this CPU")
        self.scene = lib.rtcNewScene(self.device)
        lib.rtcSetSceneFlags(self.scene, _SCENE_FLAG_ROBUST)
        geom = lib.rtcNewGeometry(self.device, _GEOMETRY_TRIANGLE)
        nt = len(triangles)
        vb = lib.rtcSetNewGeometryBuffer(geom, _BUFFER_VERTEX, 0, _FORMAT_FLOAT3, 16, 3 * nt)
        ib = lib.rtcSetNewGeometryBuffer(geom, _BUFFER_INDEX, 0, _FORMAT_UINT3, 12, nt)
        if not vb or not ib:
            lib.rtcReleaseGeometry(geom)
            raise OSError("rtcSetNewGeometryBuffer failed")
        vert = np.zeros((3 * nt, 4), np.float32)  # x, y, z and a pad, embreex's layout
        vert[:, :3] = np.asarray(triangles, np.float32).reshape(-1, 3)
        ctypes.memmove(vb, vert.ctypes.data, vert.nbytes)
        index = np.arange(3 * nt, dtype=np.uint32)
        ctypes.memmove(ib, index.ctypes.data, index.nbytes)
        lib.rtcCommitGeometry(geom)
        lib.rtcAttachGeometry(self.scene, geom)
        lib.rtcReleaseGeometry(geom)
        lib.rtcCommitScene(self.scene)
        if lib.rtcGetDeviceError(self.device):
            raise OSError("Embree reported an error while building the scene")

    def release(self) -> None:
        if self.scene:
            self._lib.rtcReleaseScene(self.scene)
            self.scene = 0
        if self.device:
            self._lib.rtcReleaseDevice(self.device)
            self.device = 0


@njit(cache=True, nogil=True)
def _occluded(scene, width, o, d, t, hit):
    """hit[i] = some triangle of ``scene`` (an RTCScene address) blocks ray i within t[i].

    Rays go in packets of ``width`` (16, 8 or 4) in their order (an RTCRay16/8/4: structure of
    arrays, aligned to 4 ``width`` bytes): ``tnear`` 0, all mask bits, Embree's default query
    arguments, as embreex's ``run`` casts them one at a time. Embree sets ``tfar``
    to -inf where the ray is blocked and leaves it otherwise; a negative t (which
    Embree ignores) counts as blocked, as it does in embreex.
    """
    n, w = o.shape[0], width
    raw = np.empty(12 * 16 + 16, np.float32)      # room for the widest packet, 64-byte aligned
    a = (64 - raw.ctypes.data % 64) % 64 // 4
    ray = raw[a:a + 12 * w]
    bits = ray.view(np.uint32)
    rawv = np.empty(32, np.int32)
    av = (64 - rawv.ctypes.data % 64) % 64 // 4
    valid = rawv[av:av + w]
    for s in range(0, n, w):
        m = min(w, n - s)
        for k in range(w):
            if k < m:
                i = s + k
                valid[k] = -1
                ray[k] = o[i, 0]
                ray[w + k] = o[i, 1]
                ray[2 * w + k] = o[i, 2]
                ray[3 * w + k] = 0.0  # tnear
                ray[4 * w + k] = d[i, 0]
                ray[5 * w + k] = d[i, 1]
                ray[6 * w + k] = d[i, 2]
                ray[7 * w + k] = 0.0  # time
                ray[8 * w + k] = t[i]  # tfar
                bits[9 * w + k] = 0xFFFFFFFF  # mask
                bits[10 * w + k] = 0  # id
                bits[11 * w + k] = 0  # flags
            else:
                valid[k] = 0
        if w == 16:
            _occluded16(valid.ctypes.data, scene, ray.ctypes.data, 0)
        elif w == 8:
            _occluded8(valid.ctypes.data, scene, ray.ctypes.data, 0)
        else:
            _occluded4(valid.ctypes.data, scene, ray.ctypes.data, 0)
        for k in range(m):
            hit[s + k] = ray[8 * w + k] < 0.0


class RayCaster:
    """An Embree scene over triangles, answering batched ray queries.

    Parameters
    ----------
    vertices : (v, 3) float
    faces : (m, 3) int
    threads : int, optional
        Worker threads per batch; default: all cores available.
    normalise : bool
        Cast in the triangles' own frame (centred on their bounding box, in
        units of its size; module docstring), whatever the scale and offset
        of the coordinates. False for a caller whose coordinates already are
        centred and of size about 1 (the visibility engine): no per-query mapping.

    Attributes
    ----------
    centre : (3,) float, unit : float
        The frame: Embree sees ``(x - centre) / unit``.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, threads: int | None = None, *,
                 normalise: bool = True) -> None:
        _embree()  # a clear message now if embreex is missing
        tri = np.asarray(vertices, dtype=np.float64)[np.asarray(faces, dtype=np.int64)].reshape(-1, 3, 3)
        self.centre, self.unit = np.zeros(3), 1.0
        if normalise and len(tri):
            lo, hi = tri.min(axis=(0, 1)), tri.max(axis=(0, 1))
            size = float((hi - lo).max())
            self.centre, self.unit = 0.5 * (lo + hi), (size if size > 0 else 1.0)
        self._mapped = bool(self.centre.any() or self.unit != 1.0)
        #: (m, 3, 3) float64 triangles in the caller's coordinates, for exact tests Embree's float32 cannot make
        self.world_triangles = tri
        self.triangles = np.ascontiguousarray((tri - self.centre) / self.unit if self._mapped else tri,
                                              dtype=np.float32)
        self._embreex = None  # embreex's scene, built when first needed (see _scene)
        self._packets = None
        lib = _embree_library() if len(self.triangles) else None
        if lib is not None:
            try:
                self._packets = _PacketScene(lib, self.triangles)
            except OSError:  # pragma: no cover - depends on the install
                self._packets = None
        self.threads = threads or cores()   # the cores this process may use
        self._pool = ThreadPoolExecutor(self.threads) if self.threads > 1 else None

    @property
    def _scene(self):
        """embreex's scene over the same triangles (first hits, and occlusion without packets)."""
        if self._embreex is None:
            rtcore_scene, TriangleMesh = _embree()
            self._embreex = rtcore_scene.EmbreeScene()
            if len(self.triangles):
                TriangleMesh(self._embreex, self.triangles)
        return self._embreex

    def _chunks(self, n: int) -> list[slice]:
        if self._pool is None or n < 2 * _MIN_CHUNK:
            return [slice(0, n)]
        step = max(_MIN_CHUNK, -(-n // (4 * self.threads)))
        return [slice(s, min(n, s + step)) for s in range(0, n, step)]

    def _map(self, fn, n: int) -> list:
        chunks = self._chunks(n)
        if len(chunks) == 1:
            return [fn(chunks[0])]
        return list(self._pool.map(fn, chunks))

    def occluded(self, origins: np.ndarray, directions: np.ndarray, distances: np.ndarray) -> np.ndarray:
        """(r,) bool: whether something blocks each ray before its distance.

        Parameters
        ----------
        origins, directions : (r, 3) float
            Directions of unit length; the caller offsets origins off their surfaces.
        distances : (r,) float
            Ray length to test (the segment's end).

        Contiguous float32 arrays are passed to Embree without a copy.
        """
        o = self._in_frame(origins)
        if self._mapped:
            distances = np.asarray(distances, np.float64) / self.unit
        d = np.ascontiguousarray(directions, dtype=np.float32)
        t = np.ascontiguousarray(distances, dtype=np.float32)
        if not len(self.triangles) or not len(o):
            return np.zeros(len(o), dtype=bool)
        out = np.empty(len(o), dtype=bool)
        packets = self._packets

        def run(s: slice) -> None:
            if packets is not None:
                _occluded(packets.scene, packets.width, o[s], d[s], t[s], out[s])
            else:
                out[s] = self._scene.run(o[s], d[s], query="OCCLUDED", dists=t[s]) >= 0

        self._map(run, len(o))
        return out

    def intersect(self, origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """First hits of rays.

        Returns
        -------
        face : (r,) int, -1 where the ray escapes
        distance : (r,) float, ray parameter of the hit (inf where none)
        barycentric : (r, 2) float, (u, v) weights of corners 1 and 2 of the hit face
        """
        origins = self._in_frame(origins)
        directions = np.ascontiguousarray(directions, dtype=np.float32)
        r = len(origins)
        face = np.full(r, -1, np.int64)
        dist = np.full(r, np.inf)
        uv = np.zeros((r, 2))
        if not len(self.triangles) or not r:
            return face, dist, uv

        def run(s: slice) -> None:
            res = self._scene.run(origins[s], directions[s], output=1)
            prim = res["primID"].astype(np.int64)
            hit = prim >= 0
            face[s] = np.where(hit, prim, -1)
            dist[s] = np.where(hit, res["tfar"], np.inf)
            uv[s] = np.stack([res["u"], res["v"]], axis=1)

        self._map(run, r)
        if self._mapped:
            dist *= self.unit  # inf stays inf
        return face, dist, uv

    def _in_frame(self, origins) -> np.ndarray:
        """Ray origins as Embree sees them: mapped into the caster's frame in float64, then float32."""
        if self._mapped:
            origins = (np.asarray(origins, np.float64) - self.centre) / self.unit
        return np.ascontiguousarray(origins, dtype=np.float32)

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None

    def __del__(self) -> None:  # pragma: no cover - interpreter shutdown order varies
        try:
            self.close()
            if self._packets is not None:
                self._packets.release()
                self._packets = None
        except Exception:
            pass
