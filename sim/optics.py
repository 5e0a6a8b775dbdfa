"""A real lens in the twin: a sequential lens prescription, traced, and what the twin takes from it.

A prescription (the ``lens:`` block of a scene's camera, docs/optics.md) lists the surfaces in
the order light meets them, object side first: ``radius_m`` (signed, + when the centre of
curvature lies towards the sensor; omitted = flat), ``thickness_m`` to the next surface (the
last one's is the distance to the sensor; ``auto`` = the paraxial back focal length), the
medium after the surface (``glass`` name or refractive index ``n``), ``semi_diameter_m`` (clear
aperture), the coating's ``reflectance`` (default: the uncoated Fresnel reflectance at normal
incidence), ``stop: true`` on the aperture stop, or ``focal_length_m`` for an ideal thin lens
(a paraxial surface: perfect imaging of infinity, a closed-form reference). Band-pass filters
and cover glasses are pairs of flat surfaces; the sensor reflects ``sensor_reflectance``.

Light travels along +z in the lens's frame. The tracer is real (exact) vectorised ray tracing
of spheres and planes with Snell's law, per-ray optical path (sum n d) and energy (each
transmission x (1 - R), each reflection x R). From it:

- per pixel, the chief ray (the ray through the stop's centre): its direction in object space
  replaces the pinhole/OpenCV ray (:class:`LensCamera`; the lens's distortion), its optical path
  through the lens (an extra path the twin adds to the return path: the part that varies over
  the field, the constant being a calibrated camera's range offset);
- the transmission of the pupil: the fraction of the light the ideal pupil of the camera
  equation (``pi r_EP^2 cos(theta)``) collects that reaches the pixel -- vignetting by the
  clear apertures and the coatings' losses (with the solid angle of the pixel this is the
  relative illumination; an ideal lens with its stop at the lens gives cos^4);
- ghosts: every two-reflection path (surface j, then back to surface i < j; the sensor counts
  as the last surface) traced with a full pupil bundle to the sensor: its energy relative to
  the direct light, its blur (RMS spot), its magnification (relative to the direct image,
  about the principal point), its extra optical path and focus shift; with the housing veil
  they form the twin's :class:`~tofhil.sim.straylight.StrayLightPSF`.

What is not modelled: see docs/optics.md (the lens's own image blur, wavelength spread, angle
dependence of coatings, refraction in the scene, participating media, direct ToF).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
from scipy.interpolate import CubicSpline

from tofhil.camera import CameraModel
from tofhil.content_cache import LRUCache
from tofhil.errors import InputFileError
from tofhil.sim.straylight import Ghost, StrayLightPSF

#: Sellmeier coefficients (B1, B2, B3, C1, C2, C3; C in um^2) of the glasses a prescription may
#: name (Schott catalogue; fused silica after Malitson 1965).
GLASSES: dict[str, tuple[float, float, float, float, float, float]] = {
    "N-BK7": (1.03961212, 0.231792344, 1.01046945, 0.00600069867, 0.0200179144, 103.560653),
    "N-SF11": (1.73759695, 0.313747346, 1.89878101, 0.013188707, 0.0623068142, 155.23629),
    "FUSED_SILICA": (0.6961663, 0.4079426, 0.8974794, 0.0684043 ** 2, 0.1162414 ** 2, 9.896161 ** 2),
}


def glass_index(name: str, wavelength_m: float) -> float:
    """Refractive index of a named glass at a wavelength (Sellmeier)."""
    b1, b2, b3, c1, c2, c3 = GLASSES[name.upper()]
    l2 = (wavelength_m * 1e6) ** 2
    return math.sqrt(1.0 + b1 * l2 / (l2 - c1) + b2 * l2 / (l2 - c2) + b3 * l2 / (l2 - c3))


@dataclass(frozen=True)
class LensSurface:
    """One surface; ``n`` is the index of the medium after it (towards the sensor)."""

    radius_m: float = math.inf
    thickness_m: float = 0.0
    n: float = 1.0
    semi_diameter_m: float = math.inf
    #: Coating reflectance; None = uncoated (Fresnel at normal incidence).
    reflectance: float | None = None
    stop: bool = False
    #: An ideal thin lens (paraxial surface) of this focal length instead of a refracting sphere.
    focal_length_m: float | None = None
    name: str = ""

    @property
    def curvature(self) -> float:
        return 0.0 if math.isinf(self.radius_m) else 1.0 / self.radius_m


@dataclass(frozen=True)
class Prescription:
    """A centred lens: surfaces (object side first), the sensor's reflectance, the housing veil."""

    surfaces: tuple[LensSurface, ...]
    sensor_reflectance: float = 0.0
    #: Fraction of the light the housing (barrel, spacers) spreads uniformly over the sensor.
    housing_veil: float = 0.0
    #: Ghost paths weaker than this (relative to the direct light) are dropped.
    ghost_threshold: float = 1e-6

    def __post_init__(self) -> None:
        if not self.surfaces:
            raise ValueError("a prescription needs at least one surface")
        if sum(s.stop for s in self.surfaces) > 1:
            raise ValueError("at most one surface is the stop")

    @property
    def stop_index(self) -> int:
        """The stop (the first surface when none is marked)."""
        for i, s in enumerate(self.surfaces):
            if s.stop:
                return i
        return 0

    @property
    def z(self) -> np.ndarray:
        """Vertex z of each surface, then the sensor's (first surface at 0)."""
        return np.concatenate([[0.0], np.cumsum([s.thickness_m for s in self.surfaces])])

    def n_before(self, k: int) -> float:
        return 1.0 if k == 0 else self.surfaces[k - 1].n

    def reflectance(self, k: int) -> float:
        """Reflectance of surface k (k = len(surfaces): the sensor)."""
        if k == len(self.surfaces):
            return self.sensor_reflectance
        s = self.surfaces[k]
        if s.reflectance is not None:
            return s.reflectance
        if s.focal_length_m is not None:
            return 0.0
        n1, n2 = self.n_before(k), s.n
        return ((n1 - n2) / (n1 + n2)) ** 2


