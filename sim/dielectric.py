"""Glass and scattering media in the twin: Fresnel interfaces, exact links through a glass slab,
homogeneous media (free flights, Henyey-Greenstein).

A dielectric material (``ior: n``, optional ``absorption_per_m: sigma_a``) is a smooth
interface between air (index 1) and the object's glass: every hit splits into the Fresnel
reflection (``R``) and the refraction (``1 - R``, Snell), and a path's optical length counts
``n d`` inside (its power ``exp(-sigma_a d)``).

The emitter is a POINT: a diffuse vertex behind glass cannot reach it with a straight shadow
ray, and a sampled direction never hits it. The light that does reach the vertex through a
plane-parallel slab (a box: the ray enters one face and leaves by the opposite one) follows
the one ray that obeys Snell at both faces; it leaves the slab parallel to the ray that
entered, so with ``a`` the air distance across the slab's normal (both legs together),
``T`` the slab's thickness and ``rho`` the sideways distance between the vertex and the
emitter the incidence angle solves

    a tan(theta) + T tan(theta_t) = rho,      sin(theta) = n sin(theta_t),

(:func:`slab_incidence`, a 1-D root in ``sin(theta)``: increasing and convex, Newton inside a
bracket). The irradiance follows from how the slab spreads the emitter's ray bundle
(intensity ``I`` per solid angle ``sin(theta) dtheta dphi`` onto the area ``rho drho dphi``):

    E = I T_F cos(theta_s) / [cos(theta) (rho / sin(theta)) (d rho / d theta)]

with ``rho / sin = a / cos(theta) + T / (n cos(theta_t))`` and ``d rho / d theta = a /
cos^2(theta) + T cos(theta) / (n cos^3(theta_t))`` (:func:`slab_geometry`); without the slab
this is ``cos(theta_s) / r^2``, on the axis ``1 / (a + T/n)^2`` (the slab's apparent
thickness ``T/n``). ``T_F`` is the product of the two Fresnel transmittances. The optical
path is ``a / cos(theta) + n T / cos(theta_t)``.

The same unfolding gives the emitter's image in the slab's back face (enter, reflect inside,
leave by the entrance face): a slab of thickness ``2T`` to the emitter mirrored in the back
face (:func:`glints`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
from numba import njit


@njit(nogil=True, cache=True, inline="always")
def fresnel(cos_i, n1, n2):  # pragma: no cover
    """Unpolarised Fresnel reflectance of a smooth interface from index ``n1`` into ``n2`` at
    incidence cosine ``cos_i`` (> 0): ``(R, cos_t)``; total internal reflection gives
    ``(1, 0)``. The transmittance is ``1 - R`` (no absorption at the interface)."""
    eta = n1 / n2
    sin2_t = eta * eta * max(0.0, 1.0 - cos_i * cos_i)
    if sin2_t >= 1.0:
        return 1.0, 0.0
    cos_t = math.sqrt(1.0 - sin2_t)
    rs = (n1 * cos_i - n2 * cos_t) / (n1 * cos_i + n2 * cos_t)
    rp = (n2 * cos_i - n1 * cos_t) / (n2 * cos_i + n1 * cos_t)
    return 0.5 * (rs * rs + rp * rp), cos_t


@njit(nogil=True, cache=True, inline="always")
def slab_incidence(a, thick, n, rho):  # pragma: no cover
    """``sin(theta)`` of the ray that crosses ``a`` of air and a slab of thickness ``thick``
    and index ``n`` (both measured along the slab's normal) and moves ``rho`` sideways:
    the root of ``a s / sqrt(1 - s^2) + thick s / sqrt(n^2 - s^2) = rho`` in [0, 1)."""
    if rho <= 0.0:
        return 0.0
    lo, hi = 0.0, 1.0
    s = rho / math.sqrt(rho * rho + (a + thick / n) ** 2)     # the paraxial answer
    for _ in range(100):
        c2 = 1.0 - s * s
        m2 = n * n - s * s
        f = a * s / math.sqrt(c2) + thick * s / math.sqrt(m2) - rho
        if f > 0.0:
            hi = s
        else:
            lo = s
        df = a / (c2 * math.sqrt(c2)) + thick * n * n / (m2 * math.sqrt(m2))
        s_new = s - f / df
        if not (lo < s_new < hi):                 # Newton left the bracket: bisect
            s_new = 0.5 * (lo + hi)
        if abs(s_new - s) <= 1e-16:
            return s_new
        s = s_new
    return s


@njit(nogil=True, cache=True, inline="always")
def slab_geometry(a, thick, n, s):  # pragma: no cover
    """For incidence ``sin(theta) = s``: ``(G, opl)`` with ``G`` the factor that turns the
    emitter's intensity into the irradiance on a surface perpendicular to the ray (``1/r^2``
    without the slab) and ``opl`` the optical path across ``a`` of air and the slab."""
    c = math.sqrt(1.0 - s * s)
    ct = math.sqrt(1.0 - (s / n) ** 2)
    rho_over_sin = a / c + thick / (n * ct)
    drho = a / (c * c) + thick * c / (n * ct * ct * ct)
    return 1.0 / (c * rho_over_sin * drho), a / c + n * thick / ct


@njit(nogil=True, cache=True)
def slab_link(px, py, pz, ex, ey, ez, centre, axes, half, k, n, sigma_a):  # pragma: no cover
    """The refracted link from point ``p`` to the emitter ``e`` across the box's slab along
    its local axis ``k`` (``axes[k]`` the unit axis in the world, ``half`` its half sizes).

    Returns ``(ok, ux, uy, uz, d1, d3, x2, y2, z2, T_F, G, opl)``: the unit direction of both
    air legs (from ``p`` toward the emitter), the air length from ``p`` to the entrance face
    ``d1`` and from the exit point ``(x2, y2, z2)`` to the emitter ``d3``, the Fresnel and
    absorption transmittance, the irradiance factor and the optical path. ``ok`` is False
    where the link does not exist through these two faces (``p`` and ``e`` not on opposite
    sides, or the refracted ray would leave through a side face).
    """
    mx, my, mz = axes[k, 0], axes[k, 1], axes[k, 2]
    hk = half[k]
    hp = (px - centre[0]) * mx + (py - centre[1]) * my + (pz - centre[2]) * mz
    he = (ex - centre[0]) * mx + (ey - centre[1]) * my + (ez - centre[2]) * mz
    bad = (False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    if not ((hp < -hk and he > hk) or (hp > hk and he < -hk)):
        return bad
    sg = 1.0 if he > hp else -1.0
    thick = 2.0 * hk
    a = abs(he - hp) - thick
    dx, dy, dz = ex - px, ey - py, ez - pz
    along = dx * mx + dy * my + dz * mz
    lx, ly, lz = dx - along * mx, dy - along * my, dz - along * mz
    rho = math.sqrt(lx * lx + ly * ly + lz * lz)
    if rho > 0.0:
        lx, ly, lz = lx / rho, ly / rho, lz / rho
    s = slab_incidence(a, thick, n, rho)
    c = math.sqrt(1.0 - s * s)
    st = s / n
    ct = math.sqrt(1.0 - st * st)
    ux, uy, uz = sg * c * mx + s * lx, sg * c * my + s * ly, sg * c * mz + s * lz
    d1 = (abs(hp) - hk) / c
    x1, y1, z1 = px + d1 * ux, py + d1 * uy, pz + d1 * uz
    g_in = thick / ct
    x2 = x1 + g_in * (sg * ct * mx + st * lx)
    y2 = y1 + g_in * (sg * ct * my + st * ly)
    z2 = z1 + g_in * (sg * ct * mz + st * lz)
    for j in range(3):       # both points on the faces, not beyond their edges
        if j == k:
            continue
        a1 = (x1 - centre[0]) * axes[j, 0] + (y1 - centre[1]) * axes[j, 1] + (z1 - centre[2]) * axes[j, 2]
        a2 = (x2 - centre[0]) * axes[j, 0] + (y2 - centre[1]) * axes[j, 1] + (z2 - centre[2]) * axes[j, 2]
        if abs(a1) > half[j] or abs(a2) > half[j]:
            return bad
    r1, _ = fresnel(c, 1.0, n)
    r2, _ = fresnel(ct, n, 1.0)
    tf = (1.0 - r1) * (1.0 - r2) * math.exp(-sigma_a * g_in)
    geo, opl = slab_geometry(a, thick, n, s)
    d3 = (abs(he) - hk) / c
    return True, ux, uy, uz, d1, d3, x2, y2, z2, tf, geo, opl


# --------------------------------------------------------------------------- media
@njit(nogil=True, cache=True, inline="always")
def hg_phase(cos_t, g):  # pragma: no cover
    """Henyey-Greenstein phase function (1/sr) at the cosine between the light's direction
    before and after scattering; integrates to 1 over the sphere, mean cosine ``g``."""
    d = 1.0 + g * g - 2.0 * g * cos_t
    return (1.0 - g * g) / (4.0 * math.pi * d * math.sqrt(d))


@njit(nogil=True, cache=True, inline="always")
def hg_sample(u1, u2, g, dx, dy, dz):  # pragma: no cover
    """A direction about the unit ``d`` drawn from the HG phase function (inverse CDF in the
    cosine, uniform azimuth): the sampling weight phase/pdf is 1."""
    if abs(g) < 1e-4:
        c = 1.0 - 2.0 * u1
    else:
        sq = (1.0 - g * g) / (1.0 - g + 2.0 * g * u1)
        c = (1.0 + g * g - sq * sq) / (2.0 * g)
    c = min(1.0, max(-1.0, c))
    sn = math.sqrt(max(0.0, 1.0 - c * c))
    phi = 2.0 * math.pi * u2
    sg = 1.0 if dz >= 0.0 else -1.0          # orthonormal frame about d (Duff et al. 2017)
    aa = -1.0 / (sg + dz)
    bb = dx * dy * aa
    t1x, t1y, t1z = 1.0 + sg * dx * dx * aa, sg * bb, -sg * dx
    t2x, t2y, t2z = bb, sg + dy * dy * aa, -dy
    a, b = sn * math.cos(phi), sn * math.sin(phi)
    return a * t1x + b * t2x + c * dx, a * t1y + b * t2y + c * dy, a * t1z + b * t2z + c * dz


@njit(nogil=True, cache=True, inline="always")
def box_chord(ox, oy, oz, dx, dy, dz, tmax, centre, axes, half):  # pragma: no cover
    """``(t0, t1)``: the part of the segment ``o + t d``, ``0 <= t <= tmax``, inside the box
    (slab method in the box's frame); ``t1 <= t0`` where it misses."""
    t0, t1 = 0.0, tmax
    for j in range(3):
        o = (ox - centre[0]) * axes[j, 0] + (oy - centre[1]) * axes[j, 1] + (oz - centre[2]) * axes[j, 2]
        d = dx * axes[j, 0] + dy * axes[j, 1] + dz * axes[j, 2]
        if abs(d) < 1e-300:
            if abs(o) > half[j]:
                return 0.0, -1.0
            continue
        a, b = (-half[j] - o) / d, (half[j] - o) / d
        if a > b:
            a, b = b, a
        t0, t1 = max(t0, a), min(t1, b)
    return t0, t1


@njit(nogil=True, cache=True, inline="always")
def hash_uniform(seed, counter):  # pragma: no cover
    """A uniform number in [0, 1) from a 64-bit seed and a counter (splitmix64): the free
    flights' random numbers, reproducible per sample and independent of threads."""
    z = np.uint64(seed) + np.uint64(counter + 1) * np.uint64(0x9E3779B97F4A7C15)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    z = z ^ (z >> np.uint64(31))
    return float(z >> np.uint64(11)) * (1.0 / 9007199254740992.0)


# --------------------------------------------------------------------------- scene tables
@dataclass
class DielectricTables:
    """Per-object arrays the path loop reads: index (0: opaque), absorption, and each box's
    centre, unit axes (rows, world frame) and half sizes."""

    ior: np.ndarray        # [O]
    sigma_a: np.ndarray    # [O] 1/m
    sigma_s: np.ndarray    # [O] 1/m (> 0: a scattering medium, index-matched)
    hg_g: np.ndarray       # [O] Henyey-Greenstein anisotropy
    centre: np.ndarray     # [O, 3]
    axes: np.ndarray       # [O, 3, 3]
    half: np.ndarray       # [O, 3]

    @property
    def any(self) -> bool:
        return bool(np.any(self.ior > 0))

    @property
    def scattering(self) -> bool:
        return bool(np.any(self.sigma_s > 0))


def dielectric_tables(scene) -> DielectricTables:
    """The scene's dielectric objects as :class:`DielectricTables` (boxes only: the parser
    refuses a dielectric material on any other object type)."""
    n = len(scene.objects)
    ior, sig, sig_s, hg = np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n)
    centre, axes, half = np.zeros((n, 3)), np.tile(np.eye(3), (n, 1, 1)), np.zeros((n, 3))
    for i, o in enumerate(scene.objects):
        m = scene.materials[o.material]
        if m.ior is None:
            continue
        ior[i], sig[i], sig_s[i], hg[i] = m.ior, m.absorption_per_m, m.scattering_per_m, m.anisotropy
        R = o.pose[:3, :3]
        centre[i] = o.pose[:3, 3]
        axes[i] = (R / np.linalg.norm(R, axis=0)).T
        half[i] = np.asarray(o.params["size"], dtype=np.float64) / 2
    return DielectricTables(ior, sig, sig_s, hg, centre, axes, half)


