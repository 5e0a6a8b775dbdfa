"""A homogeneous participating medium in a box (tofhil.sim.dielectric media, the renderer's
free flights) against closed form: pure absorption both ways, single scattering of a slab
by quadrature, the Henyey-Greenstein phase function and its sampling; bad medium keys."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tofhil.errors import TofhilError
from tofhil.sim.dielectric import hash_uniform, hg_phase, hg_sample
from tofhil.sim.render import render
from tofhil.sim.scene import scene_from_dict

F_HZ = 44.0e6
CAM = {"width": 16, "height": 12, "fx": 12.0, "fy": 12.0, "cx": 7.5, "cy": 5.5, "pixel_pitch_m": 96e-6,
       "f_number": 1.2}


def fog_scene(medium: dict, wall: bool = True, z0: float = 0.3, t: float = 0.05) -> dict:
    """Camera and a cos^1 emitter at the origin, a 3 m wide medium slab (faces z0, z0 + t),
    optionally a white wall at 1 m behind it."""
    objs = [{"name": "fog", "type": "box", "size": [3, 3, t], "material": "fog",
             "pose": {"position": [0, 0, z0 + t / 2]}}]
    if wall:
        objs.insert(0, {"name": "wall", "type": "plane", "size": [20, 20], "material": "white",
                        "pose": {"position": [0, 0, 1.0]}})
    return {"camera": CAM, "emitter": {"power_w": 1.0, "offset_m": [0, 0, 0], "profile": {"type": "cos_n", "n": 1}},
            "materials": {"white": {"reflectance": 0.8}, "fog": medium}, "objects": objs,
            "sensor": {"freq_hz": [F_HZ]}}


def pixel_angles() -> np.ndarray:
    v, u = np.mgrid[0:CAM["height"], 0:CAM["width"]].astype(float)
    return np.arctan(np.hypot((u - CAM["cx"]) / CAM["fx"], (v - CAM["cy"]) / CAM["fy"]))


def test_absorbing_slab_attenuates_both_ways() -> None:
    sigma, t = 4.0, 0.05
    a = render(scene_from_dict(fog_scene({"scattering_per_m": 0.0, "absorption_per_m": sigma}, t=t)))
    b = render(scene_from_dict(fog_scene({"scattering_per_m": 0.0, "absorption_per_m": 0.0}, t=t)))
    # index 1: no refraction, no reflection; the camera ray and the emitter's light each cross t/cos
    expected = np.exp(-sigma * 2 * t / np.cos(pixel_angles()))
    np.testing.assert_allclose(a.power_w / b.power_w, expected, rtol=1e-9)
    np.testing.assert_allclose(np.angle(a.phasor / b.phasor), 0.0, atol=1e-9)   # index 1: no delay


def test_single_scattering_of_a_slab_matches_quadrature() -> None:
    # bounces = 0: each camera ray's first scattering event, linked to the emitter at the
    # pinhole (back-scattering, cos = -1). Radiance along a ray at angle theta, distance l:
    # L = int sigma_s p(-1) I(theta) / l^2 exp(-2 sigma_t (l - l0)) dl over the slab, the path 2 l.
    sig_s, sig_a, g, z0, t = 4.0, 1.0, 0.3, 0.3, 0.05
    res = render(scene_from_dict(fog_scene({"scattering_per_m": sig_s, "absorption_per_m": sig_a, "anisotropy": g},
                                           wall=False, z0=z0, t=t)),
                 samples_per_pixel=1024, subpixel=False, bounces=0)
    sig_t = sig_s + sig_a
    p_back = (1 - g * g) / (4 * math.pi * (1 + g) ** 3)
    f = CAM["fx"] * CAM["pixel_pitch_m"]
    k = 2 * math.pi * F_HZ / 299792458.0
    cos = np.cos(pixel_angles())
    power = np.zeros_like(cos)
    phasor = np.zeros_like(cos, dtype=complex)
    for idx, c in np.ndenumerate(cos):
        ell = np.linspace(z0 / c, (z0 + t) / c, 2001)
        radiance = sig_s * p_back * (2 / (2 * math.pi)) * c / ell ** 2 * np.exp(-2 * sig_t * (ell - z0 / c))
        to_pixel = math.pi * (f / 2.4) ** 2 * c ** 4 * CAM["pixel_pitch_m"] ** 2 / f ** 2
        power[idx] = np.trapezoid(radiance, ell) * to_pixel
        phasor[idx] = np.trapezoid(radiance * np.exp(2j * k * ell), ell) * to_pixel
    rel = res.power_w / power - 1
    noise = rel.std() / math.sqrt(rel.size)            # the image sum's Monte Carlo error
    assert abs(res.power_w.sum() / power.sum() - 1) < 4 * noise + 1e-4, (res.power_w.sum() / power.sum(), noise)
    assert abs(res.phasor[0, 0].sum() / phasor.sum() - 1) < 4 * noise + 1e-4
    assert noise < 0.01


def test_henyey_greenstein_normalised_with_mean_cosine_g() -> None:
    from scipy.integrate import quad

    for g in (-0.5, 0.0, 0.3, 0.9):
        assert 2 * math.pi * quad(lambda x: hg_phase(x, g), -1, 1, points=[1.0])[0] == pytest.approx(1.0, abs=1e-9)
        assert 2 * math.pi * quad(lambda x: x * hg_phase(x, g), -1, 1)[0] == pytest.approx(g, abs=1e-9)


@pytest.mark.parametrize("g", [0.0, 0.6, -0.4])
def test_henyey_greenstein_sampling_follows_the_phase_function(g: float) -> None:
    # Directions about an oblique axis: their cosines' histogram against the phase function,
    # unit length, uniform azimuth (mean of the perpendicular part ~ 0).
    d = np.array([0.3, -0.5, 0.8])
    d /= np.linalg.norm(d)
    n = 40000
    rng = np.random.default_rng(1)
    u = rng.random((n, 2))
    w = np.array([hg_sample(a, b, g, d[0], d[1], d[2]) for a, b in u])
    np.testing.assert_allclose(np.linalg.norm(w, axis=1), 1.0, atol=1e-12)
    cos = w @ d
    hist, edges = np.histogram(cos, bins=20, range=(-1, 1))
    mids = 0.5 * (edges[1:] + edges[:-1])
    expect = np.array([2 * math.pi * hg_phase(m, g) for m in mids]) * (edges[1] - edges[0]) * n
    assert np.all(np.abs(hist - expect) < 5 * np.sqrt(expect) + 0.02 * expect)
    perp = w - cos[:, None] * d
    assert np.linalg.norm(perp.mean(axis=0)) < 0.02


def test_hash_uniform_is_uniform_and_reproducible() -> None:
    x = np.array([hash_uniform(np.uint64(12345), i) for i in range(20000)])
    assert x.min() >= 0 and x.max() < 1
    assert abs(x.mean() - 0.5) < 0.01 and abs(x.var() - 1 / 12) < 0.005
    assert hash_uniform(np.uint64(7), 3) == hash_uniform(np.uint64(7), 3)


@pytest.mark.parametrize("medium, field", [
    ({"scattering_per_m": 2.0, "ior": 1.4}, "materials.fog.ior"),
    ({"scattering_per_m": 2.0, "anisotropy": 1.5}, "materials.fog.anisotropy"),
    ({"ior": 1.0, "anisotropy": 0.5}, "materials.fog.anisotropy"),
    ({"scattering_per_m": -1.0}, "materials.fog.scattering_per_m"),
])
def test_bad_medium_names_its_field(medium: dict, field: str) -> None:
    with pytest.raises(TofhilError) as e:
        scene_from_dict(fog_scene(medium))
    assert field in str(e.value)


def test_glass_and_media_round_trip_through_the_scene_dict() -> None:
    d = fog_scene({"scattering_per_m": 3.0, "absorption_per_m": 0.5, "anisotropy": 0.4})
    d["materials"]["glass"] = {"ior": 1.6, "absorption_per_m": 2.0}
    d["objects"].append({"name": "pane", "type": "box", "size": [1, 1, 0.01], "material": "glass",
                         "pose": {"position": [0, 0, 0.2]}})
    a = scene_from_dict(d)
    b = scene_from_dict(a.to_dict())
    assert b.materials["fog"] == a.materials["fog"] and b.materials["glass"] == a.materials["glass"]
    assert (b.materials["fog"].ior, b.materials["fog"].scattering_per_m, b.materials["fog"].anisotropy) == (1.0, 3.0, 0.4)
    assert (b.materials["glass"].ior, b.materials["glass"].absorption_per_m) == (1.6, 2.0)
