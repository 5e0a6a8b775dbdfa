"""Embree 4 called from compiled (numba) kernels, without a Python round trip per batch.

embreex traces one ray at a time in a Cython loop and returns numpy arrays, so a renderer on
top of it pays for a Python call, its argument checks and several temporary arrays per batch
and per bounce. Here the same Embree library (the one embreex ships) is bound with ctypes,
a scene is built from the same float32 vertices and triangles with the same flags as
:class:`embreex.rtcore_scene.EmbreeScene` (robust), and the kernels call ``rtcIntersect1``
and ``rtcOccluded1`` directly: the same single-ray queries, so the same hits.

The symbols are made visible to LLVM (``load_library_permanently``) and declared as
external functions, so the compiled kernels stay cacheable across processes.
"""

from __future__ import annotations

import ctypes
import glob
import os
import threading
import weakref

import numpy as np
from numba import njit, types

_RTC_GEOMETRY_TYPE_TRIANGLE = 0
_RTC_BUFFER_TYPE_INDEX = 0
_RTC_BUFFER_TYPE_VERTEX = 1
_RTC_FORMAT_UINT3 = 0x5003
_RTC_FORMAT_FLOAT3 = 0x9003
_RTC_SCENE_FLAG_ROBUST = 1 << 2

#: Float32 slots of one ray record (RTCRayHit: RTCRay 12 words, then RTCHit); the buffer is
#: longer than any Embree 4 build's RTCRayHit (instance ids) and aligned to 16 bytes.
RAY_WORDS = 64
INVALID_ID = 0xFFFFFFFF

_lock = threading.Lock()
_lib: ctypes.CDLL | None = None
_error: str | None = None


def _library_path() -> str | None:
    try:
        import embreex
    except ImportError:
        return None
    base = os.path.dirname(os.path.dirname(embreex.__file__))
    found = sorted(glob.glob(os.path.join(base, "embreex.libs", "libembree4*.so*")))
    return found[0] if found else None


def library() -> ctypes.CDLL | None:
    """The Embree 4 library embreex uses, loaded for ctypes and for LLVM; None if absent."""
    global _lib, _error
    with _lock:
        if _lib is not None or _error is not None:
            return _lib
        path = _library_path()
        if path is None:
            _error = "no libembree4 next to embreex"
            return None
        try:
            import llvmlite.binding as llvm

            llvm.load_library_permanently(path)
            lib = ctypes.CDLL(path)
            lib.rtcNewDevice.restype = ctypes.c_void_p
            lib.rtcNewDevice.argtypes = [ctypes.c_char_p]
            lib.rtcReleaseDevice.argtypes = [ctypes.c_void_p]
            lib.rtcNewScene.restype = ctypes.c_void_p
            lib.rtcNewScene.argtypes = [ctypes.c_void_p]
            lib.rtcSetSceneFlags.argtypes = [ctypes.c_void_p, ctypes.c_int]
            lib.rtcNewGeometry.restype = ctypes.c_void_p
            lib.rtcNewGeometry.argtypes = [ctypes.c_void_p, ctypes.c_int]
            lib.rtcSetNewGeometryBuffer.restype = ctypes.c_void_p
            lib.rtcSetNewGeometryBuffer.argtypes = [ctypes.c_void_p, ctypes.c_int, ctypes.c_uint, ctypes.c_int,
                                                    ctypes.c_size_t, ctypes.c_size_t]
            lib.rtcCommitGeometry.argtypes = [ctypes.c_void_p]
            lib.rtcAttachGeometry.restype = ctypes.c_uint
            lib.rtcAttachGeometry.argtypes = [ctypes.c_void_p, ctypes.c_void_p]
            lib.rtcReleaseGeometry.argtypes = [ctypes.c_void_p]
            lib.rtcCommitScene.argtypes = [ctypes.c_void_p]
            lib.rtcReleaseScene.argtypes = [ctypes.c_void_p]
            lib.rtcGetDeviceError.restype = ctypes.c_int
            lib.rtcGetDeviceError.argtypes = [ctypes.c_void_p]
            _lib = lib
        except (OSError, AttributeError, ImportError) as exc:
            _error = str(exc)
        return _lib