def inside_box(tab: DielectricTables, i: int, pts: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """Which of the world points ``pts`` [N, 3] lie inside box ``i`` (grown by ``margin``)."""
    loc = (np.atleast_2d(pts) - tab.centre[i]) @ tab.axes[i].T
    return np.all(np.abs(loc) < tab.half[i] + margin, axis=1)


@dataclass
class Glint:
    """A specular return with no diffuse vertex: the emitter's image in a face of a glass box,
    a point source for the camera. ``power_w`` lands on the pixel its ray ``direction`` (unit,
    world, from the camera) goes through."""

    object_index: int
    kind: str              # "front": off the face; "back": inside, off the opposite face
    direction: np.ndarray
    power_w: float
    opl_m: float


def glints(tab: DielectricTables, camera_pos: np.ndarray, camera_axis: np.ndarray, emitter_pos: np.ndarray,
           emitter_axis: np.ndarray, intensity_w_sr: Callable[[float], float], aperture_area_m2: float,
           blocked: Callable[[np.ndarray, np.ndarray, float], bool]) -> list[Glint]:
    """The emitter's images in the faces of every glass box, seen from the camera's pinhole.

    Front: the face reflects ``R(theta)``; the image is the emitter mirrored in the face, a
    point source at the unfolded distance ``L``: ``P = I R A cos(alpha) / L^2``. Back: the
    light enters, reflects off the opposite face inside (``R_i``) and leaves by the entrance
    face; unfolded about that face it is a slab of twice the thickness to the emitter's
    mirror image (:func:`slab_link`): ``P = I T_F R_i G A cos(alpha)``. ``alpha`` is the
    ray's angle to the camera's axis, ``A`` the aperture area; ``intensity_w_sr(cos)`` the
    emitter's intensity at that cosine to its axis; ``blocked(origin, unit_dir, dist)`` the
    scene's occlusion test of the air legs. Higher internal reflections (``R^3`` and less)
    are left out.
    """
    out: list[Glint] = []
    c, e = np.asarray(camera_pos, float), np.asarray(emitter_pos, float)
    eps = 1e-5
    for i in np.flatnonzero(tab.ior > 1.0):        # (index 1: no reflection)
        n = float(tab.ior[i])
        for k in range(3):
            for side in (1.0, -1.0):
                m = side * tab.axes[i, k]
                hk = tab.half[i, k]
                face = tab.centre[i] + hk * m
                hc, he = (c - face) @ m, (e - face) @ m
                if hc <= 0 or he <= 0:
                    continue
                lateral = [j for j in range(3) if j != k]
                # front face: the emitter mirrored in the face's plane
                e_img = e - 2 * he * m
                h = c + (e_img - c) * (hc / (hc + he))
                loc = (h - tab.centre[i]) @ tab.axes[i].T
                L = float(np.linalg.norm(e_img - c))
                d_cam = (e_img - c) / L
                if all(abs(loc[j]) <= tab.half[i, j] for j in lateral):
                    r, _ = fresnel((hc + he) / L, 1.0, n)
                    d_e = (h - e) / np.linalg.norm(h - e)
                    if not (blocked(c, d_cam, np.linalg.norm(h - c) - 2 * eps)
                            or blocked(e, d_e, np.linalg.norm(h - e) - 2 * eps)):
                        p = intensity_w_sr(float(d_e @ emitter_axis)) * r * aperture_area_m2 \
                            * max(float(d_cam @ camera_axis), 0.0) / L ** 2
                        out.append(Glint(int(i), "front", d_cam, p, L))
                # back face: unfold about the opposite face (a slab 2x as thick, from the
                # entrance face to its mirror image) to the emitter's image there
                back = tab.centre[i] - hk * m
                e_img = e - 2 * ((e - back) @ m) * m
                half = tab.half[i].copy()
                half[k] = 2 * hk
                ok, ux, uy, uz, d1, d3, x2, y2, z2, tf, geo, opl = slab_link(
                    c[0], c[1], c[2], e_img[0], e_img[1], e_img[2], back, tab.axes[i], half, k, n,
                    float(tab.sigma_a[i]))
                if not ok:
                    continue
                u = np.array([ux, uy, uz])
                _, ct = fresnel(float(abs(u @ m)), 1.0, n)
                r_in, _ = fresnel(ct, n, 1.0)
                x2r = np.array([x2, y2, z2])
                x2r = x2r - 2 * ((x2r - back) @ m) * m            # the real exit point
                d_e = (x2r - e) / np.linalg.norm(x2r - e)
                if blocked(c, u, d1 - 2 * eps) or blocked(e, d_e, d3 - 2 * eps):
                    continue
                p = intensity_w_sr(float(d_e @ emitter_axis)) * tf * r_in * geo * aperture_area_m2 \
                    * max(float(u @ camera_axis), 0.0)
                out.append(Glint(int(i), "back", u, p, opl))
    return out