# ---------------------------------------------------------------------------------------------
# Real ray tracing (vectorised)
# ---------------------------------------------------------------------------------------------
@dataclass
class Rays:
    """A bundle: positions, unit directions, optical path so far, energy, alive."""

    pos: np.ndarray
    dir: np.ndarray
    opl: np.ndarray
    w: np.ndarray
    alive: np.ndarray

    @classmethod
    def make(cls, pos: np.ndarray, d: np.ndarray) -> "Rays":
        pos = np.array(pos, dtype=np.float64, ndmin=2)
        d = np.array(d, dtype=np.float64, ndmin=2)
        d = d / np.linalg.norm(d, axis=-1, keepdims=True)
        pos, d = np.broadcast_arrays(pos, d)
        n = pos.shape[0]
        return cls(pos.copy(), d.copy(), np.zeros(n), np.ones(n), np.ones(n, dtype=bool))


def _to_surface(r: Rays, z0: float, curvature: float, semi_diameter: float, n_medium: float) -> np.ndarray:
    """Move the rays to the surface (vertex at ``z0``); returns its unit normal (+z side)."""
    p = r.pos - np.array([0.0, 0.0, z0])
    d = r.dir
    c = curvature
    # Sphere through the vertex: c |q|^2 - 2 q_z = 0; the root nearest the vertex plane.
    b = c * np.einsum("ij,ij->i", p, d) - d[:, 2]
    cc = c * np.einsum("ij,ij->i", p, p) - 2.0 * p[:, 2]
    disc = b * b - c * cc
    ok = disc >= 0
    den = -b + np.sign(d[:, 2]) * np.sqrt(np.where(ok, disc, 0.0))
    ok &= np.abs(den) > 1e-300
    s = np.where(ok, cc / np.where(ok, den, 1.0), 0.0)
    q = p + s[:, None] * d
    ok &= np.hypot(q[:, 0], q[:, 1]) <= semi_diameter
    ok &= s >= -1e-12
    r.alive &= ok
    r.pos = q + np.array([0.0, 0.0, z0])
    r.opl = r.opl + n_medium * s
    nrm = np.stack([-c * q[:, 0], -c * q[:, 1], 1.0 - c * q[:, 2]], axis=-1)
    return nrm / np.linalg.norm(nrm, axis=-1, keepdims=True)


def _refract(r: Rays, nrm: np.ndarray, n1: float, n2: float) -> None:
    """Vector Snell's law; total internal reflection ends the ray."""
    cos_i = -np.einsum("ij,ij->i", nrm, r.dir)
    nrm = np.where((cos_i < 0)[:, None], -nrm, nrm)
    cos_i = np.abs(cos_i)
    mu = n1 / n2
    k = 1.0 - mu * mu * (1.0 - cos_i * cos_i)
    r.alive &= k >= 0
    r.dir = mu * r.dir + (mu * cos_i - np.sqrt(np.clip(k, 0.0, None)))[:, None] * nrm


def _reflect(r: Rays, nrm: np.ndarray) -> None:
    r.dir = r.dir - 2.0 * np.einsum("ij,ij->i", nrm, r.dir)[:, None] * nrm


def _ideal_lens(r: Rays, f: float) -> None:
    """An ideal thin lens in air at the ray's current plane: tangents ``t -> t - h / f`` in the
    direction of travel (parallel light meets at ``f t``), and the optical path that makes every
    ray of a parallel bundle arrive in phase at its focus."""
    sz = np.sign(r.dir[:, 2])
    t = r.dir[:, :2] / np.abs(r.dir[:, 2:3])
    h = r.pos[:, :2]
    t2 = t - h / f
    tt = np.einsum("ij,ij->i", t, t)
    r.opl = (r.opl + f * np.sqrt(1.0 + tt) - np.sqrt(f * f + np.einsum("ij,ij->i", f * t - h, f * t - h))
             - np.einsum("ij,ij->i", h, t) / np.sqrt(1.0 + tt))
    d = np.concatenate([t2, sz[:, None]], axis=1)
    r.dir = d / np.linalg.norm(d, axis=-1, keepdims=True)