class DirectScene:
    """An Embree scene of one triangle mesh, queried from numba kernels by its handle."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray) -> None:
        lib = library()
        if lib is None:
            raise RuntimeError(f"Embree 4 is not available: {_error}")
        v = np.ascontiguousarray(vertices, dtype=np.float32)
        f = np.ascontiguousarray(faces, dtype=np.uint32)
        dev = lib.rtcNewDevice(None)
        scene = lib.rtcNewScene(dev)
        lib.rtcSetSceneFlags(scene, _RTC_SCENE_FLAG_ROBUST)
        geom = lib.rtcNewGeometry(dev, _RTC_GEOMETRY_TYPE_TRIANGLE)
        # Vertex stride 16 bytes (Embree may read 4 bytes past the last float3).
        vb = lib.rtcSetNewGeometryBuffer(geom, _RTC_BUFFER_TYPE_VERTEX, 0, _RTC_FORMAT_FLOAT3, 16, len(v))
        va = np.ctypeslib.as_array((ctypes.c_float * (4 * len(v))).from_address(vb)).reshape(-1, 4)
        va[:, :3] = v
        va[:, 3] = 0.0
        ib = lib.rtcSetNewGeometryBuffer(geom, _RTC_BUFFER_TYPE_INDEX, 0, _RTC_FORMAT_UINT3, 12, len(f))
        np.ctypeslib.as_array((ctypes.c_uint32 * (3 * len(f))).from_address(ib)).reshape(-1, 3)[:] = f
        lib.rtcCommitGeometry(geom)
        lib.rtcAttachGeometry(scene, geom)
        lib.rtcReleaseGeometry(geom)
        lib.rtcCommitScene(scene)
        err = lib.rtcGetDeviceError(dev)
        if err != 0:
            lib.rtcReleaseScene(scene)
            lib.rtcReleaseDevice(dev)
            raise RuntimeError(f"Embree error {err} while building the scene")
        self.handle = int(scene)
        self._finalizer = weakref.finalize(self, _release, lib, scene, dev)


def _release(lib: ctypes.CDLL, scene: int, dev: int) -> None:
    lib.rtcReleaseScene(scene)
    lib.rtcReleaseDevice(dev)


#: Rays per packet query (RTCRayHit8: AVX2's width; Embree's packet layout is the single
#: ray's, every field widened to LANES words, so field ``i`` of lane ``l`` is word i*LANES + l).
LANES = 8
#: Words of a packet buffer: RTCRayHit8 (<= 256 words with instance ids), a shadow RTCRay8
#: (128), the two valid masks (16 each), and 64-byte alignment slack.
PACKET_WORDS = 416 + 16


def ray_buffer() -> np.ndarray:
    """A per-thread ray record: float32 words, padded so a 16-byte aligned record fits."""
    return np.zeros(RAY_WORDS + 4, dtype=np.float32)


def packet_buffer() -> np.ndarray:
    """A per-thread packet record (:func:`packet_record`): a ray-hit packet, a shadow-ray
    packet and their valid masks."""
    return np.zeros(PACKET_WORDS, dtype=np.float32)


# Pointers pass as uint64 (same registers as pointers in the x86-64 and AArch64 ABIs).
rtc_intersect1 = types.ExternalFunction("rtcIntersect1", types.void(types.uint64, types.uint64, types.uint64))
rtc_occluded1 = types.ExternalFunction("rtcOccluded1", types.void(types.uint64, types.uint64, types.uint64))
_pk_sig = types.void(types.uint64, types.uint64, types.uint64, types.uint64)   # (valid*, scene, rays*, args*)
rtc_intersect8 = types.ExternalFunction("rtcIntersect8", _pk_sig)
rtc_occluded8 = types.ExternalFunction("rtcOccluded8", _pk_sig)


@njit(nogil=True, cache=True, inline="always")
def packet_record(buf):  # pragma: no cover
    """(word offset of the 64-byte aligned packet record in ``buf``, its address): the hit
    packet at ``o``, the shadow packet at ``o + 256``, their valid masks at ``o + 384`` and
    ``o + 400``."""
    base = buf.ctypes.data
    addr = ((base + 63) // 64) * 64
    return (addr - base) // 4, addr


@njit(nogil=True, cache=True, inline="always")
def record(buf):  # pragma: no cover
    """(address, float32 word offset) of the 16-byte aligned ray record inside ``buf``."""
    base = buf.ctypes.data
    addr = ((base + 15) // 16) * 16
    return addr, (addr - base) // 4


@njit(nogil=True, cache=True, inline="always")
def set_ray(f, u, o, ox, oy, oz, dx, dy, dz, tfar):  # pragma: no cover
    """Fill the RTCRay (and reset the RTCHit ids) at word ``o`` of ``f`` (float32) / ``u`` (uint32 view)."""
    f[o + 0] = ox
    f[o + 1] = oy
    f[o + 2] = oz
    f[o + 3] = 0.0
    f[o + 4] = dx
    f[o + 5] = dy
    f[o + 6] = dz
    f[o + 7] = 0.0
    f[o + 8] = tfar
    u[o + 9] = INVALID_ID
    u[o + 10] = 0
    u[o + 11] = 0
    u[o + 17] = INVALID_ID
    u[o + 18] = INVALID_ID
    u[o + 19] = INVALID_ID

