"""Embree's nearest hits for the bakers of `jaxnm.transfer`: a triangle mesh in a robust-mode
scene (a ray through an edge or a vertex that triangles share hits one of them).

Embree comes with ``embreex`` (the ``bake`` extra). Two ways to reach it, the same hits:

- **direct**: the Embree library that embreex's wheel ships (and has loaded), called through
  ``ctypes``: the mesh is shared with Embree without a copy, and rays go in packets of 16
  with the GIL released, so threads cast at once;
- **embreex**: embreex's own scene (``EmbreeScene.run``, one ray at a time, holding the
  GIL), used where that library cannot be found or opened.
"""

from __future__ import annotations

import ctypes
import glob
import os
import weakref

import numpy as np

__all__ = ["ENGINES", "EmbreeScene"]

#: The ways to reach Embree (`EmbreeScene`'s ``engine``); None picks the first that works.
ENGINES = ("direct", "embreex")

_LANES = 16  # rays per packet (rtcIntersect16)
_ROWS = 24  # 16-float rows per packet buffer: RTCRayHit16 uses 20 or 21 (with instPrimID)
_ORG, _TNEAR, _DIR, _TFAR, _MASK, _U, _V, _PRIM, _GEOM = 0, 3, 4, 8, 9, 15, 16, 17, 18
_INVALID = 0xFFFFFFFF  # RTC_INVALID_GEOMETRY_ID
_ROBUST, _TRIANGLE, _INDEX, _VERTEX, _UINT3, _FLOAT3 = 4, 0, 0, 1, 0x5003, 0x9003


def _embreex():
    try:
        from embreex import mesh_construction, rtcore_scene
    except ImportError:
        raise ImportError('ray-cast baking needs Embree (embreex): pip install -e ".[bake]"'
                          ) from None
    return mesh_construction, rtcore_scene


def _library():
    """The Embree 4 library beside embreex (its wheel's), opened with ctypes, or None."""
    import embreex

    site = os.path.dirname(os.path.dirname(os.path.abspath(embreex.__file__)))
    for pattern in ("embreex.libs/libembree4*.so*", "embreex/.dylibs/libembree4*.dylib",
                    "embreex.libs/embree4*.dll", "embreex/libembree4*"):
        for path in sorted(glob.glob(os.path.join(site, pattern))):
            try:
                lib = ctypes.CDLL(path)
                p, u, i, s = ctypes.c_void_p, ctypes.c_uint, ctypes.c_int, ctypes.c_size_t
                for name, res, args in (
                        ("rtcNewDevice", p, [ctypes.c_char_p]), ("rtcNewScene", p, [p]),
                        ("rtcSetSceneFlags", None, [p, i]), ("rtcNewGeometry", p, [p, i]),
                        ("rtcSetSharedGeometryBuffer", None, [p, i, u, i, p, s, s, s]),
                        ("rtcCommitGeometry", None, [p]), ("rtcAttachGeometry", u, [p, p]),
                        ("rtcReleaseGeometry", None, [p]), ("rtcCommitScene", None, [p]),
                        ("rtcIntersect16", None, [p, p, p, p]),
                        ("rtcGetDeviceError", i, [p]), ("rtcReleaseScene", None, [p]),
                        ("rtcReleaseDevice", None, [p])):
                    getattr(lib, name).restype = res
                    getattr(lib, name).argtypes = args
                return lib
            except (OSError, AttributeError):
                continue
    return None


def _release(lib, scene, device):
    lib.rtcReleaseScene(scene)
    lib.rtcReleaseDevice(device)


