"""Embree 4's C API through ctypes, for compiled code: the library embreex bundles, one
scene per base mesh built as embreex builds it (robust flag, default build quality,
float3 vertices and uint3 triangles), and the addresses of `rtcIntersect1` /
`rtcOccluded1`, so a ray's instances are traced in one compiled loop instead of one Python
call per mesh. Hits are the same bit for bit as embreex's (tests/workers/test_rtc.py).

The functions' addresses travel as kernel arguments (`INTERSECT1`, `OCCLUDED1`) to the
kernels of `nprt.workers.kernels.crossings`, which hold no process-specific constant, so
numba caches them like every other kernel."""

from __future__ import annotations

import ctypes
import glob
import os
import threading

import embreex
import numpy as np

_P = ctypes.c_uint64  # pointers travel as integers: the same registers on x86-64 and arm64
RTC_SCENE_FLAG_ROBUST = 1 << 2
RTC_GEOMETRY_TYPE_TRIANGLE = 0
RTC_BUFFER_TYPE_INDEX, RTC_BUFFER_TYPE_VERTEX = 0, 1
RTC_FORMAT_UINT3, RTC_FORMAT_FLOAT3 = 0x5003, 0x9003


def _library() -> ctypes.CDLL:
    here = os.path.join(os.path.dirname(embreex.__file__), "..", "embreex.libs")
    found = sorted(glob.glob(os.path.join(here, "libembree4*")))
    if not found:
        raise ImportError(f"no libembree4 beside embreex in {os.path.abspath(here)}")
    lib = ctypes.CDLL(found[0])
    for name, res, args in (
            ("rtcNewDevice", _P, [ctypes.c_char_p]),
            ("rtcNewScene", _P, [_P]),
            ("rtcSetSceneFlags", None, [_P, ctypes.c_int]),
            ("rtcNewGeometry", _P, [_P, ctypes.c_int]),
            ("rtcSetNewGeometryBuffer", _P, [_P, ctypes.c_int, ctypes.c_uint, ctypes.c_int,
                                             ctypes.c_size_t, ctypes.c_size_t]),
            ("rtcCommitGeometry", None, [_P]),
            ("rtcAttachGeometry", ctypes.c_uint, [_P, _P]),
            ("rtcReleaseGeometry", None, [_P]),
            ("rtcCommitScene", None, [_P]),
            ("rtcReleaseScene", None, [_P])):
        fn = getattr(lib, name)
        fn.restype, fn.argtypes = res, args
    return lib


_lib = _library()
_device = None
_device_lock = threading.Lock()
# Addresses of rtcIntersect1 and rtcOccluded1, both (scene, ray*, args*) -> void.
INTERSECT1 = ctypes.cast(_lib.rtcIntersect1, ctypes.c_void_p).value
OCCLUDED1 = ctypes.cast(_lib.rtcOccluded1, ctypes.c_void_p).value
def _dev() -> int:
    global _device
    with _device_lock:
        if _device is None:
            _device = _lib.rtcNewDevice(None)
        return _device


class RtcScene:
    """One committed Embree scene of a mesh's triangles: vertices (v, 3), faces (f, 3);
    `handle` is the RTCScene pointer as an int."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        v = np.ascontiguousarray(vertices, np.float32)
        f = np.ascontiguousarray(faces, np.uint32)
        if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
            raise ValueError(f"RtcScene: vertices (v, 3) and faces (f, 3), got {v.shape} "
                             f"and {f.shape}")
        self.handle = _lib.rtcNewScene(_dev())
        _lib.rtcSetSceneFlags(self.handle, RTC_SCENE_FLAG_ROBUST)
        g = _lib.rtcNewGeometry(_dev(), RTC_GEOMETRY_TYPE_TRIANGLE)
        vb = _lib.rtcSetNewGeometryBuffer(g, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3,
                                          12, len(v))
        ib = _lib.rtcSetNewGeometryBuffer(g, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3,
                                          12, len(f))
        ctypes.memmove(vb, v.ctypes.data, v.nbytes)
        ctypes.memmove(ib, f.ctypes.data, f.nbytes)
        _lib.rtcCommitGeometry(g)
        _lib.rtcAttachGeometry(self.handle, g)
        _lib.rtcReleaseGeometry(g)
        _lib.rtcCommitScene(self.handle)

    def __del__(self):
        if getattr(self, "handle", 0):
            _lib.rtcReleaseScene(self.handle)
            self.handle = 0


