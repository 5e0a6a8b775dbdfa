"""Embree renderer of the simulator twin: per-pixel complex phasors of the emitter's light.

For every camera sample a path is traced from the camera; at every surface vertex the
point emitter is connected by a shadow ray (next-event estimation). A connection at vertex
``k`` carries the optical power ``w`` (W) it delivers onto the pixel and its optical path
length ``L`` (camera -> x0 -> ... -> xk -> emitter). Per modulation frequency ``f`` and
harmonic ``h`` the renderer accumulates ``sum w exp(+i 2 pi h f L / c)``.

Radiometry (docs/scene-format.md): ``I(theta) = P p(theta)/norm``; irradiance
``E = I cos(theta_s)/r^2``; radiance ``L = f_r E``; pixel power by the camera equation
``P = L A_ap cos^4(alpha) a_pix / f^2`` with ``A_ap = pi (f/2N)^2``. Indirect light:
cosine-weighted bounce sampling, throughput ``f_r * pi`` per bounce.

Work is split into chunks of whole pixels (all samples of a pixel in one chunk), run on a
thread pool: embreex and the compiled per-ray kernels (:mod:`tofhil.sim.kernels`) release
the GIL, and chunks write disjoint pixel ranges.
"""

from __future__ import annotations

import functools
import math
import os
import sys
import threading
import warnings
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from tofhil import C_M_PER_S
from tofhil.camera import CameraModel
from tofhil.content_cache import LRUCache, content_digest
from tofhil.lens_models import MAX_ITER as LENS_MAX_ITER
from tofhil.errors import TofhilError
from tofhil.progress import Progress, no_progress
from tofhil.sim import dielectric, embree4, kernels
from tofhil.sim.geometry import BATCH, RAY_EPSILON_M, Geometry, WorkerPool
from tofhil.sim.radiometry import DEFAULT_PIXEL_PITCH_M, aperture_area_m2, pixel_area_normalized
from tofhil.sim.scene import Scene, Texture



@dataclass
class RenderResult:
    """Rendered phasors and ground truth of one view. Arrays are ``[..., H, W]``."""

    freq_hz: np.ndarray
    harmonics: tuple[int, ...]
    phasor: np.ndarray                   # complex128 [F, NH, H, W], W (watts) * exp(+i 2 pi h f L/c)
    power_w: np.ndarray                  # [H, W] emitter power on the pixel (sum of w)
    ambient_power_w: np.ndarray          # [H, W] ambient light power on the pixel
    radial_m: np.ndarray                 # [H, W] radial distance of the first hit of the centre ray
    object_id: np.ndarray                # [H, W] int32 object index, -1 = background
    phasor_direct: np.ndarray | None = None
    phasor_indirect: np.ndarray | None = None
    transient: np.ndarray | None = None  # [T, H, W] power per optical-path-length bin
    transient_edges_m: np.ndarray | None = None
    camera: CameraModel | None = None
    samples_per_pixel: int = 1
    rays_traced: int = 0                 # closest-hit plus shadow rays sent to Embree
    bounces: int = 0
    #: [H, W] ambient power on the pixel per W/m^2 of ambient irradiance (m^2): the ambient
    #: light is linear in the irradiance, so a cached render serves any ambient level.
    ambient_power_per_irradiance: np.ndarray | None = None
    #: [B + 1, O, H, W] emitter power on the pixel (W) by bounce count (0 = direct) and by the
    #: object the light came from (``render(..., multipath_shares=True)``; see :mod:`multipath`).
    share_power_w: np.ndarray | None = None


# --------------------------------------------------------------------------- set-up
def _render_setting(scene: Scene, key: str, given: Any, default: Any) -> Any:
    return given if given is not None else getattr(scene.render, key, default)


def _materials_table(scene: Scene) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rho_d = np.array([scene.materials[o.material].reflectance for o in scene.objects])
    rho_s = np.array([scene.materials[o.material].glossy_reflectance for o in scene.objects])
    n_s = np.array([scene.materials[o.material].glossy_exponent for o in scene.objects])
    return rho_d, rho_s, n_s


def _object_texture(scene: Scene, obj: Any) -> Texture | None:
    """The texture on an object: a board's printed pattern (its reflectances times the
    material's, 1 by default), else its material's texture."""
    if obj.type == "board":
        return Texture("image", image=obj.board.reflectance_image())
    return scene.materials[obj.material].texture


def content_key(*parts: Any) -> str:
    """A digest of what ``parts`` hold (:func:`tofhil.content_cache.content_digest`), a
    Scene's fields that do not change a render left out: equal content gives equal keys,
    whatever object identity or dictionary order."""
    return content_digest(*parts, skip_fields={Scene: _NOT_RENDERED})


#: Scene fields that do not change a render (effects and expression parameters are applied
#: in the scene already).
_NOT_RENDERED = frozenset({"effects", "params", "source", "text", "name", "description", "rgb_camera"})


# Embree scenes and per-pixel view arrays, keyed by content: renders of one scene with a
# moved camera or other materials (as while fitting) share them.
_GEOMETRY = LRUCache(4, thread_safe=True)
# (two each: at camera resolution an entry is 10-20 MB, and a fit makes a new pose or camera
# every evaluation; the base camera's rays stay cached on its CameraModel)
_VIEWS = LRUCache(2, thread_safe=True)
_CAMERAS = LRUCache(2, thread_safe=True)


def scene_geometry(scene: Scene) -> Geometry:
    """The scene's Embree geometry (shared by every scene with the same objects)."""
    key = content_key([(o.type, o.params, o.pose, o.mesh if o.type == "mesh" else None) for o in scene.objects])
    geom = _GEOMETRY.get(key)
    if geom is None:
        geom = Geometry.build(scene)
        _GEOMETRY.put(key, geom)
    return geom


