"""Light from a surface the scene lacks: one indirect bounce off a reflector outside the twin.

A white panel, a wall or a person beside the camera, outside its field of view, is lit by the
emitter and lights the scene in turn: every scene point receives a second, longer path. The
twin cannot make it (the surface is not in its scene), so its residual is a smooth extra light
whose phase says how much longer its path is, on every frequency alike.
"""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from tofhil import C_M_PER_S
from tofhil.content_cache import LRUCache, content_digest
from tofhil.sim.effects.base import Effect, EffectContext, Param
from tofhil.sim.effects.registry import register
from tofhil.sim.sensor import OpticalSignal


#: The last frame's scene points, by the content of its distances and camera (a fit evaluates
#: the effect on one render hundreds of times).
_LAST_POINTS = LRUCache(1)


def scene_points(radial_m: np.ndarray, camera: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each pixel's first hit ``X`` (camera frame), its surface normal facing the camera (from
    the neighbouring hits) and where a hit exists, ``[H, W, 3]``, ``[H, W, 3]``, ``[H, W]``."""
    r = np.asarray(radial_m, dtype=np.float64)
    key = content_digest(r, camera)
    points = _LAST_POINTS.get(key)
    if points is None:
        points = _scene_points(r, camera)
        _LAST_POINTS.put(key, points)
    return points


def _scene_points(r: np.ndarray, camera: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rays = camera.rays
    # a pixel whose ray a distortion leaves undefined sees nothing (its NaN would spread)
    hit = np.isfinite(r) & (r > 0) & np.isfinite(rays).all(axis=-1)
    x = np.where(hit[..., None], rays * np.where(hit, r, 0.0)[..., None], 0.0)
    n = np.cross(np.gradient(x, axis=1), np.gradient(x, axis=0))
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        n = np.where(norm > 0, n / norm, 0.0)
    n *= -np.sign(np.sum(n * x, axis=-1, keepdims=True))
    return x, n, hit


@register
class UnseenReflectorEffect(Effect):
    name = "unseen_reflector"
    stage = "signal"
    rank = 55
    beyond_direct = "multipath"
    pixel_local = False  # the surface normals come from the neighbouring pixels' hits
    local_given_render = True  # ... of the render; each pixel's light is its own
    summary = ("light from a diffuse reflector outside the view that the scene lacks (its direction, distance and "
               "effective area): one bounce, emitter -> reflector -> scene point, with its longer path")
    doc = ("One indirect bounce off a small diffuse reflector that the scene does not have (a panel, a wall or a "
           "person beside the camera, outside its view): the emitter lights the reflector at P (camera frame: "
           "`azimuth_deg` about the optical axis, `beyond_deg` beyond the view's half-diagonal, `distance_m`), "
           "which lights each scene point X as a small diffuse patch of effective area `10^log_area` m^2 (its "
           "albedo / pi, its size and the emitter's cosine on it) whose normal faces the scene's centre, turned "
           "by `turn_deg` and `tilt_deg`. Both lights leave X by the same BRDF, so the pixel gets "
           "`area cos_out(P) cos_in(X) / |X - P|^2` over the direct `p(X) cos_direct(X) / |X - E|^2` (p the emitter's "
           "beam) of its direct light, with the path longer by `|P - E| + |X - P| - |X - E|` (E the "
           "emitter). Modulated and unmodulated light alike; acts before the lens's stray light. Needs the "
           "render's first-hit distances.")
    # Where the reflector is: outside the view (a surface inside it would be in the image), so
    # by its direction from the camera (azimuth about the optical axis, the angle beyond the
    # view's edge) and its distance; the fit starts on each side of the view.
    params = {
        "azimuth_deg": Param(0.0, -180.0, 180.0, "deg", "direction about the optical axis (0 = +x, 90 = +y)",
                             default=0.0, fit=(-180.0, 180.0), step=2.0, start=0.0, starts=(90.0, 180.0, -90.0),
                             periodic=True),
        "beyond_deg": Param(20.0, 0.0, 150.0, "deg", "angle from the optical axis beyond the view's edge",
                            default=20.0, fit=(0.0, 120.0), step=2.0, start=20.0),
        "distance_m": Param(0.5, 0.0, 20.0, "m", "distance from the camera", default=0.5,
                            fit=(0.1, 3.0), step=0.02, start=0.5),
        "log_area": Param(-12.0, -12.0, 1.0, "log10 m^2", "effective area (albedo / pi x size x cosines)",
                          default=-2.0, fit=(-12.0, 0.0), step=0.1, start=-2.5),
        # a diffuse patch sends light by the cosine to its normal: facing the scene's centre,
        # turned about the camera's y and x axes
        "turn_deg": Param(0.0, -90.0, 90.0, "deg", "the reflector's normal turned about the camera's y axis",
                          fit=(-80.0, 80.0), step=2.0, start=0.0, starts=(-40.0, 40.0)),
        "tilt_deg": Param(0.0, -90.0, 90.0, "deg", "the reflector's normal tilted about the camera's x axis",
                          fit=(-80.0, 80.0), step=2.0, start=0.0),
    }

    @staticmethod
    def position(values: Mapping[str, Any], camera: Any) -> np.ndarray:
        """The reflector's position (camera frame, m)."""
        edge = float(np.nanmax(np.arccos(np.clip(camera.rays[..., 2], -1.0, 1.0))))  # the view's half-diagonal
        polar = min(edge + np.radians(float(values["beyond_deg"])), np.pi)
        az = np.radians(float(values["azimuth_deg"]))
        d = float(values["distance_m"])
        return d * np.array([np.sin(polar) * np.cos(az), np.sin(polar) * np.sin(az), np.cos(polar)])

    def is_off(self, values: Mapping[str, Any]) -> bool:
        return float(values.get("log_area", -12.0)) <= -12.0

    @staticmethod
    def normal(values: Mapping[str, Any], p: np.ndarray, x: np.ndarray, hit: np.ndarray) -> np.ndarray:
        """The reflector's unit normal: toward the scene's centre (the hit nearest the view's
        centre), turned by ``turn_deg`` about the camera's y axis and ``tilt_deg`` about x."""
        h, w = hit.shape
        pts = x[hit]
        centre = x[h // 2, w // 2] if hit[h // 2, w // 2] else (pts.mean(axis=0) if pts.size else np.array([0, 0, 1.0]))
        m = centre - p
        m = m / max(float(np.linalg.norm(m)), 1e-12)
        a, b = np.radians(float(values.get("turn_deg", 0.0))), np.radians(float(values.get("tilt_deg", 0.0)))
        m = np.array([np.cos(a) * m[0] + np.sin(a) * m[2], m[1], -np.sin(a) * m[0] + np.cos(a) * m[2]])
        return np.array([m[0], np.cos(b) * m[1] - np.sin(b) * m[2], np.sin(b) * m[1] + np.cos(b) * m[2]])

    @staticmethod
    def share(values: Mapping[str, Any], ctx: EffectContext, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        """The reflector's light over each pixel's direct light, and its path excess (m), on a
        signal of ``shape`` (the frame, or the pixels of ``ctx.pixels``)."""
        if ctx.radial_m is None:
            raise ValueError("unseen_reflector needs the render's first-hit distances")
        x, n, hit = scene_points(ctx.radial_m, ctx.camera)
        e = np.zeros(3) if ctx.emitter is None else np.asarray(ctx.emitter.offset_m, dtype=np.float64)
        p = UnseenReflectorEffect.position(values, ctx.camera)
        m = UnseenReflectorEffect.normal(values, p, x, hit)
        if ctx.pixels is not None:  # the whole frame's geometry, at the pixels asked for
            x, n, hit = x.reshape(-1, 3)[ctx.pixels], n.reshape(-1, 3)[ctx.pixels], hit.reshape(-1)[ctx.pixels]
        to_p = p - x
        r2 = np.linalg.norm(to_p, axis=-1)
        from_e = x - e
        re = np.linalg.norm(from_e, axis=-1)
        with np.errstate(invalid="ignore", divide="ignore"):
            cos_in = np.clip(np.sum(to_p * n, axis=-1) / r2, 0.0, None)
            cos_out = np.clip(-(to_p @ m) / r2, 0.0, None)
            cos_direct = np.clip(-np.sum(from_e * n, axis=-1) / re, 0.0, None)
            axis = np.array([0.0, 0.0, 1.0]) if ctx.emitter is None else np.asarray(ctx.emitter.axis, dtype=np.float64)
            beam = (np.clip(from_e @ axis / re, 0.0, 1.0) if ctx.emitter is None
                    else ctx.emitter.profile.relative(from_e @ axis / re))
            direct = beam * cos_direct / re ** 2
            ratio = np.where(hit & (direct > 0), 10.0 ** float(values["log_area"]) * cos_in * cos_out / r2 ** 2
                             / np.where(direct > 0, direct, 1.0), 0.0)
        excess = np.where(hit, float(np.linalg.norm(p - e)) + r2 - re, 0.0)
        return ratio.reshape(shape), excess.reshape(shape)

    def apply_signal(self, signal: OpticalSignal, values: Mapping[str, Any], ctx: EffectContext) -> OpticalSignal:
        if self.is_off(values):
            return signal.copy()
        ratio, excess = self.share(values, ctx, signal.shape)
        h = np.asarray(signal.harmonics, dtype=np.float64)
        k = 2.0 * np.pi * signal.freq_hz[:, None] * h[None, :] / C_M_PER_S               # [F, NH]
        out = signal.copy()
        out.phasor_w = signal.phasor_w * (1.0 + ratio * np.exp(1j * k[..., None, None] * excess))
        out.dc_w = np.asarray(signal.dc_w) * (1.0 + ratio)
        return out