def trace_path(lens: Prescription, rays: Rays, events: Sequence[tuple[int, str]], start_medium: float = 1.0) -> Rays:
    """Trace ``rays`` through ``events`` in order: ``(k, "t")`` transmits through surface k,
    ``(k, "r")`` reflects off it (``k = len(surfaces)``: the sensor plane, ``"s"`` to stop on it).
    Energy takes ``1 - R`` per transmission and ``R`` per reflection; the optical path adds
    ``n d`` in each medium. ``start_medium``: the index the rays start in."""
    z = lens.z
    ns = len(lens.surfaces)
    n_cur = start_medium
    for k, act in events:
        if k == ns:
            nrm = _to_surface(rays, z[k], 0.0, math.inf, n_cur)
            if act == "r":
                rays.w = rays.w * lens.sensor_reflectance
                _reflect(rays, nrm)
            elif act == "s":
                rays.w = rays.w * (1.0 - lens.sensor_reflectance)
            continue
        s = lens.surfaces[k]
        nrm = _to_surface(rays, z[k], s.curvature, s.semi_diameter_m, n_cur)
        R = lens.reflectance(k)
        forward = rays.dir[:, 2] > 0
        n_other = s.n if np.all(forward[rays.alive]) else lens.n_before(k)
        if act == "r":
            rays.w = rays.w * R
            _reflect(rays, nrm)
        else:
            rays.w = rays.w * (1.0 - R)
            if s.focal_length_m is not None:
                _ideal_lens(rays, s.focal_length_m)
            else:
                _refract(rays, nrm, n_cur, n_other)
            n_cur = n_other
    return rays


def direct_events(lens: Prescription, first: int = 0) -> list[tuple[int, str]]:
    """Straight through from surface ``first`` to the sensor (absorbed there)."""
    ns = len(lens.surfaces)
    return [(k, "t") for k in range(first, ns)] + [(ns, "s")]


def ghost_events(lens: Prescription, i: int, j: int) -> list[tuple[int, str]]:
    """Two reflections: through to surface j, reflected, back to surface i, reflected, then on
    to the sensor (``j = len(surfaces)``: the sensor itself)."""
    ns = len(lens.surfaces)
    ev = [(k, "t") for k in range(0, j)] + [(j, "r")]
    ev += [(k, "t") for k in range(j - 1, i, -1)] + [(i, "r")]
    return ev + [(k, "t") for k in range(i + 1, ns)] + [(ns, "s")]


# ---------------------------------------------------------------------------------------------
# First-order properties
# ---------------------------------------------------------------------------------------------
_PARAXIAL_H = 1e-6  # ray height (m) of the paraxial rays: real rays in the paraxial limit


@dataclass(frozen=True)
class Ghost2R:
    """A two-reflection ghost path traced on the sensor."""

    i: int
    j: int
    name: str
    weight: float            # energy relative to the direct light of the same pupil bundle
    sigma_m: float           # RMS blur per axis on the sensor
    magnification: float     # ghost image height / direct image height (about the axis)
    extra_path_m: float      # optical path beyond the direct light's
    focus_shift_m: float     # ghost focus - direct focus along z (- = in front of the sensor)