class EmbreeScene:
    """A triangle mesh in an Embree scene, robust mode; `cast` finds nearest hits.

    **Arguments:** `positions` (V, 3), `faces` (F, 3); `engine`: one of `ENGINES`, or
    None for ``"direct"`` where it can be had, else ``"embreex"``.
    """

    def __init__(self, positions: np.ndarray, faces: np.ndarray, *, engine: str | None = None):
        if engine not in (None,) + ENGINES:
            raise ValueError(f"engine must be one of {', '.join(ENGINES)} or None, got {engine!r}")
        mesh_construction, rtcore_scene = _embreex()
        lib = _library() if engine in (None, "direct") else None
        if lib is not None:
            try:
                self._build_direct(lib, positions, faces)
                self.engine = "direct"
                return
            except OSError:
                if engine == "direct":
                    raise
        elif engine == "direct":
            raise OSError("Embree: the library of embreex's wheel was not found")
        self.engine = "embreex"
        self._scene = rtcore_scene.EmbreeScene(robust=True)
        self._mesh = mesh_construction.TriangleMesh(
            self._scene, np.ascontiguousarray(positions, np.float32),
            np.ascontiguousarray(faces, np.int32))
        self.cast(np.zeros((1, 3)), np.ones((1, 3)), 0.0)  # builds the BVH

    def _build_direct(self, lib, positions, faces):
        self._lib = lib
        # Embree reads vertices with 16-byte loads: one more row of padding
        self._vertices = np.zeros((len(positions) + 1, 3), np.float32)
        self._vertices[:-1] = positions
        self._faces = np.ascontiguousarray(faces, np.uint32)
        self._device = lib.rtcNewDevice(None)
        if not self._device:
            raise OSError("Embree: no device")
        self._ptr = lib.rtcNewScene(self._device)
        weakref.finalize(self, _release, lib, self._ptr, self._device)
        lib.rtcSetSceneFlags(self._ptr, _ROBUST)
        geom = lib.rtcNewGeometry(self._device, _TRIANGLE)
        lib.rtcSetSharedGeometryBuffer(geom, _INDEX, 0, _UINT3, self._faces.ctypes.data, 0, 12,
                                       len(self._faces))
        lib.rtcSetSharedGeometryBuffer(geom, _VERTEX, 0, _FLOAT3, self._vertices.ctypes.data, 0,
                                       12, len(positions))
        lib.rtcCommitGeometry(geom)
        lib.rtcAttachGeometry(self._ptr, geom)
        lib.rtcReleaseGeometry(geom)
        lib.rtcCommitScene(self._ptr)
        error = lib.rtcGetDeviceError(self._device)
        if error != 0:
            raise OSError(f"Embree: error {error} while building the scene")

    def cast(self, origins: np.ndarray, directions: np.ndarray, max_distance: float):
        """The nearest hit of each ray at or beyond its origin, front or back face, within
        ``max_distance`` (0: no limit): (triangle or -1, Embree's barycentrics u and v,
        distance), the point being ``(1 - u - v) p0 + u p1 + v p2``."""
        far = np.float32(max_distance) if max_distance > 0 else np.float32(np.inf)
        if self.engine == "embreex":
            o = np.ascontiguousarray(origins, np.float32)
            d = np.ascontiguousarray(directions, np.float32)
            dist = None if max_distance <= 0 else np.full(len(o), far, np.float32)
            r = self._scene.run(o, d, dists=dist, output=1)
            return (r["primID"].astype(np.int64), r["u"].astype(np.float64),
                    r["v"].astype(np.float64), r["tfar"].astype(np.float64))
        return self._cast_packets(origins, directions, far)

    def _cast_packets(self, origins, directions, far):
        n = len(origins)
        if n == 0:
            return np.zeros(0, np.int64), np.zeros(0), np.zeros(0), np.zeros(0)
        packets = -(-n // _LANES)
        raw = np.zeros(packets * _ROWS * _LANES + _LANES, np.float32)
        start = (-raw.ctypes.data % 64) // 4  # RTCRayHit16 is 64-byte aligned
        buf = raw[start:start + packets * _ROWS * _LANES].reshape(packets, _ROWS, _LANES)
        lanes = np.zeros(packets * _LANES, np.float32)
        for k in range(3):  # structure of arrays: a row of 16 lanes per coordinate
            lanes[:n] = origins[:, k]
            buf[:, _ORG + k] = lanes.reshape(packets, _LANES)
            lanes[:n] = directions[:, k]
            buf[:, _DIR + k] = lanes.reshape(packets, _LANES)
        buf[:, _TFAR] = far
        bits = buf.view(np.uint32)
        bits[:, _MASK] = _INVALID  # every ray sees every geometry
        bits[:, _GEOM] = _INVALID
        valid = np.full((2, _LANES), -1, np.int32)
        valid[1, n - (packets - 1) * _LANES:] = 0  # the last packet's unused lanes
        f, scene, base = self._lib.rtcIntersect16, self._ptr, buf.ctypes.data
        full, last, step = valid[0].ctypes.data, valid[1].ctypes.data, _ROWS * _LANES * 4
        for i in range(packets - 1):
            f(full, scene, base + i * step, None)
        f(last, scene, base + (packets - 1) * step, None)
        prim = bits[:, _PRIM].reshape(-1)[:n].astype(np.int64)
        prim[bits[:, _GEOM].reshape(-1)[:n] == _INVALID] = -1
        return (prim, buf[:, _U].reshape(-1)[:n].astype(np.float64),
                buf[:, _V].reshape(-1)[:n].astype(np.float64),
                buf[:, _TFAR].reshape(-1)[:n].astype(np.float64))