def _camera_arrays(camera: CameraModel, pixels: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Per-pixel arrays of a camera (its pose aside): centre rays, pixel area, cos^4. With
    ``pixels`` (flat bool mask) a camera not seen whole yet gets them only there (elsewhere
    as a pixel that sees nothing; a fit of the lens distortion makes a new camera every
    evaluation), each value computed as for the whole grid."""
    key = content_key(camera)
    arrays = _CAMERAS.get(key)
    if arrays is not None:
        return arrays
    if pixels is None:
        rays, area, ok = _seen(camera.rays.reshape(-1, 3), pixel_area_normalized(camera).ravel())
    else:
        key = content_key(key, "pixels", np.packbits(pixels))
        arrays = _CAMERAS.get(key)
        if arrays is not None:
            return arrays
        idx = np.flatnonzero(pixels)
        v, u = np.divmod(idx, camera.width)
        u, v = u.astype(np.float64), v.astype(np.float64)
        at_rays, at_area, at_ok = _seen(camera.pixel_rays(u, v), pixel_area_normalized(camera, u, v))
        # the other pixels as a pixel that sees nothing (checked and mended on these only: a
        # fit of the lens makes a new camera at every evaluation)
        rays = np.zeros((pixels.size, 3))
        rays[:, 2] = 1.0
        rays[idx] = at_rays
        area = np.zeros(pixels.size)
        area[idx] = at_area
        ok = np.zeros(pixels.size, dtype=bool)
        ok[idx] = at_ok
    arrays = {"rays": rays, "area": area, "cos4": rays[:, 2] ** 4, "key": key, "ok": ok}
    _CAMERAS.put(key, arrays)
    return arrays


def _seen(rays: np.ndarray, area: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rays, pixel areas and which pixels see: a pixel the lens maps no ray to (beyond the
    fold of its model) or whose ray points 90 degrees or more off axis (a fisheye) sees
    nothing: weight 0, a finite ray for Embree."""
    ok = np.isfinite(rays).all(axis=1) & (rays[:, 2] > 0)
    if not ok.all():
        rays = np.where(ok[:, None], rays, np.array([0.0, 0.0, 1.0]))
    return rays, np.where(ok & np.isfinite(area), area, 0.0), ok


def _view_arrays(camera: CameraModel, pose: np.ndarray, pixels: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Per-pixel arrays of a camera at a pose (repeated renders of one view, e.g. while
    fitting, share them; renders of one camera at other poses share its rays and areas)."""
    cam = _camera_arrays(camera, pixels)
    key = content_key(cam["key"], pose)
    view = _VIEWS.get(key)
    if view is not None:
        return view
    rays = cam["rays"]
    world = np.array(_rotate(rays, pose[:3, :3]), dtype=np.float64)  # writable: one kernel type
    view = {"rays": rays, "world": world, "world32": world.astype(np.float32), "area": cam["area"],
            "cos4": cam["cos4"], "ok": cam["ok"]}
    _VIEWS.put(key, view)
    return view


# Read-only constants of a frame's size (0..n-1, zeros) that chunks slice instead of making
# their own (per-chunk arrays are fresh pages in the worker threads: page faults, ~2 us each).
_CONSTANTS = LRUCache(4, thread_safe=True)


def _constant(kind: str, n: int) -> np.ndarray:
    """``np.arange(n)`` (``"index"``) or ``np.zeros(n)`` (``"zeros"``), shared: never write to it."""
    a = _CONSTANTS.get((kind, n))
    if a is None:
        a = np.arange(n, dtype=np.int64) if kind == "index" else np.zeros(n)
        _CONSTANTS.put((kind, n), a)
    return a


class _FramePool:
    """The frame-sized arrays of earlier renders (phasors, power, ambient, maps), reused by
    later renders of the same size once nothing but the pool refers to them.

    Why: freed after every frame (~16 MB at 640 x 480), they go back to the kernel (glibc
    trims its heap), and the next frame's first writes page-fault them in again: ~4600 faults,
    ~12 ms of CPU per VGA frame on two threads, where the whole direct render costs ~45.
    A set is reused only when no array of it is referred to from outside (the caller dropped
    the result; a numpy view holds its base, so views count); ``max_sets`` per size, so
    ``res = render(...)`` in a loop, whose previous result is alive during the call, reuses
    the set before it. At most ``max_bytes`` are kept (two VGA sets; at 512 x 512 a diagnosis's
    renders of several harmonics are ~27 MB a set, and holding more raised its peak memory).
    """

    def __init__(self, max_sets: int = 2, max_bytes: int = 48 << 20) -> None:
        self.max_sets, self.max_bytes = max_sets, max_bytes
        self._lock = threading.Lock()
        self._sets: list[tuple[Any, list[np.ndarray]]] = []     # oldest first

    @staticmethod
    def _unreferenced(arrays: list[np.ndarray]) -> bool:
        # references: the list, the loop variable, getrefcount's argument
        return all(sys.getrefcount(a) <= 3 for a in arrays)

    def take(self, key: Any) -> list[np.ndarray] | None:
        """A set of ``key`` nothing else refers to, out of the pool (None: make new arrays)."""
        with self._lock:
            for i, (k, arrays) in enumerate(self._sets):
                if k == key and self._unreferenced(arrays):
                    del self._sets[i]
                    return arrays
        return None

    def give(self, key: Any, arrays: list[np.ndarray]) -> None:
        """Keep ``arrays`` for a later render (the oldest sets beyond the bounds are dropped)."""
        with self._lock:
            self._sets.append((key, arrays))
            same = [i for i, (k, _) in enumerate(self._sets) if k == key]
            for i in reversed(same[:-self.max_sets]):
                del self._sets[i]
            while sum(a.nbytes for _, arrays in self._sets for a in arrays) > self.max_bytes and len(self._sets) > 1:
                del self._sets[0]


_FRAMES = _FramePool()

#: The uniforms of chunks rendered for some of their pixels (:meth:`_Context._chunk_uniforms`).
_UNIFORMS = LRUCache(256, 16 << 20, nbytes=lambda a: a.nbytes, thread_safe=True)


def _pixel_weights(view: dict[str, Any], scale: float) -> tuple[np.ndarray, np.ndarray]:
    """``scale * area`` and ``scale * area * cos^4`` per pixel of a view, made once per scale
    (the aperture area over the samples per pixel) and kept in the view's cache entry."""
    weights = view.setdefault("weights", {})
    w = weights.get(scale)
    if w is None:
        if len(weights) >= 4:              # (a fit of the f-number makes a new scale each time)
            weights.clear()
        pix = scale * view["area"]
        w = weights[scale] = (pix, pix * view["cos4"])
    return w


class _Context:
    """Everything a chunk worker needs, precomputed once per render call."""

    def __init__(self, scene: Scene, camera: CameraModel, freq_hz: np.ndarray, harmonics: tuple[int, ...],
                 spp: int, bounces: int, seed: int, separate: bool, transient_edges: np.ndarray | None,
                 subpixel: bool, sampler: str, pose: np.ndarray, shares: bool = False,
                 pixels: np.ndarray | None = None) -> None:
        self.scene, self.camera = scene, camera
        # Only these pixels are traced (flat bool mask), each with exactly the samples of a
        # full render: the chunks, their random streams and the sample order are the full
        # render's, so a traced pixel's value is bit-identical to the full frame's.
        self.pixels = pixels
        # Multipath shares: one accumulator row per (bounce, source object) instead of
        # direct/indirect, and a 0 Hz channel last whose real part is the power of each row.
        self.n_obj = len(scene.objects) if shares else 0
        self.rows = (bounces + 1) * self.n_obj if shares else (2 if bounces else 1)
        self.geom = scene_geometry(scene)
        self.spp, self.bounces, self.seed = spp, bounces, seed
        self.sampler = sampler
        self.dims = 4 + 2 * bounces
        self.share = camera_ray_share(spp, bounces)
        if sampler == "sobol" and spp > 1:
            self.sobol = _sobol_points(spp, bounces, self.share)
        self.subpixel = subpixel and spp > 1
        self.thin_lens = scene.thin_lens
        self.H, self.W = camera.shape
        # Phase per metre of optical path for every (f, h), flattened [F*NH].
        self.k = (2 * np.pi / C_M_PER_S) * (np.asarray(freq_hz)[:, None] *
                                            np.asarray(harmonics, dtype=np.float64)[None, :]).ravel()
        if shares:
            self.k = np.append(self.k, 0.0)
        self.rho_d, self.rho_s, self.n_s = (np.asarray(a, dtype=np.float64) for a in _materials_table(scene))
        self.glossy = bool(np.any(self.rho_s > 0))
        self.textured = [(i, _object_texture(scene, o)) for i, o in enumerate(scene.objects)
                         if _object_texture(scene, o) is not None]
        self.inv_pose = [np.linalg.inv(o.pose) for o in scene.objects]
        R, t = pose[:3, :3], pose[:3, 3]
        self.R, self.t = R, t
        self.emitter_pos = R @ scene.emitter.offset_m + t
        self.emitter_axis = R @ scene.emitter.axis
        self.emitter = scene.emitter
        pitch = camera.pixel_pitch_m or DEFAULT_PIXEL_PITCH_M
        self.focal_m = camera.fx * pitch
        n_f = scene.radiometric_f_number
        self.aperture_radius_m = self.focal_m / (2 * n_f)
        self.aperture_area_m2 = aperture_area_m2(camera, n_f)
        self.focus_m = scene.focus_distance_m
        view = _view_arrays(camera, pose, pixels)
        # Per-pixel weight without cos^4: A_ap * pixel area (normalised coords) / spp, and with
        # it (centre rays); kept with the view: two frame-sized products per render otherwise,
        # on the serial path before the chunks start. Read only (the wavefront loop copies).
        self.pix_weight, self.centre_weight = _pixel_weights(view, self.aperture_area_m2 / spp)
        self.ambient = scene.ambient_irradiance_w_m2
        self.edges = transient_edges
        self.centre_rays = view["rays"]
        self.centre_world = view["world"]
        self.centre_world32 = view["world32"]
        self.centre_ok = view["ok"]          # false: the pixel has no ray (it sees nothing)
        self._origin32: np.ndarray | None = None
        prof = scene.emitter.profile
        # Beam profile (I = i0 p): cos^n in the kernels; -1: tabulated, `beam` for the fused
        # loop (the wavefront loop's vertex kernel leaves it to numpy).
        self.cos_n = float(prof.n) if prof.kind == "cos_n" else -1.0
        self.i0 = scene.emitter.power_w / prof.solid_angle_norm_sr
        self.beam = _beam_table(prof)
        # The fused path loop covers uniform reflectances and any beam; textures take the
        # wavefront loop below.
        self.fused = (self.geom.direct is not None and not self.textured
                      and os.environ.get("TOFHIL_RENDER_WAVEFRONT", "") in ("", "0"))
        self.glass = dielectric.dielectric_tables(scene)
        # The compiled loop writes every pixel's radial distance and object itself (one centre
        # ray per pixel, every pixel traced): the frame's maps need no fill beforehand.
        self.maps_in_place = self.fused and spp == 1 and not self.subpixel and not self.thin_lens and pixels is None
        if self.glass.any:
            _check_glass(scene, self.glass, self.fused and self.cos_n >= 0, t, self.emitter_pos)
            if shares:
                raise TofhilError("multipath shares are not computed through glass or media", field="multipath_shares",
                                  expected="a scene without materials with ior or scattering_per_m")

    @property
    def origin32(self) -> np.ndarray:
        """Float32 pinhole origins for one chunk's primary rays (a chunk holds <= BATCH + spp);
        made when the wavefront loop first needs them (the fused loop does not: 0.8 MB a frame)."""
        if self._origin32 is None:
            n = min(self.camera.width * self.camera.height * self.spp, BATCH + self.spp)
            o32 = np.empty((n, 3), dtype=np.float32)
            o32[:] = self.t
            self._origin32 = o32
        return self._origin32

    # ------------------------------------------------------------------ shading helpers
    def reflectance(self, obj: np.ndarray, x: np.ndarray) -> np.ndarray:
        """Diffuse reflectance at world points ``x`` of objects ``obj`` (textures applied)."""
        rho = self.rho_d[obj]
        for i, tex in self.textured:
            m = obj == i
            if not np.any(m):
                continue
            xl = x[m] @ self.inv_pose[i][:3, :3].T + self.inv_pose[i][:3, 3]
            if tex.kind == "checker":
                # Boundaries at multiples of size_m in local x, y and half-way between them in
                # z, so a plane (local z = 0) sits mid-cell instead of on a rounding edge.
                q = xl / tex.size_m
                q[:, 2] += 0.5
                cell = np.floor(q).astype(np.int64).sum(axis=1)
                rho[m] = np.where(cell % 2 == 0, tex.values[0], tex.values[1])
            else:
                lo, hi = self.geom.local_bounds[i]
                img = tex.image
                span = np.where(hi - lo > 0, hi - lo, 1.0)
                col = np.clip(((xl[:, 0] - lo[0]) / span[0] * img.shape[1]).astype(np.int64), 0, img.shape[1] - 1)
                row = np.clip(((xl[:, 1] - lo[1]) / span[1] * img.shape[0]).astype(np.int64), 0, img.shape[0] - 1)
                rho[m] = self.rho_d[i] * img[row, col]
        return rho

    def uniforms(self, rng: np.random.Generator, npix: int, keep_pix: np.ndarray | None = None) -> np.ndarray:
        """Per-sample uniforms in [0, 1)^D for ``npix`` pixels x ``spp`` samples.

        ``random``: independent uniforms (plain Monte Carlo, error ~ 1/sqrt(spp)).
        ``sobol``: the same Sobol' points in every pixel (:func:`_sobol_points`), XORed with a
        random 32-bit vector per pixel (a random digital shift): every sample is uniform on
        [0, 1)^D (unbiased per pixel) and each pixel's points keep the Sobol' net structure
        (a Cranley-Patterson rotation, used before, does not, and converged more slowly:
        docs/scene-format.md, ``render:``).
        Either way the camera columns 0-3 are the same within each group of ``share``
        consecutive samples of a pixel: they continue one camera ray (:func:`camera_ray_share`).
        """
        if self.sampler == "random" or self.spp == 1:
            u = rng.random((npix * self.spp, self.dims))
            if self.share > 1:   # a group's camera ray is its first sample's
                g = u.reshape(-1, self.share, self.dims)
                g[:, 1:, :4] = g[:, :1, :4]
            return u if keep_pix is None else u.reshape(npix, self.spp, self.dims)[keep_pix].reshape(-1, self.dims)
        shift = rng.integers(0, 1 << 32, (npix, self.dims), dtype=np.uint32)
        if keep_pix is not None:  # (drawn for every pixel of the chunk: the full render's stream)
            shift = shift[keep_pix]
        u = np.empty((len(shift) * self.spp, self.dims))
        kernels.sobol_digital_shift(self.sobol, shift, u)
        return u

    def _chunk_uniforms(self, chunk: int, npix: int, keep_pix: np.ndarray | None) -> np.ndarray:
        """:meth:`uniforms` of a chunk from its own stream; those of some pixels are kept (a
        fit renders the same pixels at every evaluation, and drawing the chunk's whole stream
        to keep a few of its pixels is most of a small render's sampling)."""
        if keep_pix is None:
            return self.uniforms(np.random.default_rng([self.seed, chunk]), npix, keep_pix)
        key = (self.sampler, self.spp, self.dims, self.share, self.seed, chunk, npix,
               content_digest(np.asarray(keep_pix, dtype=bool)))
        u = _UNIFORMS.get(key)
        if u is None:
            u = self.uniforms(np.random.default_rng([self.seed, chunk]), npix, keep_pix)
            u.setflags(write=False)
            _UNIFORMS.put(key, u)
        return u

    # ------------------------------------------------------------------ one chunk
    def run_chunk(self, chunk: int, p0: int, p1: int, dest: dict[str, np.ndarray] | None = None
                  ) -> dict[str, np.ndarray]:
        """Trace pixels ``p0:p1``; with ``dest`` (the frame's accumulators) the fused loop
        adds into them in place, otherwise the chunk's own arrays are returned."""
        npix = p1 - p0
        if dest is not None and "clear" in dest:
            for a in dest["clear"]:         # a reused frame (render's _FRAMES): this chunk's pixels
                a[..., p0:p1] = 0
        pix, U, keep_pix, origins, dirs, beta, path0 = self._camera_rays(chunk, p0, p1)
        out, acc_re, acc_im, power, ambient_unit, trans, edges = self._accumulators(npix, p0, p1, dest)
        geom = self.geom
        smooth = geom.vnormal is not None
        vnormal = geom.vnormal if smooth else np.zeros((1, 3, 3))

        # Live paths: ray origins (one shared pinhole, or one per path), directions, the
        # path length so far, throughput, pixel (chunk-local) and row in U.
        org = np.ascontiguousarray(np.atleast_2d(origins), dtype=np.float64)
        shared = org.shape[0] == 1 and len(dirs) != 1
        dirs = np.ascontiguousarray(dirs, dtype=np.float64)
        # (one sample per pixel: the chunk-local pixel of sample s is s)
        local = _constant("index", self.H * self.W)[:npix] if self.spp == 1 and keep_pix is None else pix - p0
        if self.fused:
            return self._run_fused(npix, p0, p1, org, shared, dirs, path0, beta, local, U, out, acc_re, acc_im,
                                   power, ambient_unit, edges, trans, vnormal, smooth,
                                   dest if dest is not None else {}, keep_pix)
        return self._run_wavefront(npix, p0, p1, pix, org, shared, dirs, path0, beta, local, U, out, acc_re, acc_im,
                                   power, ambient_unit, edges, trans, vnormal, smooth, keep_pix)

    def _camera_rays(self, chunk: int, p0: int, p1: int) -> tuple[np.ndarray, np.ndarray, np.ndarray | None,
                                                                   Any, np.ndarray, np.ndarray, np.ndarray]:
        """The camera rays of pixels ``p0:p1``: each sample's pixel, the chunk's uniforms, the
        pixels kept (None: all), the ray origins (the pinhole, or one per sample through a thin
        lens), directions (world), throughput and optical path already travelled."""
        npix = p1 - p0
        spp = self.spp
        pix = _constant("index", self.H * self.W)[p0:p1] if spp == 1 else np.repeat(np.arange(p0, p1), spp)
        # [samples, D] uniforms: subpixel, lens, 2 per bounce (none needed for centre rays
        # through the pinhole without bounces).
        need_u = self.subpixel or self.thin_lens or self.bounces > 0 or self.glass.scattering
        keep_pix = None if self.pixels is None else self.pixels[p0:p1]
        if keep_pix is not None and keep_pix.all():
            keep_pix = None
        # (the chunk's uniforms are drawn for all its pixels, the full render's stream, and
        # kept for the pixels asked for)
        U = self._chunk_uniforms(chunk, npix, keep_pix) if need_u else np.zeros((0, self.dims))
        if keep_pix is not None:
            pix = pix[keep_pix[pix - p0]]
        if self.subpixel and not self.thin_lens:
            # Sub-pixel rays through the pinhole: generated, weighted and rotated in one
            # compiled pass (the camera model's arithmetic, no per-sample temporaries).
            dirs, beta = np.empty((len(U), 3)), np.empty(len(U))
            cam = self.camera
            kernels.subpixel_rays(np.arange(p0, p1) if keep_pix is None else p0 + np.flatnonzero(keep_pix), spp,
                                  self.W, U, cam.fx, cam.fy, cam.cx, cam.cy,
                                  np.asarray(cam.kernel_coeffs), LENS_MAX_ITER, self.R,
                                  not np.array_equal(self.R, np.eye(3)), self.pix_weight, dirs, beta,
                                  cam.is_fisheye, self.share)
        elif self.subpixel:
            uu = (pix % self.W) + U[:, 0] - 0.5
            vv = (pix // self.W) + U[:, 1] - 0.5
            d_cam = self.camera.pixel_rays(uu, vv)
            no_ray = ~(d_cam[:, 2] > 0)       # (as the compiled pass: weight 0, a finite ray)
            d_cam[no_ray] = (0.0, 0.0, 1.0)
            beta = np.where(no_ray, 0.0, self.pix_weight[pix] * d_cam[:, 2] ** 4)
        elif keep_pix is not None:
            d_cam = self.centre_rays[pix]
            beta = self.centre_weight[pix]
        else:
            d_cam = self.centre_rays[p0:p1] if spp == 1 else np.repeat(self.centre_rays[p0:p1], spp, axis=0)
            beta = self.centre_weight[p0:p1] if spp == 1 else self.centre_weight[pix]
        if self.thin_lens:
            # Sample the aperture disk; every ray through the same pixel position meets the
            # pinhole ray on the focal plane. The lens makes optical paths to the focus point
            # equal, so L_cam = |F| + (t - |F - a|).
            r = self.aperture_radius_m * np.sqrt(U[:, 2])
            phi = 2 * np.pi * U[:, 3]
            a = np.stack([r * np.cos(phi), r * np.sin(phi), np.zeros_like(r)], axis=1)
            focus = d_cam * (self.focus_m / d_cam[:, 2])[:, None]
            to_f = focus - a
            dist_f = np.linalg.norm(to_f, axis=1)
            dirs_cam = to_f / dist_f[:, None]
            path0 = np.linalg.norm(focus, axis=1) - dist_f
            origins = _rotate(a, self.R) + self.t
            dirs = _rotate(dirs_cam, self.R)
        else:
            path0 = _constant("zeros", len(pix))   # no camera path before the pinhole
            origins = self.t                  # one shared origin: the pinhole
            if keep_pix is not None and not self.subpixel:
                dirs = self.centre_world[pix]
            elif not self.subpixel:  # (sub-pixel rays: the compiled pass above made them)
                cw = self.centre_world[p0:p1]
                dirs = cw if spp == 1 else np.repeat(cw, spp, axis=0)
        return pix, U, keep_pix, origins, dirs, beta, path0

    def _accumulators(self, npix: int, p0: int, p1: int, dest: dict[str, np.ndarray] | None
                      ) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                 np.ndarray]:
        """The chunk's output map and the arrays its light is added into (the frame's own
        with ``dest`` and the fused loop, else the chunk's), and the transient's bin edges."""
        nk = len(self.k)
        out: dict[str, np.ndarray] = {}
        edges = self.edges if self.edges is not None else np.zeros(1)
        if dest is not None and self.fused:
            # The compiled loop adds into the frame's own arrays (disjoint pixel ranges).
            acc_re, acc_im = dest["re"][:, :, p0:p1], dest["im"][:, :, p0:p1]
            power, ambient_unit = dest["power"][p0:p1], dest["ambient_unit"][p0:p1]
            # (no transient: the kernels never index it, one element will do)
            trans = dest["trans"][p0:p1] if dest.get("trans") is not None else np.zeros((1, 1))
            out["in_place"] = np.array(True)
        else:
            rows = self.rows                     # no indirect row without bounces
            acc_re = np.zeros((rows, nk, npix))  # [direct/indirect, f*h, pixel]
            acc_im = np.zeros((rows, nk, npix))
            power = np.zeros(npix)
            ambient_unit = np.zeros(npix)
            trans = np.zeros((npix, max(len(edges) - 1, 1)))
        return out, acc_re, acc_im, power, ambient_unit, trans, edges

    def _run_wavefront(self, npix: int, p0: int, p1: int, pix: np.ndarray, org: np.ndarray, shared: bool,
                       dirs: np.ndarray, path0: np.ndarray, beta: np.ndarray, local: np.ndarray, U: np.ndarray,
                       out: dict[str, np.ndarray], acc_re: np.ndarray, acc_im: np.ndarray, power: np.ndarray,
                       ambient_unit: np.ndarray, edges: np.ndarray, trans: np.ndarray, vnormal: np.ndarray,
                       smooth: bool, keep_pix: np.ndarray | None) -> dict[str, np.ndarray]:
        """The wavefront loop (the path tracer outside the fused kernel: multipath shares,
        transients, glass): every live path's hit, its emitter connection and its next bounce,
        one bounce of all paths at a time; returns the chunk's arrays."""
        spp = self.spp
        geom = self.geom
        path_in = path0
        # (connect_and_bounce updates the throughput in place: never the cached pixel weights)
        beta = np.array(beta, dtype=np.float64)
        ambient = np.zeros(npix)
        sid = np.arange(len(pix))
        src = np.zeros(len(pix), dtype=np.int64)     # the object the light came from (shares)
        rays = 0
        for bounce in range(self.bounces + 1):
            if bounce == 0 and shared and not self.subpixel and keep_pix is None and len(dirs) <= len(self.origin32):
                o32, d32 = self.origin32[:len(dirs)], self.centre_world32[p0:p1]
                if spp > 1:
                    d32 = np.repeat(d32, spp, axis=0)
            else:
                o32 = np.ascontiguousarray(np.broadcast_to(org, dirs.shape) if shared else org, dtype=np.float32)
                d32 = np.ascontiguousarray(dirs, dtype=np.float32)
            r = geom.embree.run(o32, d32, output=1)
            rays += len(dirs)
            prim = r["primID"]
            idx = np.flatnonzero(prim >= 0)
            m = len(idx)
            x, ngf, nf, wo, wi = (np.empty((m, 3)) for _ in range(5))
            r1, cos_s, cos_e, t_hit, path, irr = (np.empty(m) for _ in range(6))
            so, sd = np.empty((m, 3), np.float32), np.empty((m, 3), np.float32)
            sdist = np.empty(m, np.float32)
            kernels.vertex(idx, prim, r["tfar"], r["u"], r["v"], org, shared, dirs, path_in, geom.plane_c,
                           geom.normal, vnormal, smooth, self.emitter_pos, self.emitter_axis, RAY_EPSILON_M,
                           self.cos_n, self.i0, x, ngf, nf, wo, wi, r1, cos_s, cos_e, t_hit, path, irr,
                           so, sd, sdist)
            obj = geom.tri_object[prim[idx]]
            if m < len(prim):
                src = src[idx]
            if bounce <= 1:
                src = obj.astype(np.int64)          # the seen object (direct) or the one that lit it
            if self.n_obj:
                which = bounce * self.n_obj + src
            else:
                which = np.full(m, 0 if bounce == 0 else 1, dtype=np.int64)
            if bounce == 0:
                if keep_pix is not None:
                    out["radial"], out["object_id"], n_c = self._centre_maps(p0, p1, keep_pix)
                    rays += n_c
                elif not self.subpixel and not self.thin_lens:
                    # Centre rays from the pinhole: the primary hits are the ground truth.
                    t_full = np.full(len(dirs), np.inf)
                    t_full[idx] = t_hit
                    o_full = np.full(len(dirs), -1, dtype=np.int32)
                    o_full[idx] = obj
                    out["radial"], out["object_id"] = t_full[::spp], o_full[::spp]
                else:
                    hc = geom.intersect(self.t, self.centre_world[p0:p1])
                    rays += npix
                    out["radial"] = hc.full(hc.t, np.inf)
                    out["object_id"] = hc.full(geom.tri_object[hc.prim], -1).astype(np.int32)
            if m < len(prim):                        # drop the paths that left the scene
                beta, local, sid = beta[idx], local[idx], sid[idx]
            if m == 0:
                break
            rho = self.reflectance(obj, x)
            if bounce == 0:
                albedo = beta * (rho + self.rho_s[obj])
                ambient_unit = np.bincount(local, albedo * (1.0 / np.pi), minlength=npix)
                if self.ambient > 0:
                    ambient = np.bincount(local, albedo * (self.ambient / np.pi), minlength=npix)
            if self.cos_n < 0:                       # tabulated beam profile
                irr = self.emitter.intensity_w_sr(cos_e) * np.maximum(cos_s, 0.0) / (r1 * r1)
            lit = np.flatnonzero(irr > 0)
            rs, ns = (self.rho_s[obj], self.n_s[obj]) if self.glossy else (np.zeros(m), np.zeros(m))
            blocked = np.zeros(m, dtype=np.bool_)
            if len(lit) == m:
                blocked = geom.embree.run(so, sd, dists=sdist, query="OCCLUDED") >= 0
            elif len(lit):
                blocked[lit] = geom.embree.run(so[lit], sd[lit], dists=sdist[lit], query="OCCLUDED") >= 0
            rays += len(lit)
            do_bounce = bounce < self.bounces
            if do_bounce:
                u1 = np.ascontiguousarray(U[sid, 4 + 2 * bounce])
                u2 = np.ascontiguousarray(U[sid, 5 + 2 * bounce])
                nb_org, nb_dir, nb_keep = np.empty((m, 3)), np.empty((m, 3)), np.empty(m, dtype=np.int64)
            else:
                u1 = u2 = np.zeros(0)
                nb_org = nb_dir = np.zeros((0, 3))
                nb_keep = np.zeros(0, dtype=np.int64)
            count = kernels.connect_and_bounce(
                irr, blocked, rho, rs, ns, nf, ngf, wo, wi, r1, x, beta, path,
                local, which, self.k, acc_re, acc_im, power, edges, trans, do_bounce,
                u1, u2, RAY_EPSILON_M, nb_org, nb_dir, nb_keep)
            if not do_bounce or count == 0:
                break
            keep = nb_keep[:count]
            org, dirs, shared = nb_org[:count], nb_dir[:count], False
            path_in, beta, local, sid, src = path[keep], beta[keep], local[keep], sid[keep], src[keep]

        out["re"], out["im"], out["power"], out["ambient"] = acc_re, acc_im, power, ambient
        out["ambient_unit"] = ambient_unit
        out["rays"] = np.array(rays)
        if self.edges is not None:
            out["transient"] = trans
        return out

    def _centre_maps(self, p0: int, p1: int, keep_pix: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
        """Radial distance and object of the centre ray of the chunk's pixels asked for
        (inf / -1 elsewhere), and the rays traced."""
        sel = np.flatnonzero(keep_pix)
        radial = np.full(p1 - p0, np.inf)
        oid = np.full(p1 - p0, -1, dtype=np.int32)
        if len(sel):
            hc = self.geom.intersect(self.t, self.centre_world[p0 + sel])
            radial[sel] = hc.full(hc.t, np.inf)
            oid[sel] = hc.full(self.geom.tri_object[hc.prim], -1).astype(np.int32)
        return radial, oid, len(sel)

    def _run_fused(self, npix: int, p0: int, p1: int, org: np.ndarray, shared: bool, dirs: np.ndarray,
                   path0: np.ndarray, beta: np.ndarray, local: np.ndarray, U: np.ndarray, out: dict,
                   acc_re: np.ndarray, acc_im: np.ndarray, power: np.ndarray, ambient_unit: np.ndarray,
                   edges: np.ndarray, trans: np.ndarray, vnormal: np.ndarray, smooth: bool,
                   out_maps: dict[str, np.ndarray], keep_pix: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """The chunk's paths in one compiled loop that calls Embree per ray (no textures):
        no per-bounce Python round trip and no per-ray temporary arrays."""
        geom = self.geom
        n = len(dirs)
        # One centre ray per pixel and the frame's maps at hand: the primary hits go straight
        # into them (no per-chunk arrays to copy over).
        direct_maps = "radial" in out_maps and self.maps_in_place and keep_pix is None
        if direct_maps:
            first_t, first_obj = out_maps["radial"][p0:p1], out_maps["object_id"][p0:p1]
        else:
            first_t = np.empty(n)
            first_obj = np.empty(n, dtype=np.int32)
        U2 = U if U.shape[0] else np.zeros((0, self.dims))
        if self.glass.any:
            g = self.glass
            rays = kernels.trace_paths_media(
                geom.direct.handle, embree4.ray_buffer(), org, shared, dirs,
                np.ascontiguousarray(path0, dtype=np.float64), np.ascontiguousarray(beta, dtype=np.float64),
                np.ascontiguousarray(local, dtype=np.int64), np.ascontiguousarray(U2), self.bounces,
                geom.normal, geom.plane_c, vnormal, smooth, geom.tri_object, self.rho_d, self.rho_s, self.n_s,
                g.ior, g.sigma_a, g.sigma_s, g.hg_g, g.centre, g.axes, g.half,
                self.emitter_pos, self.emitter_axis, RAY_EPSILON_M, self.cos_n, self.i0, self.k,
                acc_re, acc_im, power, ambient_unit, edges, trans, first_t, first_obj)
        else:
            rays = kernels.trace_paths(
                geom.direct.handle, embree4.packet_buffer(), org, shared, dirs,
                np.ascontiguousarray(path0, dtype=np.float64), np.ascontiguousarray(beta, dtype=np.float64),
                np.ascontiguousarray(local, dtype=np.int64), np.ascontiguousarray(U2), self.bounces,
                geom.normal, geom.plane_c, vnormal, smooth, geom.tri_object, self.rho_d, self.rho_s, self.n_s,
                self.emitter_pos, self.emitter_axis, RAY_EPSILON_M, self.cos_n, self.i0, self.beam, self.k,
                acc_re, acc_im, power, ambient_unit, edges, trans, first_t, first_obj, self.n_obj, self.share)
        if direct_maps:
            out["maps_in_place"] = np.array(True)
        elif keep_pix is not None:
            out["radial"], out["object_id"], n_c = self._centre_maps(p0, p1, keep_pix)
            rays += n_c
        elif not self.subpixel and not self.thin_lens:
            out["radial"], out["object_id"] = first_t[::self.spp], first_obj[::self.spp]
        else:
            hc = geom.intersect(self.t, self.centre_world[p0:p1])
            rays += npix
            out["radial"] = hc.full(hc.t, np.inf)
            out["object_id"] = hc.full(geom.tri_object[hc.prim], -1).astype(np.int32)
        out["re"], out["im"], out["power"] = acc_re, acc_im, power
        if "in_place" not in out:     # (in place: the frame's ambient is made from ambient_unit once)
            out["ambient"] = ambient_unit * self.ambient
        out["ambient_unit"] = ambient_unit
        out["rays"] = np.array(rays)
        if self.edges is not None:
            out["transient"] = trans
        return out


#: At most this many consecutive samples of a pixel continue one camera ray (a divisor of the
#: compiled loop's packet of 8, so a group never straddles two packets).
CAMERA_RAY_SHARE = 4
#: Sub-pixel positions (camera rays) per pixel below which samples do not share them.
MIN_CAMERA_RAYS = 64


def camera_ray_share(spp: int, bounces: int) -> int:
    """How many consecutive samples of a pixel continue one camera ray (splitting).

    The depth error of a multipath render is all in its indirect light (docs/scene-format.md,
    ``render:``, has the corner's figures), and a pixel's direct light hardly varies over its sub-pixel positions; so a group of samples
    shares the camera ray, its first vertex and that vertex's emitter connection (traced and
    added once, for the group), and each sample draws its own bounces from there. A sample
    is still one path: ``samples_per_pixel`` paths per pixel, ``spp / share`` sub-pixel
    positions. Unbiased (each path is distributed as before; only the paths of a group are
    correlated). None without bounces, and at least :data:`MIN_CAMERA_RAYS` sub-pixel
    positions per pixel are kept: where the direct light's sub-pixel variation is the error
    (a plane seen obliquely, no multipath), fewer positions would cost more than the rays
    saved.
    """
    if bounces <= 0:
        return 1
    share = CAMERA_RAY_SHARE
    while share > 1 and (spp % share or spp // share < MIN_CAMERA_RAYS):
        share //= 2
    return share


@functools.lru_cache(maxsize=16)
def _sobol_points(spp: int, bounces: int, share: int) -> np.ndarray:
    """The Sobol' points (unscrambled, uint32 [spp, 4 + 2B]; the per-pixel digital shift
    randomises them) in the renderer's column order: the bounce columns ``4 + 2b, 5 + 2b``
    take Sobol' dimensions ``2b, 2b + 1`` of the ``spp`` points, where the low dimensions'
    points are best stratified: the depth error is in the indirect light (on the corner this
    order needs fewer samples than the sub-pixel position first: docs/scene-format.md);
    the camera columns 0-3 take the next four dimensions of ``spp / share`` points, one per
    group of ``share`` samples that continue one camera ray."""
    from scipy.stats import qmc

    nb = 2 * bounces
    with warnings.catch_warnings():       # balance is best for 2^m points; any n is valid
        warnings.simplefilter("ignore")
        pts = qmc.Sobol(nb + 4, scramble=False, bits=32).random(spp)
    cam = pts[:spp // share, nb:]   # (an unscrambled sequence's first spp / share points)
    out = np.empty((spp, nb + 4), dtype=np.uint32)
    # (Sobol' floats with 32 bits are k / 2^32 exactly)
    out[:, 4:] = np.ldexp(pts[:, :nb], 32).astype(np.uint32)
    out[:, :4] = np.repeat(np.ldexp(cam, 32).astype(np.uint32), share, axis=0)
    out.setflags(write=False)  # (kept: every render of these settings shares it)
    return out


def _beam_table(prof: Any) -> np.ndarray:
    """A tabulated beam profile as the fused kernel reads it (:func:`kernels._beam`): rows
    theta_deg and relative intensity; one column when it is the same value over the whole
    sphere (isotropic), so the kernel skips the arccos. Empty for cos^n."""
    if prof.kind == "cos_n":
        return np.zeros((2, 0))
    th, va = np.asarray(prof.theta_deg, dtype=np.float64), np.asarray(prof.values, dtype=np.float64)
    if th[0] == 0.0 and th[-1] == 180.0 and np.all(va == va[0]):
        return np.array([[0.0], [va[0]]])
    return np.ascontiguousarray(np.stack([th, va]))


def _check_glass(scene: Scene, glass: dielectric.DielectricTables, fused: bool, camera_pos: np.ndarray,
                 emitter_pos: np.ndarray) -> None:
    """Refuse the glass set-ups the renderer does not model (rather than render them wrong)."""
    from tofhil.sim.geometry import object_mesh

    first = int(np.flatnonzero(glass.ior > 0)[0])
    if not fused:
        raise TofhilError("glass and media (materials with ior or scattering_per_m) render in the compiled "
                          "path loop only",
                          field=f"materials.{scene.objects[first].material}.ior",
                          expected="uniform reflectances (no textures), a cos_n beam profile, Embree 4 and "
                                   "TOFHIL_RENDER_WAVEFRONT unset")
    for i in np.flatnonzero(glass.ior > 0):
        f = f"objects[{i}]"
        if dielectric.inside_box(glass, i, np.stack([camera_pos, emitter_pos]), 2 * RAY_EPSILON_M).any():
            raise TofhilError(f"the camera or the emitter is inside the glass box {scene.objects[i].name!r}",
                              field=f + ".pose", expected="the camera and the emitter outside every glass or medium box")
        for j, other in enumerate(scene.objects):
            if j == i:
                continue
            v, _, _ = object_mesh(other)
            v = v @ other.pose[:3, :3].T + other.pose[:3, 3]
            if dielectric.inside_box(glass, i, v).any():
                raise TofhilError(f"object {other.name!r} reaches into the glass box {scene.objects[i].name!r}",
                                  field=f"objects[{j}].pose",
                                  expected="objects outside glass boxes (surfaces inside glass are not modelled)")


def _add_glints(ctx: "_Context", acc: np.ndarray, power: np.ndarray, trans: np.ndarray | None) -> None:
    """The emitter's images in the glass faces (:func:`tofhil.sim.dielectric.glints`): point
    sources that the path loop cannot hit, each added to the pixel its ray goes through."""
    geom, cam = ctx.geom, ctx.camera

    def blocked(o: np.ndarray, d: np.ndarray, dist: float) -> bool:
        return bool(geom.embree.run(o[None].astype(np.float32), d[None].astype(np.float32),
                                    dists=np.array([dist], np.float32), query="OCCLUDED")[0] >= 0)

    def intensity(cos_e: float) -> float:
        return float(ctx.emitter.intensity_w_sr(np.array([cos_e]))[0]) if cos_e > 0 else 0.0

    for g in dielectric.glints(ctx.glass, ctx.t, ctx.R[:, 2], ctx.emitter_pos, ctx.emitter_axis, intensity,
                               ctx.aperture_area_m2, blocked):
        d_cam = ctx.R.T @ g.direction
        if d_cam[2] <= 0 or g.power_w <= 0:
            continue
        col, row = np.rint(cam.project(d_cam)).astype(int)
        if not (0 <= col < ctx.W and 0 <= row < ctx.H):
            continue
        q = row * ctx.W + col
        acc[0, :, q] += g.power_w * np.exp(1j * ctx.k * g.opl_m)
        power[q] += g.power_w
        if trans is not None:
            b = np.searchsorted(ctx.edges, g.opl_m, side="right") - 1
            if 0 <= b < trans.shape[1]:
                trans[q, b] += g.power_w


def _rotate(v: np.ndarray, R: np.ndarray) -> np.ndarray:
    """``v @ R.T`` for [N, 3] rows without BLAS (tiny inner dimension; avoids BLAS threads)."""
    if np.array_equal(R, np.eye(3)):
        return v
    out = np.empty((len(v), 3))
    kernels.rotate_rows(np.ascontiguousarray(v, dtype=np.float64), np.ascontiguousarray(R, dtype=np.float64), out)
    return out


def _transient_edges(scene: Scene, geom: Geometry, bins: int | Sequence[float], bounces: int,
                     pose: np.ndarray) -> np.ndarray:
    if np.ndim(bins) == 1:
        edges = np.asarray(bins, dtype=np.float64)
        if len(edges) < 2 or np.any(np.diff(edges) <= 0):
            raise TofhilError("transient bin edges must increase", field="transient_bins",
                              expected="an integer or >= 2 increasing edges in m")
        return edges
    nb = int(bins)
    if nb < 1:
        raise TofhilError(f"got {bins!r}", field="transient_bins", expected="a positive integer")
    # Upper bound of any path: camera -> farthest vertex, bounces x bounding-box diagonal,
    # farthest vertex -> emitter.
    lo, hi = geom.world_bounds
    corners = np.array([[a[0], b[1], c[2]] for a in (lo, hi) for b in (lo, hi) for c in (lo, hi)])
    reach = np.linalg.norm(corners - pose[:3, 3], axis=1).max()
    diag = np.linalg.norm(hi - lo)
    lmax = 2 * reach + np.linalg.norm(scene.emitter.offset_m) + bounces * diag
    return np.linspace(0.0, lmax * 1.05 + 1e-9, nb + 1)


# --------------------------------------------------------------------------- public API
def render(scene: Scene, *, freq_hz: Sequence[float] | np.ndarray | None = None,
           harmonics: Sequence[int] = (1,), samples_per_pixel: int | None = None,
           bounces: int | None = None, seed: int | None = None, separate_direct: bool = False,
           transient_bins: int | Sequence[float] | None = None, camera: CameraModel | None = None,
           progress: Progress | None = None, threads: int | None = None, subpixel: bool | None = None,
           sampler: str | None = None, camera_pose: np.ndarray | None = None,
           multipath_shares: bool = False, pixels: np.ndarray | None = None) -> RenderResult:
    """Render the scene's emitter light as per-pixel phasors (see the module docstring).

    ``freq_hz`` defaults to the scene's sensor frequencies; ``samples_per_pixel``,
    ``bounces`` and ``subpixel`` to the scene's ``render:`` block (1, 0, true). With more than
    one sample per pixel and ``subpixel`` the samples are spread uniformly over the pixel
    (mixed pixels at depth edges); one sample goes through the pixel centre. ``camera``
    replaces the scene's camera model and ``camera_pose`` (4x4 camera-to-world) its pose, e.g.
    a distorted or re-posed camera while fitting; the scene itself is not changed.
    ``multipath_shares`` adds ``share_power_w``, the pixel's power by bounce count and by the
    object the light came from (:mod:`tofhil.sim.multipath`), from the same paths.
    ``pixels`` (bool ``[H, W]``): trace only these pixels (a fit's pixels); each is
    bit-identical to its value in the full render, the others are left at zero light, no hit.
    """
    cam = camera if camera is not None else scene.camera
    freq = scene.freq_hz if freq_hz is None else np.atleast_1d(np.asarray(freq_hz, dtype=np.float64))
    harm = tuple(int(h) for h in harmonics)
    if not harm or min(harm) < 1:
        raise TofhilError(f"got {harmonics!r}", field="harmonics", expected="harmonic orders >= 1")
    spp = int(_render_setting(scene, "samples_per_pixel", samples_per_pixel, 1))
    nb = int(_render_setting(scene, "bounces", bounces, 0))
    sub = bool(_render_setting(scene, "subpixel", subpixel, True))
    seed = int(_render_setting(scene, "seed", seed, 0))
    smp = str(_render_setting(scene, "sampler", sampler, "sobol"))
    if smp not in ("sobol", "random"):
        raise TofhilError(f"got {smp!r}", field="sampler", expected="'sobol' or 'random'")
    if spp < 1:
        raise TofhilError(f"got {spp}", field="samples_per_pixel", expected="an integer >= 1")
    if nb < 0:
        raise TofhilError(f"got {nb}", field="bounces", expected="an integer >= 0")
    geom = scene_geometry(scene)
    pose = scene.camera_pose if camera_pose is None else np.asarray(camera_pose, dtype=np.float64)
    if pose.shape != (4, 4) or not np.allclose(pose[:3, :3] @ pose[:3, :3].T, np.eye(3), atol=1e-6):
        raise TofhilError("not a rigid 4x4 transform", field="camera_pose",
                          expected="a 4x4 camera-to-world matrix with an orthonormal rotation")
    edges = None if transient_bins is None else _transient_edges(scene, geom, transient_bins, nb, pose)
    H, W = cam.shape
    if pixels is not None:
        pixels = np.asarray(pixels, dtype=bool)
        if pixels.shape != (H, W):
            raise TofhilError(f"got shape {pixels.shape}", field="pixels", expected=f"a bool mask of shape {(H, W)}")
        pixels = None if pixels.all() else pixels.ravel()
    ctx = _Context(scene, cam, freq, harm, spp, nb, seed, separate_direct, edges, sub, smp, pose,
                   shares=multipath_shares, pixels=pixels)
    npix_total = H * W
    # An even number of equal chunks of at most BATCH samples: balanced on two threads, and
    # independent of the thread count (each chunk has its own random stream).
    n_chunks = 2 * math.ceil(npix_total * spp / (2 * BATCH))
    per_chunk = max(1, math.ceil(npix_total / n_chunks))
    starts = list(range(0, npix_total, per_chunk))
    nthreads = threads or int(os.environ.get("TOFHIL_RENDER_THREADS", 0)) or min(2, os.cpu_count() or 1)

    nk = len(ctx.k)
    rows = ctx.rows                                # no indirect row without bounces
    # [direct/indirect, f*h, pixel]; the kernels add into its real and imaginary parts (strided
    # views), so the result's phasors are this array reshaped, not a copy of two.
    frame_key = (rows, nk, npix_total)
    frame = _FRAMES.take(frame_key)
    clear_in_chunks = False
    if frame is None:
        frame = [np.zeros((rows, nk, npix_total), dtype=np.complex128), np.zeros(npix_total), np.zeros(npix_total),
                 np.zeros(npix_total), np.empty(npix_total), np.empty(npix_total, dtype=np.int32)]
    elif pixels is None:           # every chunk runs: each clears its own pixels, in parallel
        clear_in_chunks = True
    else:
        for a in frame[:4]:
            a.fill(0)
    acc, power, ambient, ambient_unit, radial, oid = frame
    acc_re, acc_im = acc.real, acc.imag
    if not ctx.maps_in_place:      # (in place: the chunks write every pixel's maps)
        radial.fill(np.inf)
        oid.fill(-1)
    trans = None if edges is None else np.zeros((npix_total, len(edges) - 1))

    ray_count = [0]

    def store(p0: int, p1: int, r: dict[str, np.ndarray]) -> None:
        ray_count[0] += int(r["rays"])
        if "maps_in_place" not in r:
            radial[p0:p1] = r["radial"]
            oid[p0:p1] = r["object_id"]
        if "in_place" in r:
            return
        ambient[p0:p1] = r["ambient"]
        acc_re[:, :, p0:p1] = r["re"]
        acc_im[:, :, p0:p1] = r["im"]
        power[p0:p1] = r["power"]
        ambient_unit[p0:p1] = r["ambient_unit"]
        if trans is not None:
            trans[p0:p1] = r["transient"]

    dest = {"re": acc_re, "im": acc_im, "power": power, "ambient_unit": ambient_unit, "trans": trans,
            "radial": radial, "object_id": oid}
    if clear_in_chunks:
        dest["clear"] = [acc, power, ambient, ambient_unit]
    jobs = [(i, p0, min(p0 + per_chunk, npix_total), dest) for i, p0 in enumerate(starts)]
    if pixels is not None:  # (a chunk keeps its index: its random stream is the full render's)
        jobs = [j for j in jobs if pixels[j[1]:j[2]].any()]
    if nthreads <= 1 or len(jobs) == 1:
        for job in jobs:
            store(job[1], job[2], ctx.run_chunk(*job))
    else:
        pool = WorkerPool.get(nthreads)
        futures = [(job, pool.submit(ctx.run_chunk, *job)) for job in jobs]
        for job, fut in (progress or no_progress)(futures, len(futures), "render"):
            store(job[1], job[2], fut.result())

    _FRAMES.give(frame_key, frame)
    if ctx.glass.any:
        _add_glints(ctx, acc, power, trans)
    if not ctx.centre_ok.all():              # pixels without a ray see nothing
        radial[~ctx.centre_ok] = np.inf
        oid[~ctx.centre_ok] = -1
    shape = (len(freq), len(harm), H, W)
    if ctx.fused and ctx.ambient != 0:
        # the fused chunks added into ambient_unit in place; the ambient power is its multiple
        np.multiply(ambient_unit, ctx.ambient, out=ambient)

    share_power = None
    if ctx.n_obj:
        # rows (bounce, object) and a last 0 Hz channel: its real part is each row's power
        share_power = acc[:, -1].real.reshape(nb + 1, ctx.n_obj, H, W).copy()
        acc = acc[:, :-1].reshape(nb + 1, ctx.n_obj, nk - 1, npix_total).sum(axis=1)
        if nb:
            acc = np.stack([acc[0], acc[1:].sum(axis=0)])
    direct = acc[0].reshape(shape)
    if nb == 0:                                      # no indirect light was traced
        indirect = np.zeros(shape, dtype=np.complex128) if separate_direct else None
        total = direct.copy() if separate_direct else direct
    else:
        indirect = acc[1].reshape(shape)
        total = direct + indirect
    return RenderResult(
        freq_hz=freq, harmonics=harm, phasor=total,
        power_w=power.reshape(H, W), ambient_power_w=ambient.reshape(H, W),
        radial_m=radial.reshape(H, W), object_id=oid.reshape(H, W),
        phasor_direct=direct if separate_direct else None,
        phasor_indirect=indirect if separate_direct else None,
        transient=None if trans is None else np.ascontiguousarray(trans.T.reshape(-1, H, W)),
        transient_edges_m=edges, camera=cam, samples_per_pixel=spp, bounces=nb,
        rays_traced=ray_count[0], ambient_power_per_irradiance=ambient_unit.reshape(H, W),
        share_power_w=share_power)
