"""Multipath (path tracing with next-event estimation) checked against independent physics."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tofhil import C_M_PER_S
from tofhil.camera import CameraModel
from tofhil.demod import phase_to_distance, wrapped_phase
from tofhil.sim.render import render
from tofhil.sim.scene import load_scene, scene_from_dict

F_HZ = 44.0e6


def test_one_bounce_phasor_matches_quadrature_over_the_corner_walls() -> None:
    """The rendered first-bounce phasor of a pixel equals a brute-force integral over the walls."""
    c = 1.2 / math.sqrt(3)
    target = np.array([0.35, 0.45, 0.0])                       # a point on the wall z = 0
    scene = load_scene("corner", overrides={"camera": {"pose": {
        "position": [c, c, c], "look_at": target.tolist()}}})
    cam = CameraModel(width=3, height=3, fx=300.0, fy=300.0, cx=1.0, cy=1.0, pixel_pitch_m=24e-6)
    res = render(scene, camera=cam, samples_per_pixel=4096, bounces=1, separate_direct=True,
                 subpixel=False, seed=3)
    rho, size = 0.8, 1.6
    C = scene.camera_pose[:3, 3]
    axis = scene.camera_pose[:3, 2]
    x0 = target
    n0 = np.array([0.0, 0.0, 1.0])
    k = 2 * math.pi * F_HZ / C_M_PER_S

    def intensity(x: np.ndarray) -> np.ndarray:                # cos^2 beam, P = 0.3 W
        v = x - C
        cos_e = v @ axis / np.linalg.norm(v, axis=-1)
        return 0.3 * 3 / (2 * math.pi) * np.clip(cos_e, 0, None) ** 2

    # Midpoint rule over the two other walls (x = 0 and y = 0), 4 mm cells.
    m = 400
    g = (np.arange(m) + 0.5) * size / m
    a, b = np.meshgrid(g, g, indexing="ij")
    radiance = 0.0 + 0.0j
    for n1, pts in ((np.array([1.0, 0, 0]), np.stack([0 * a, a, b], -1)),
                    (np.array([0, 1.0, 0]), np.stack([a, 0 * a, b], -1))):
        to_e = C - pts
        r_e = np.linalg.norm(to_e, axis=-1)
        e1 = intensity(pts) * (to_e @ n1) / r_e / r_e ** 2
        d01 = pts - x0
        r01 = np.linalg.norm(d01, axis=-1)
        cos0 = (d01 @ n0) / r01
        cos1 = -(d01 @ n1) / r01
        dE = rho / math.pi * e1 * cos0 * cos1 / r01 ** 2 * (size / m) ** 2
        length = np.linalg.norm(x0 - C) + r01 + r_e
        radiance += rho / math.pi * np.sum(dE * np.exp(1j * k * length))
    f = cam.fx * 24e-6
    expect = radiance * math.pi * (f / (2 * 1.2)) ** 2 / (cam.fx * cam.fy)   # centre pixel, cos(alpha) = 1
    got = res.phasor_indirect[0, 0, 1, 1]
    assert abs(got) == pytest.approx(abs(expect), rel=0.01)
    assert abs(np.angle(got / expect)) < 0.003                  # rad; 0.003 rad = 1.6 mm of path


def test_closed_diffuse_sphere_follows_the_geometric_series_of_its_albedo() -> None:
    """Inside a Lambertian sphere every bounce after the first lights the wall uniformly with
    rho^k P / A, whatever the beam profile, so indirect/direct per pixel = sum_k rho^k * E0/E_dir."""
    rho, radius, power, n = 0.6, 1.0, 1.0, 2.0
    d = {"camera": {"width": 16, "height": 12, "fx": 8.0, "fy": 8.0, "cx": 7.5, "cy": 5.5,
                    "pixel_pitch_m": 50e-6},
         "emitter": {"power_w": power, "profile": {"type": "cos_n", "n": n}},
         "materials": {"wall": {"reflectance": rho}},
         "objects": [{"name": "sphere", "type": "sphere", "radius": radius, "subdivisions": 5,
                      "material": "wall"}],
         "sensor": {"freq_hz": [F_HZ]}}
    scene = scene_from_dict(d)
    cam = scene.camera
    e_uniform = power / (4 * math.pi * radius ** 2)              # P / A
    cos_a = cam.ray_z
    e_direct = power * (n + 1) / (2 * math.pi) * cos_a ** n / radius ** 2
    for bounces in (1, 3, 6):
        res = render(scene, samples_per_pixel=256, bounces=bounces, separate_direct=True, seed=bounces)
        ind = res.power_w - np.abs(res.phasor_direct[0, 0])           # indirect power (h = 0)
        ratio = np.sum(ind) / np.sum(np.abs(res.phasor_direct[0, 0]) * e_uniform / e_direct)
        series = sum(rho ** k for k in range(1, bounces + 1))
        assert ratio == pytest.approx(series, rel=0.01)
    assert series == pytest.approx(rho / (1 - rho), rel=0.05)    # 6 bounces: within 5 % of the limit


def test_corner_multipath_reads_too_far_most_near_the_concave_edges() -> None:
    """A room corner seen from 3 m: every pixel reads too far; the interreflection is strongest
    at the concave edges and the range error peaks in a band along them, falling off toward the
    open middle of the walls (at the edge line itself the extra path length goes to zero)."""
    scene = load_scene("corner", overrides={"params": {"wall_size_m": 8.0, "camera_distance_m": 3.0}})
    cam = scene.camera.scaled(0.2)
    res = render(scene, camera=cam, samples_per_pixel=64, bounces=2, separate_direct=True,
                 subpixel=False, seed=1)
    d_direct = phase_to_distance(wrapped_phase(res.phasor_direct[0, 0]), F_HZ)
    d_total = phase_to_distance(wrapped_phase(res.phasor[0, 0]), F_HZ)
    np.testing.assert_allclose(d_direct, res.radial_m, atol=1e-6)   # co-located emitter: direct is exact
    err = d_total - d_direct
    assert np.all(err > 0.02)
    pts = (cam.rays * res.radial_m[..., None]) @ scene.camera_pose[:3, :3].T + scene.camera_pose[:3, 3]
    s = np.sort(np.abs(pts), axis=-1)[..., 1]                    # distance from the nearest edge line
    strength = (res.power_w - np.abs(res.phasor_direct[0, 0])) / np.abs(res.phasor_direct[0, 0])
    assert strength[s < 0.1].mean() > 1.5 * strength[s > 0.8].mean()
    near, far = err[(s > 0.2) & (s < 0.6)].mean(), err[s > 1.0].mean()
    assert near > 1.3 * far


@pytest.mark.parametrize("sampler", ["random", "sobol"])
def test_monte_carlo_error_falls_as_one_over_sqrt_samples(sampler: str) -> None:
    scene = load_scene("corner")
    cam = scene.camera.scaled(0.15)

    def rms_spread(spp: int) -> float:
        runs = [render(scene, camera=cam, samples_per_pixel=spp, bounces=1, subpixel=False,
                       sampler=sampler, seed=s).phasor[0, 0] for s in range(4)]
        runs = np.stack(runs)
        return float(np.sqrt(np.mean(np.abs(runs - runs.mean(axis=0)) ** 2)))

    ratio = rms_spread(4) / rms_spread(64)                       # 16x the samples
    if sampler == "random":
        assert ratio == pytest.approx(4.0, rel=0.15)             # exactly 1/sqrt(N)
    else:
        assert ratio > 4.0 * 0.9                                 # at least as fast (QMC: faster)


def test_multipath_estimate_is_unbiased_across_samplers() -> None:
    scene = load_scene("corner")
    cam = scene.camera.scaled(0.1)
    a = render(scene, camera=cam, samples_per_pixel=1024, bounces=2, subpixel=False, sampler="random", seed=5)
    b = render(scene, camera=cam, samples_per_pixel=1024, bounces=2, subpixel=False, sampler="sobol", seed=6)
    # Whole-image sums average out the per-pixel noise (< 0.5 %).
    assert abs(a.phasor.sum() / b.phasor.sum() - 1) < 0.005


def test_renders_are_deterministic_for_a_seed_and_independent_of_threads() -> None:
    scene = load_scene("corner")
    cam = scene.camera.scaled(0.5)                     # 80 x 60 at 16 spp: several batches
    a = render(scene, camera=cam, samples_per_pixel=16, bounces=1, seed=4, threads=1)
    b = render(scene, camera=cam, samples_per_pixel=16, bounces=1, seed=4, threads=2)
    c = render(scene, camera=cam, samples_per_pixel=16, bounces=1, seed=5, threads=2)
    np.testing.assert_array_equal(a.phasor, b.phasor)
    assert not np.array_equal(a.phasor, c.phasor)