class LensModel:
    """A traced prescription: first-order data, per-field tables, ghosts."""

    def __init__(self, lens: Prescription, field_samples: int = 256, pupil_samples: int = 64) -> None:
        self.lens = lens
        self.field_samples = field_samples
        self.pupil_samples = pupil_samples
        #: Pupil grid of the ghost bundles (their weights are ratios to the direct bundle on
        #: the same grid, so a coarse grid suffices).
        self.ghost_samples = max(8, pupil_samples // 2)

    # ------------------------------------------------------------------ paraxial
    def _parallel(self, h: float, n_events: list[tuple[int, str]] | None = None) -> Rays:
        rays = Rays.make([[h, 0.0, -1e-3]], [[0.0, 0.0, 1.0]])
        return trace_path(self.lens, rays, n_events if n_events is not None else direct_events(self.lens)[:-1])

    @cached_property
    def efl_m(self) -> float:
        """Effective focal length (paraxial): ``-h / u'`` of a ray entering parallel at height h."""
        r = self._parallel(_PARAXIAL_H)
        u = r.dir[0, 0] / r.dir[0, 2]
        if not r.alive[0] or u == 0:
            raise ValueError("the lens has no focal length (afocal or blocked on axis)")
        return float(-_PARAXIAL_H / u)

    @cached_property
    def bfl_m(self) -> float:
        """Back focal length: last surface to the paraxial focus."""
        r = self._parallel(_PARAXIAL_H)
        u = r.dir[0, 0] / r.dir[0, 2]
        return float(-r.pos[0, 0] / u + r.pos[0, 2] - self.lens.z[-2])

    @cached_property
    def entrance_pupil(self) -> tuple[float, float]:
        """``(z, radius)`` of the paraxial entrance pupil (the stop imaged into object space)."""
        lens, s = self.lens, self.lens.stop_index
        a = 1e-4
        back = self._stop_backward(np.array([a]))
        q, b = back.pos[0], back.dir[0]
        z_ep = q[2] - q[0] * b[2] / b[0]
        # Pupil radius: a parallel ray's height at the stop is proportional to its entry height.
        r = trace_path(lens, Rays.make([[_PARAXIAL_H, 0.0, -1e-3]], [[0, 0, 1.0]]), [(k, "t") for k in range(s)])
        _to_surface(r, lens.z[s], lens.surfaces[s].curvature, math.inf, lens.n_before(s))
        ratio = r.pos[0, 0] / _PARAXIAL_H
        return float(z_ep), float(lens.surfaces[s].semi_diameter_m / abs(ratio))

    @property
    def f_number(self) -> float:
        return self.efl_m / (2.0 * self.entrance_pupil[1])

    # ------------------------------------------------------------------ chief rays
    def _stop_backward(self, alpha: np.ndarray) -> Rays:
        """Chief rays leaving the stop's centre at angles ``alpha`` (in the medium after the
        stop), traced backwards to object space: directions there point at the scene."""
        lens, s = self.lens, self.lens.stop_index
        z = lens.z
        d = np.stack([np.sin(alpha), np.zeros_like(alpha), np.cos(alpha)], axis=-1)
        r = Rays.make(np.array([[0.0, 0.0, z[s]]]), -d)
        sf = lens.surfaces[s]
        if sf.focal_length_m is not None:
            _ideal_lens(r, sf.focal_length_m)
        else:
            _refract(r, np.array([[0.0, 0.0, 1.0]]), sf.n, lens.n_before(s))
        trace_path(lens, r, [(k, "t") for k in range(s - 1, -1, -1)], start_medium=lens.n_before(s))
        return r

    def _stop_forward(self, alpha: np.ndarray) -> Rays:
        lens, s = self.lens, self.lens.stop_index
        d = np.stack([np.sin(alpha), np.zeros_like(alpha), np.cos(alpha)], axis=-1)
        r = Rays.make(np.array([[0.0, 0.0, lens.z[s]]]), d)
        return trace_path(lens, r, direct_events(lens, s + 1), start_medium=lens.surfaces[s].n)

    @cached_property
    def chief(self) -> dict[str, np.ndarray]:
        """Chief rays over the field: object angle ``theta``, image height ``rho_m`` (both
        increasing from 0), the lens's extra path ``extra_path_m`` (from the entrance pupil's
        centre, to first order in 1/distance), on the monotonic, unvignetted part of the field."""
        n_s = self.lens.surfaces[self.lens.stop_index].n
        alpha = np.linspace(0.0, math.asin(min(1.0, 0.999 / n_s)) * 0.999, self.field_samples)
        back, fwd = self._stop_backward(alpha), self._stop_forward(alpha)
        b = back.dir
        theta = np.arccos(np.clip(-b[:, 2], -1.0, 1.0))
        rho = np.abs(fwd.pos[:, 0])
        z_ep = self.entrance_pupil[0]
        c = np.array([0.0, 0.0, z_ep])
        # Lens path from the first surface to the sensor minus what the pinhole (from C) counts.
        extra = back.opl + fwd.opl - np.einsum("ij,ij->i", back.pos - c, b)
        ok = back.alive & fwd.alive & (b[:, 2] < 0)
        good = np.flatnonzero(~ok)
        last = good[0] if good.size else alpha.size
        mono = np.flatnonzero((np.diff(rho[:last]) <= 0) | (np.diff(theta[:last]) <= 0))
        last = min(last, mono[0] + 1 if mono.size else last)
        if last < 4:
            raise ValueError("the chief ray does not pass the lens")
        return {"theta": theta[:last], "rho_m": rho[:last], "extra_path_m": extra[:last]}

    @cached_property
    def _splines(self) -> tuple[CubicSpline, CubicSpline, CubicSpline]:
        t = self.chief
        return (CubicSpline(t["theta"], t["rho_m"]), CubicSpline(t["rho_m"], t["theta"]),
                CubicSpline(t["theta"], t["extra_path_m"]))

    def image_height(self, theta: np.ndarray) -> np.ndarray:
        return self._splines[0](np.asarray(theta, dtype=np.float64))

    def field_angle(self, rho_m: np.ndarray) -> np.ndarray:
        return self._splines[1](np.asarray(rho_m, dtype=np.float64))

    def extra_path(self, theta: np.ndarray) -> np.ndarray:
        """The lens's optical path along the chief ray beyond the pinhole's (one way)."""
        return self._splines[2](np.asarray(theta, dtype=np.float64))

    @property
    def max_image_height_m(self) -> float:
        return float(self.chief["rho_m"][-1])

    # ------------------------------------------------------------------ pupil bundles
    def bundle(self, theta: float, events: Sequence[tuple[int, str]] | None = None,
               pupil_scale: float = 1.6, samples: int | None = None) -> tuple[Rays, float]:
        """A parallel bundle at field angle ``theta`` on a square grid over the entrance pupil
        (``pupil_scale`` x its radius, perpendicular to the bundle) traced along ``events``;
        returns the rays and the area per ray (m^2, perpendicular to the bundle)."""
        z_ep, r_ep = self.entrance_pupil
        n = samples or self.pupil_samples
        half = pupil_scale * r_ep
        g = (np.arange(n) + 0.5) / n * 2 * half - half
        gx, gy = np.meshgrid(g, g)
        d = np.array([math.sin(theta), 0.0, math.cos(theta)])
        ex = np.array([math.cos(theta), 0.0, -math.sin(theta)])
        ey = np.array([0.0, 1.0, 0.0])
        start = np.array([0.0, 0.0, z_ep]) + gx.reshape(-1, 1) * ex + gy.reshape(-1, 1) * ey
        # Start on a plane in front of every surface's sag (a lens's length ahead), in air.
        z_start = min(0.0, z_ep) - float(self.lens.z[-1]) - 0.01 - 2 * half
        s = (z_start - start[:, 2]) / d[2]
        rays = Rays.make(start + s[:, None] * d, d)
        trace_path(self.lens, rays, events if events is not None else direct_events(self.lens))
        return rays, (2 * half / n) ** 2

    def transmission(self, theta: np.ndarray) -> np.ndarray:
        """Light reaching the sensor at field angle ``theta`` (per unit radiance and pixel solid
        angle) over the camera equation's ``pi r_EP^2 cos(theta)``: vignetting x coatings."""
        z_ep, r_ep = self.entrance_pupil
        # The grid's own area of the ideal pupil (cells whose centres fall inside it) instead of
        # pi r^2: the counting error of the grid cancels (1 % at 48 samples otherwise).
        n = self.pupil_samples
        g = ((np.arange(n) + 0.5) / n * 2 - 1) * 1.6
        ideal = np.count_nonzero(np.add.outer(g ** 2, g ** 2) <= 1.0) * (2 * 1.6 * r_ep / n) ** 2
        out = []
        for t in np.atleast_1d(theta):
            rays, area = self.bundle(float(t))
            out.append(float(rays.w[rays.alive].sum()) * area / (ideal * math.cos(t)))
        return np.array(out)

    @cached_property
    def _transmission_spline(self) -> CubicSpline:
        th = np.linspace(0.0, float(self.chief["theta"][-1]), 17)
        return CubicSpline(th, self.transmission(th))

    def relative_illumination(self, theta: np.ndarray) -> np.ndarray:
        """Image irradiance at field angle ``theta`` over the axis's: transmission x cos(theta)
        x the pixel's solid angle ratio (``sin t dt / (rho d rho)`` from the chief-ray mapping)."""
        t = np.asarray(theta, dtype=np.float64)
        rho = self.image_height(t)
        drho = self._splines[0](t, 1)
        with np.errstate(invalid="ignore", divide="ignore"):
            omega = np.where(t > 0, np.sin(t) / (rho * drho), 1.0 / self.efl_m ** 2)
        tr = self._transmission_spline(t) / self._transmission_spline(0.0)
        return tr * np.cos(t) * omega * self.efl_m ** 2

    # ------------------------------------------------------------------ ghosts
    def surface_name(self, k: int) -> str:
        if k == len(self.lens.surfaces):
            return "sensor"
        return self.lens.surfaces[k].name or f"S{k + 1}"

    def _direct(self, theta: float) -> Rays:
        """The direct bundle at a field angle (traced once: every ghost compares with it)."""
        cache = self.__dict__.setdefault("_direct_cache", {})
        if theta not in cache:
            cache[theta] = self.bundle(theta, samples=self.ghost_samples)[0]
        return cache[theta]

    @staticmethod
    def _focus_z(r: Rays) -> float:
        """Best-focus plane (least squares) of the live rays, from their sensor hits."""
        a = r.alive & (r.w > 0)
        t = r.dir[a, :2] / r.dir[a, 2:3]
        p = r.pos[a, :2]
        den = float(np.einsum("ij,ij->", t, t))
        return float(r.pos[a, 2].mean() - np.einsum("ij,ij->", p, t) / den) if den > 0 else math.inf

    def ghost(self, i: int, j: int, field_theta: float | None = None) -> Ghost2R:
        """The ghost of surfaces ``i < j`` (``j = len(surfaces)``: the sensor)."""
        lens = self.lens
        ev = ghost_events(lens, i, j)
        d0 = self._direct(0.0)
        g0, _ = self.bundle(0.0, ev, samples=self.ghost_samples)
        wd = float(d0.w[d0.alive].sum())
        a = g0.alive & (g0.w > 0)
        wg = float(g0.w[a].sum())
        if wd <= 0 or wg <= 0:
            return Ghost2R(i, j, f"{self.surface_name(i)}-{self.surface_name(j)}", 0.0, 0.0, 1.0, 0.0, 0.0)
        wts = g0.w[a] / wg
        sigma = math.sqrt(float(np.sum(wts * (g0.pos[a, 0] ** 2 + g0.pos[a, 1] ** 2))) / 2.0)
        ad = d0.alive & (d0.w > 0)
        extra = float(np.sum(wts * g0.opl[a]) - np.average(d0.opl[ad], weights=d0.w[ad]))
        # Ghost focus: rewind the sensor hits along the rays (the ghost came in forward).
        shift = self._focus_z(g0) - self._focus_z(d0)
        # Magnification: centroids of an off-axis bundle, ghost over direct.
        th = field_theta if field_theta is not None else 0.5 * float(self.chief["theta"][-1])
        mag = 1.0
        for t in (th, th / 4):
            dd = self._direct(t)
            gg, _ = self.bundle(t, ev, samples=self.ghost_samples)
            ad, ag = dd.alive & (dd.w > 0), gg.alive & (gg.w > 0)
            if ad.any() and ag.any():
                xd = np.average(dd.pos[ad, 0], weights=dd.w[ad])
                xg = np.average(gg.pos[ag, 0], weights=gg.w[ag])
                mag = float(xg / xd)
                break
        return Ghost2R(i, j, f"{self.surface_name(i)}-{self.surface_name(j)}", wg / wd, sigma, mag, extra, shift)

    @cached_property
    def ghosts(self) -> list[Ghost2R]:
        """Every two-reflection ghost above the prescription's threshold, strongest first."""
        ns = len(self.lens.surfaces)
        out = []
        for j in range(1, ns + 1):
            if self.lens.reflectance(j) <= 0:
                continue
            for i in range(j):
                if self.lens.reflectance(i) <= 0:
                    continue
                g = self.ghost(i, j)
                if g.weight > self.lens.ghost_threshold:
                    out.append(g)
        return sorted(out, key=lambda g: -g.weight)

    def stray_light(self, pixel_pitch_m: float, *, ghosts: Sequence[Ghost2R] | None = None,
                    veil: bool = True) -> StrayLightPSF:
        """The prescription's stray light as the one PSF type: each ghost (weight relative to
        the direct light, blur, magnification about the principal point, extra path) and the
        housing veil; light is added (``conserve = false``): the direct light's losses are in
        :meth:`transmission`."""
        gs = self.ghosts if ghosts is None else ghosts
        return StrayLightPSF(
            ghosts=tuple(Ghost(g.weight, g.sigma_m / pixel_pitch_m, None, g.magnification, g.extra_path_m)
                         for g in gs),
            veil=self.lens.housing_veil if veil else 0.0, conserve=False,
            info={"source": "lens prescription", "ghosts": [g.name for g in gs]})

    # ------------------------------------------------------------------ per pixel
    def pixel_maps(self, camera: CameraModel) -> dict[str, np.ndarray]:
        """Per pixel: field angle, transmission (vignetting x coatings) and the lens's extra
        path relative to the axis's (one way)."""
        v, u = np.mgrid[0:camera.height, 0:camera.width].astype(np.float64)
        rho = self.efl_m * np.hypot((u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy)
        theta = self.field_angle(np.clip(rho, 0.0, self.max_image_height_m))
        tr = self._transmission_spline(theta)
        extra = self.extra_path(theta) - self.extra_path(0.0)
        return {"theta": theta, "transmission": tr, "extra_path_m": extra}


# ---------------------------------------------------------------------------------------------
# The camera with a lens
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class LensCamera(CameraModel):
    """A camera whose rays are the prescription's chief rays (object-space directions through
    the entrance pupil's centre: the camera's origin). ``fx = fy = EFL / pitch``; ``dist``
    holds the OpenCV model fitted to the lens's distortion (what a session file stores)."""

    lens: Prescription | None = None

    @cached_property
    def model(self) -> LensModel:
        return lens_model(self.lens)  # type: ignore[arg-type]

    @property
    def has_distortion(self) -> bool:
        return True

    @cached_property
    def stage(self) -> "LensStage":
        """The lens stage of this camera (per-pixel maps, the prescription's stray light and
        its operator), built once: the twin applies it on every prediction."""
        return lens_stage(self)

    def undistort_normalized(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        xd = (np.asarray(u, dtype=np.float64) - self.cx) / self.fx
        yd = (np.asarray(v, dtype=np.float64) - self.cy) / self.fy
        f = self.model.efl_m
        rd = np.hypot(xd, yd)
        theta = self.model.field_angle(np.clip(rd * f, 0.0, None))
        with np.errstate(invalid="ignore", divide="ignore"):
            k = np.where(rd > 0, np.tan(theta) / np.where(rd > 0, rd, 1.0), 1.0)
        return xd * k, yd * k

    def distort_normalized(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        ru = np.hypot(x, y)
        rd = self.model.image_height(np.arctan(ru)) / self.model.efl_m
        with np.errstate(invalid="ignore", divide="ignore"):
            k = np.where(ru > 0, rd / np.where(ru > 0, ru, 1.0), 1.0)
        return x * k, y * k

    def to_dict(self) -> dict[str, Any]:
        d = super().to_dict()
        d["lens"] = prescription_to_dict(self.lens) if self.lens is not None else None
        return d


#: Traced models by prescription (a frozen dataclass: its own content key). At most 17: the
#: 18th prescription empties the cache first (a process rarely sees more than a few lenses).
_MODELS = LRUCache()
_MODELS_KEPT = 16


def lens_model(lens: Prescription) -> LensModel:
    """The traced model of a prescription (traced once per prescription)."""
    m = _MODELS.get(lens)
    if m is None:
        if len(_MODELS) > _MODELS_KEPT:
            _MODELS.clear()
        m = LensModel(lens)
        _MODELS.put(lens, m)
    return m


def opencv_fit(model: LensModel, r_max: float) -> tuple[float, float, float, float, float]:
    """OpenCV ``(k1, k2, 0, 0, k3)`` fitted to the lens's mapping tan(theta) -> rho / EFL up to
    the normalised radius ``r_max`` (least squares on the distorted radius)."""
    ru = np.linspace(1e-4, max(r_max, 1e-3), 200)
    rd = model.image_height(np.arctan(ru)) / model.efl_m
    a = np.stack([ru ** 3, ru ** 5, ru ** 7], axis=1)
    k1, k2, k3 = np.linalg.lstsq(a, rd - ru, rcond=None)[0]
    return float(k1), float(k2), 0.0, 0.0, float(k3)


def lens_camera(base: CameraModel, lens: Prescription, *, source: str | Path = "<camera>",
                field: str = "camera.lens") -> LensCamera:
    """A :class:`LensCamera` on ``base``'s sensor (size, pitch, principal point)."""
    if base.pixel_pitch_m is None:
        raise InputFileError("a lens prescription needs the sensor's pixel pitch", file=source,
                             field="camera.pixel_pitch_m", expected="the pixel pitch in metres")
    try:
        m = lens_model(lens)
        f = m.efl_m
        rho_max = m.max_image_height_m
    except ValueError as exc:
        raise InputFileError(str(exc), file=source, field=field, expected="a lens that images the sensor") from None
    if not f > 0:
        raise InputFileError(f"the lens's focal length is {f:g} m", file=source, field=field,
                             expected="a positive (converging) lens")
    p = base.pixel_pitch_m
    corner = p * max(math.hypot(x, y) for x in (base.cx, base.width - 1 - base.cx)
                     for y in (base.cy, base.height - 1 - base.cy))
    if corner > rho_max:
        raise InputFileError(f"the chief ray reaches {rho_max * 1e3:.3f} mm off axis, the sensor's corner is "
                             f"{corner * 1e3:.3f} mm", file=source, field=field,
                             expected="a lens whose field covers the sensor")
    fpx = f / p
    cam = LensCamera(width=base.width, height=base.height, fx=fpx, fy=fpx, cx=base.cx, cy=base.cy,
                     name=base.name, pixel_pitch_m=p, extra=dict(base.extra), lens=lens)
    r_corner = corner / f
    return replace(cam, dist=opencv_fit(m, math.tan(float(m.field_angle(corner))) if r_corner > 0 else 0.1))


# ---------------------------------------------------------------------------------------------
# The lens block (scene files)
# ---------------------------------------------------------------------------------------------
_SURFACE_KEYS = ("name", "radius_m", "thickness_m", "glass", "n", "semi_diameter_m", "reflectance", "stop",
                 "focal_length_m")
_LENS_KEYS = ("surfaces", "sensor_reflectance", "housing_veil", "wavelength_m", "ghost_threshold")


def prescription_from_dict(d: Any, *, source: str | Path = "<camera>", prefix: str = "camera.lens",
                           wavelength_m: float | None = None) -> Prescription:
    """Parse and validate a ``lens:`` block; errors name the file and the field."""
    from tofhil.schema import Schema

    sch = Schema(source)

    def bad(f: str, got: Any, expected: str) -> InputFileError:
        return InputFileError(f"got {got!r}", file=source, field=f, expected=expected)

    if not isinstance(d, Mapping):
        raise bad(prefix, d, "a mapping with surfaces, sensor_reflectance, housing_veil")
    sch.keys(d, prefix, _LENS_KEYS)
    wl = d.get("wavelength_m", wavelength_m)
    wl = 850e-9 if wl is None else sch.number(wl, f"{prefix}.wavelength_m", lo=2e-7, hi=2e-6)
    surfs = d.get("surfaces")
    if not isinstance(surfs, list) or not surfs:
        raise bad(f"{prefix}.surfaces", surfs, "a non-empty list of surfaces")
    out: list[LensSurface] = []
    auto_last = False
    for idx, s in enumerate(surfs):
        f = f"{prefix}.surfaces[{idx}]"
        if not isinstance(s, Mapping):
            raise bad(f, s, "a mapping: radius_m, thickness_m, glass or n, semi_diameter_m, reflectance, stop")
        sch.keys(s, f, _SURFACE_KEYS)
        kw: dict[str, Any] = {"name": str(s.get("name", ""))}
        if s.get("radius_m") is not None:
            r = sch.number(s["radius_m"], f"{f}.radius_m", lo=-1e3, hi=1e3)
            if r == 0:
                raise bad(f"{f}.radius_m", r, "a non-zero radius (omit it for a flat surface)")
            kw["radius_m"] = r
        t = s.get("thickness_m", 0.0)
        if t == "auto":
            if idx != len(surfs) - 1:
                raise bad(f"{f}.thickness_m", t, "a thickness in metres ('auto' only on the last surface)")
            auto_last, t = True, 0.0
        kw["thickness_m"] = sch.number(t, f"{f}.thickness_m", lo=0.0, hi=10.0)
        if "glass" in s and "n" in s:
            raise bad(f"{f}.glass", s["glass"], "either glass or n, not both")
        if "glass" in s:
            g = str(s["glass"])
            if g.upper() not in GLASSES and g.lower() != "air":
                raise bad(f"{f}.glass", g, "one of air, " + ", ".join(GLASSES) + " (or give n)")
            kw["n"] = 1.0 if g.lower() == "air" else glass_index(g, wl)
        elif "n" in s:
            kw["n"] = sch.number(s["n"], f"{f}.n", lo=1.0, hi=4.0)
        if s.get("semi_diameter_m") is not None:
            kw["semi_diameter_m"] = sch.number(s["semi_diameter_m"], f"{f}.semi_diameter_m", lo=0.0, lo_open=True,
                                               hi=1.0)
        if s.get("reflectance") is not None:
            kw["reflectance"] = sch.number(s["reflectance"], f"{f}.reflectance", lo=0.0, hi=1.0)
        if s.get("focal_length_m") is not None:
            fl = sch.number(s["focal_length_m"], f"{f}.focal_length_m", lo=-10.0, hi=10.0)
            if fl == 0:
                raise bad(f"{f}.focal_length_m", fl, "a non-zero focal length")
            if "radius_m" in kw:
                raise bad(f"{f}.radius_m", kw["radius_m"], "no radius on an ideal lens (focal_length_m)")
            kw["focal_length_m"] = fl
        stop = s.get("stop", False)
        if not isinstance(stop, bool):
            raise bad(f"{f}.stop", stop, "true or false")
        kw["stop"] = stop
        out.append(LensSurface(**kw))
    if sum(s.stop for s in out) > 1:
        raise bad(f"{prefix}.surfaces", [s.name for s in out if s.stop], "exactly one surface with stop: true")
    k_stop = next((i for i, s in enumerate(out) if s.stop), 0)
    if math.isinf(out[k_stop].semi_diameter_m):
        raise InputFileError("the aperture stop has no size", file=source,
                             field=f"{prefix}.surfaces[{k_stop}].semi_diameter_m",
                             expected="the stop's semi-diameter in metres (it sets the f-number)")
    pres = Prescription(
        surfaces=tuple(out),
        sensor_reflectance=sch.number(d.get("sensor_reflectance", 0.0), f"{prefix}.sensor_reflectance", lo=0, hi=1),
        housing_veil=sch.number(d.get("housing_veil", 0.0), f"{prefix}.housing_veil", lo=0.0, hi=0.5),
        ghost_threshold=sch.number(d.get("ghost_threshold", 1e-6), f"{prefix}.ghost_threshold", lo=0.0, hi=1.0))
    if auto_last:
        try:
            bfl = LensModel(pres).bfl_m
        except ValueError as exc:
            raise InputFileError(str(exc), file=source, field=f"{prefix}.surfaces",
                                 expected="a lens with a focal length") from None
        if not bfl > 0:
            raise InputFileError(f"the back focal length is {bfl:g} m", file=source,
                                 field=f"{prefix}.surfaces[{len(out) - 1}].thickness_m",
                                 expected="a lens focusing behind its last surface, or a thickness")
        last = replace(out[-1], thickness_m=bfl)
        pres = replace(pres, surfaces=tuple(out[:-1]) + (last,))
    return pres


def prescription_to_dict(p: Prescription) -> dict[str, Any]:
    """Plain form (indices resolved) of a prescription."""
    surfs = []
    for s in p.surfaces:
        e: dict[str, Any] = {"thickness_m": s.thickness_m, "n": s.n}
        if s.name:
            e["name"] = s.name
        if not math.isinf(s.radius_m):
            e["radius_m"] = s.radius_m
        if not math.isinf(s.semi_diameter_m):
            e["semi_diameter_m"] = s.semi_diameter_m
        if s.reflectance is not None:
            e["reflectance"] = s.reflectance
        if s.stop:
            e["stop"] = True
        if s.focal_length_m is not None:
            e["focal_length_m"] = s.focal_length_m
        surfs.append(e)
    return {"surfaces": surfs, "sensor_reflectance": p.sensor_reflectance, "housing_veil": p.housing_veil,
            "ghost_threshold": p.ghost_threshold}


# ---------------------------------------------------------------------------------------------
# The twin's lens stage
# ---------------------------------------------------------------------------------------------
@dataclass
class LensStage:
    """What the twin applies to the light on the sensor for a :class:`LensCamera`: the pupil's
    transmission, the lens's extra return path and the ghosts + housing veil (with its
    operator for the camera's sensor)."""

    transmission: np.ndarray
    extra_path_m: np.ndarray
    psf: StrayLightPSF
    operator: Any = None
    info: dict[str, Any] = field(default_factory=dict)


def lens_stage(camera: LensCamera, *, psf: StrayLightPSF | None = None) -> LensStage:
    """The lens stage of a camera; ``psf`` replaces the prescription's stray light."""
    from tofhil.sim.straylight import StrayLightOperator

    m = camera.model
    maps = m.pixel_maps(camera)
    psf = m.stray_light(camera.pixel_pitch_m) if psf is None else psf
    op = None if psf.is_identity else StrayLightOperator(psf, camera.shape, (camera.cx, camera.cy))
    return LensStage(maps["transmission"], maps["extra_path_m"], psf, op)


def apply_lens(signal: Any, camera: CameraModel, *, psf: StrayLightPSF | None = None) -> Any:
    """The lens's part of the forward model (nothing for a pinhole/OpenCV camera): the light
    (modulated and not) times the pupil's transmission, the return path longer by the lens's
    extra path, then the ghosts and housing veil added on the sensor (``psf``: another
    stray-light PSF instead of the prescription's, e.g. a subset of its ghosts)."""
    if not isinstance(camera, LensCamera) or camera.lens is None:
        return signal
    from tofhil.sim.effects.base import _rotate_phase

    st = camera.stage if psf is None else lens_stage(camera, psf=psf)
    if signal.shape != camera.shape:
        raise ValueError(f"signal is {signal.shape}, the lens camera {camera.shape}")
    out = _rotate_phase(signal, st.extra_path_m)
    out.phasor_w = out.phasor_w * st.transmission
    out.dc_w = np.asarray(signal.dc_w) * st.transmission
    out.ambient_w = np.asarray(signal.ambient_w) * st.transmission
    if st.operator is not None:
        op = st.operator
        freq = (out.freq_hz[:, None] * np.asarray(out.harmonics, dtype=np.float64)[None, :])[..., None, None]
        out.phasor_w = op.apply(out.phasor_w, freq_hz=freq)
        both = op.apply(np.stack([out.dc_w, out.ambient_w]))
        out.dc_w, out.ambient_w = both[0], both[1]
    return out


__all__ = ["GLASSES", "Ghost2R", "LensCamera", "LensModel", "LensStage", "LensSurface", "Prescription", "Rays",
           "apply_lens", "direct_events", "ghost_events", "glass_index", "lens_camera", "lens_model", "lens_stage",
           "opencv_fit", "prescription_from_dict", "prescription_to_dict", "trace_path"]
