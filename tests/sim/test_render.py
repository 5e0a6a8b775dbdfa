"""Direct-light rendering checked against closed-form physics of a fronto-parallel plane."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tofhil import C_M_PER_S
from tofhil.camera import CameraModel
from tofhil.demod import phase_to_distance, wrapped_phase
from tofhil.sim import kernels
from tofhil.sim.render import render, scene_geometry
from tofhil.sim.scene import scene_from_dict

F_HZ = 44.0e6


def plane_scene(distance: float = 1.0, reflectance: float = 0.8, n: float = 1.0, power: float = 1.0,
                offset=(0.0, 0.0, 0.0), camera: dict | None = None, size: float = 20.0, **extra) -> dict:
    d = {
        "camera": camera or {"preset": "holmlund_thesis"},
        "emitter": {"power_w": power, "offset_m": list(offset), "profile": {"type": "cos_n", "n": n}},
        "materials": {"white": {"reflectance": reflectance}},
        "objects": [{"name": "wall", "type": "plane", "size": [size, size], "material": "white",
                     "pose": {"position": [0.0, 0.0, distance]}}],
        "sensor": {"freq_hz": [F_HZ]},
    }
    d.update(extra)
    return d


def small_camera() -> dict:
    # 40 x 30 crop of the thesis camera geometry keeps the tests fast.
    return {"width": 40, "height": 30, "fx": 29.17, "fy": 29.17, "cx": 19.5, "cy": 14.5,
            "pixel_pitch_m": 96e-6}


def closed_form_power(cam: CameraModel, distance: float, rho: float, n: float, power: float,
                      f_number: float) -> np.ndarray:
    """Pixel power of a Lambertian plane lit by a co-located cos^n emitter, written out by hand.

    Pixel ray at angle a to the axis hits the plane at r = D/cos a; the emitter sees it at
    angle a, the surface normal too: E = P (n+1)/(2 pi) cos^n a * cos a / r^2,
    L = rho E / pi, P_pix = L * pi (f/2N)^2 * cos^4 a * pitch^2 / f^2.
    """
    v, u = np.mgrid[0:cam.height, 0:cam.width].astype(float)
    x, y = (u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy
    cos_a = 1.0 / np.sqrt(1 + x * x + y * y)
    r = distance / cos_a
    irradiance = power * (n + 1) / (2 * math.pi) * cos_a ** n * cos_a / r ** 2
    radiance = rho * irradiance / math.pi
    f = cam.fx * cam.pixel_pitch_m
    return radiance * math.pi * (f / (2 * f_number)) ** 2 * cos_a ** 4 * cam.pixel_pitch_m ** 2 / f ** 2


def exact_radial(cam: CameraModel, distance: float) -> np.ndarray:
    v, u = np.mgrid[0:cam.height, 0:cam.width].astype(float)
    x, y = (u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy
    return distance * np.sqrt(1 + x * x + y * y)


@pytest.mark.parametrize("distance", [0.5, 1.0, 2.7])
def test_plane_phase_gives_exact_radial_distance(distance: float) -> None:
    scene = scene_from_dict(plane_scene(distance))
    res = render(scene)
    truth = exact_radial(scene.camera, distance)
    d_phase = phase_to_distance(wrapped_phase(res.phasor[0, 0]), F_HZ)
    wrapped_truth = np.mod(truth, C_M_PER_S / (2 * F_HZ))  # far corners at 2.7 m pass c/2f
    assert np.abs(d_phase - wrapped_truth).max() < 1e-4   # < 0.1 mm at every pixel
    assert np.abs(res.radial_m - truth).max() < 1e-6
    assert np.all(res.object_id == 0)


def test_plane_power_matches_camera_equation() -> None:
    for rho, n, p, fn in [(0.8, 1.0, 1.0, None), (0.3, 4.0, 2.5, 2.0)]:
        extra = {} if fn is None else {"f_number": fn}
        d = plane_scene(1.3, rho, n, p, camera={"preset": "holmlund_thesis", **extra})
        scene = scene_from_dict(d)
        res = render(scene)
        expect = closed_form_power(scene.camera, 1.3, rho, n, p, 1.2 if fn is None else fn)
        np.testing.assert_allclose(res.power_w, expect, rtol=1e-9)
        # |phasor| is the power for a single path per pixel.
        np.testing.assert_allclose(np.abs(res.phasor[0, 0]), expect, rtol=1e-9)


def test_inverse_square_law() -> None:
    # Doubling the distance quarters the centre pixel's power (all cosines = 1 there).
    cam = {"width": 3, "height": 3, "fx": 100.0, "fy": 100.0, "cx": 1.0, "cy": 1.0, "pixel_pitch_m": 20e-6}
    p1 = render(scene_from_dict(plane_scene(0.8, camera=cam))).power_w[1, 1]
    p2 = render(scene_from_dict(plane_scene(1.6, camera=cam))).power_w[1, 1]
    assert p1 / p2 == pytest.approx(4.0, rel=1e-9)


def test_phase_wraps_at_half_wavelength() -> None:
    ambiguity = C_M_PER_S / (2 * F_HZ)                    # 3.41 m at 44 MHz
    cam = {"width": 5, "height": 5, "fx": 100.0, "fy": 100.0, "cx": 2.0, "cy": 2.0, "pixel_pitch_m": 20e-6}
    for d in (ambiguity - 0.2, ambiguity + 0.3, 2 * ambiguity + 0.1):
        res = render(scene_from_dict(plane_scene(d, camera=cam)))
        d_phase = phase_to_distance(wrapped_phase(res.phasor[0, 0]), F_HZ)[2, 2]
        assert d_phase == pytest.approx(math.fmod(d, ambiguity), abs=1e-6)


def test_emitter_offset_path_length_and_harmonics() -> None:
    # Offset emitter: L = |x| + |x - e|; harmonic h turns h times faster.
    off = (0.05, -0.02, 0.0)
    scene = scene_from_dict(plane_scene(1.0, offset=off, camera=small_camera()))
    res = render(scene, harmonics=(1, 3))
    cam = scene.camera
    pts = cam.rays * exact_radial(cam, 1.0)[..., None]
    L = np.linalg.norm(pts, axis=-1) + np.linalg.norm(pts - np.array(off), axis=-1)
    for i, h in enumerate((1, 3)):
        expect = np.mod(2 * np.pi * h * F_HZ * L / C_M_PER_S, 2 * np.pi)
        got = np.mod(np.angle(res.phasor[0, i]), 2 * np.pi)
        err = np.angle(np.exp(1j * (got - expect)))
        assert np.abs(err).max() < 1e-9


def test_several_frequencies_and_harmonics_keep_their_axes() -> None:
    scene = scene_from_dict(plane_scene(2.0, camera=small_camera()))
    freqs = [20e6, 80e6, 100e6]
    res = render(scene, freq_hz=freqs, harmonics=(1, 2))
    truth = exact_radial(scene.camera, 2.0)
    assert res.phasor.shape == (3, 2, 30, 40)
    for i, f in enumerate(freqs):
        for j, h in enumerate((1, 2)):
            expect = np.exp(1j * 4 * np.pi * h * f * truth / C_M_PER_S)
            np.testing.assert_allclose(res.phasor[i, j] / np.abs(res.phasor[i, j]), expect, atol=1e-9)


def test_camera_pose_override_moves_the_camera_not_the_scene() -> None:
    scene = scene_from_dict(plane_scene(1.0, offset=(0.03, 0.0, 0.0), camera=small_camera()))
    pose = np.eye(4)
    pose[2, 3] = 0.25                                    # 25 cm toward the wall
    moved = render(scene, camera_pose=pose)
    cam = scene.camera
    np.testing.assert_allclose(moved.radial_m, exact_radial(cam, 0.75), rtol=1e-12)
    # The emitter rides with the camera: L = |x| + |x - e| in the moved camera frame.
    pts = cam.rays * exact_radial(cam, 0.75)[..., None]
    L = np.linalg.norm(pts, axis=-1) + np.linalg.norm(pts - np.array([0.03, 0, 0]), axis=-1)
    err = np.angle(moved.phasor[0, 0] * np.exp(-2j * np.pi * F_HZ * L / C_M_PER_S))
    assert np.abs(err).max() < 1e-9
    np.testing.assert_array_equal(scene.camera_pose, np.eye(4))
    np.testing.assert_allclose(render(scene).radial_m, exact_radial(cam, 1.0), rtol=1e-12)


def test_fused_path_loop_equals_the_wavefront_loop(monkeypatch: pytest.MonkeyPatch) -> None:
    """The compiled per-sample path loop (Embree called from the kernel) and the bounce-by-bounce
    wavefront loop over embreex trace the same float32 rays with the same uniforms: equal
    phasors, transients, ground truth and ray counts, for a smooth sphere, a glossy wall,
    subpixel sampling, two bounces, two frequencies and two harmonics."""
    d = plane_scene(distance=1.5, camera=small_camera(), size=4.0, offset=(0.02, 0.0, 0.0))
    d["materials"]["shiny"] = {"reflectance": 0.5, "glossy": {"reflectance": 0.3, "exponent": 8}}
    d["objects"].append({"name": "ball", "type": "sphere", "radius": 0.25, "subdivisions": 2,
                         "material": "shiny", "pose": {"position": [0.1, 0.05, 1.0]}})
    d["sensor"] = {"freq_hz": [F_HZ, 2 * F_HZ]}
    scene = scene_from_dict(d)
    geom = scene_geometry(scene)
    assert geom.vnormal is not None and geom.direct is not None
    out = {}
    for mode in ("1", "0"):
        monkeypatch.setenv("TOFHIL_RENDER_WAVEFRONT", mode)
        out[mode] = render(scene, samples_per_pixel=4, bounces=2, harmonics=(1, 3), transient_bins=16,
                           separate_direct=True, seed=3)
    a, b = out["1"], out["0"]
    scale = np.abs(a.phasor).max()
    assert scale > 0 and np.abs(a.phasor_indirect).max() > 0
    for x, y in ((a.phasor_direct, b.phasor_direct), (a.phasor_indirect, b.phasor_indirect)):
        np.testing.assert_allclose(x, y, rtol=0, atol=1e-12 * scale)
    np.testing.assert_allclose(a.transient, b.transient, rtol=0, atol=1e-12 * a.transient.max())
    np.testing.assert_allclose(a.power_w, b.power_w, rtol=1e-12)
    np.testing.assert_array_equal(a.radial_m, b.radial_m)
    np.testing.assert_array_equal(a.object_id, b.object_id)
    np.testing.assert_allclose(a.ambient_power_per_irradiance, b.ambient_power_per_irradiance, rtol=1e-12)
    assert a.rays_traced == b.rays_traced


@pytest.mark.parametrize("profile", [
    {"type": "table", "theta_deg": [0.0, 180.0], "relative_intensity": [1.0, 1.0]},     # isotropic
    # tilted axis: surface points before the table (2.0), on it and after its end (0)
    {"type": "table", "theta_deg": [50.0, 80.0, 95.0], "relative_intensity": [2.0, 1.0, 0.5]},
])
def test_fused_loop_takes_tabulated_beams_like_the_wavefront_loop(monkeypatch: pytest.MonkeyPatch,
                                                                  profile: dict) -> None:
    """A tabulated beam (isotropic: one value over the sphere) runs in the compiled path loop
    with the table looked up in the kernel: the same phasors as the wavefront loop, where
    numpy's ``BeamProfile.relative`` gives the intensity."""
    d = plane_scene(distance=1.5, camera=small_camera(), size=4.0)
    d["emitter"]["profile"] = profile
    d["emitter"]["axis"] = [math.sin(math.radians(70.0)), 0.0, math.cos(math.radians(70.0))]
    d["objects"].append({"name": "ball", "type": "sphere", "radius": 0.25, "subdivisions": 1,
                         "material": "white", "pose": {"position": [0.1, 0.05, 1.0]}})
    scene = scene_from_dict(d)
    fused_calls = []
    trace = kernels.trace_paths
    monkeypatch.setattr(kernels, "trace_paths", lambda *a: fused_calls.append(1) or trace(*a))
    out = {}
    for mode in ("1", "0"):
        monkeypatch.setenv("TOFHIL_RENDER_WAVEFRONT", mode)
        out[mode] = render(scene, samples_per_pixel=2, bounces=2, separate_direct=True, seed=5)
        assert bool(fused_calls) == (mode == "0")
    a, b = out["1"], out["0"]
    scale = np.abs(a.phasor).max()
    assert scale > 0 and np.abs(a.phasor_indirect).max() > 0
    if len(profile["theta_deg"]) == 3:
        # some pixels lit, some beyond the table's end (dark in the direct light)
        assert np.mean(np.abs(a.phasor_direct[0, 0]) == 0) > 0.05
        assert np.mean(np.abs(a.phasor_direct[0, 0]) > 0) > 0.05
    for x, y in ((a.phasor_direct, b.phasor_direct), (a.phasor_indirect, b.phasor_indirect)):
        np.testing.assert_allclose(x, y, rtol=0, atol=1e-12 * scale)
    np.testing.assert_allclose(a.power_w, b.power_w, rtol=1e-12, atol=1e-15 * a.power_w.max())
    assert a.rays_traced == b.rays_traced


@pytest.mark.parametrize("sampler", ["sobol", "random"])
def test_samples_sharing_a_camera_ray_are_the_paths_of_the_wavefront_loop(monkeypatch: pytest.MonkeyPatch,
                                                                         sampler: str) -> None:
    """With bounces and 256 samples, groups of 4 consecutive samples of a pixel continue one
    camera ray (the sampler gives them the same camera uniforms): the compiled loop traces
    that ray and its emitter connection once per group and adds the connection 4 times over;
    the wavefront loop traces every sample's copy. Same phasors, transients and ambient;
    fewer rays, by at most the followers' camera and shadow rays."""
    from tofhil.sim import render as render_mod

    cam = {"width": 10, "height": 8, "fx": 7.3, "fy": 7.3, "cx": 4.5, "cy": 3.5, "pixel_pitch_m": 384e-6}
    d = plane_scene(distance=1.2, camera=cam, size=2.0, offset=(0.02, 0.0, 0.0))
    d["objects"].append({"name": "floor", "type": "plane", "size": [1.0, 2.0], "material": "white",
                         "pose": {"position": [0.0, 0.3, 1.0], "rotation_deg": [90.0, 0.0, 0.0]}})
    scene = scene_from_dict(d)
    spp = 256
    assert render_mod.camera_ray_share(spp, 2) == 4
    grabbed = []
    uniforms = render_mod._Context.uniforms
    monkeypatch.setattr(render_mod._Context, "uniforms",
                        lambda self, *a: grabbed.append(uniforms(self, *a)) or grabbed[-1])
    out = {}
    for mode in ("1", "0"):
        monkeypatch.setenv("TOFHIL_RENDER_WAVEFRONT", mode)
        out[mode] = render(scene, samples_per_pixel=spp, bounces=2, transient_bins=16, separate_direct=True,
                           seed=7, sampler=sampler)
    U = grabbed[-1].reshape(-1, 4, 8)
    assert np.all(U[:, 1:, :4] == U[:, :1, :4])                  # one camera ray per group
    assert np.all(U[:, 1:, 4:] != U[:, :1, 4:])                  # each sample its own bounces
    a, b = out["1"], out["0"]
    scale = np.abs(a.phasor).max()
    assert scale > 0 and np.abs(a.phasor_indirect).max() > 0.01 * scale
    for x, y in ((a.phasor_direct, b.phasor_direct), (a.phasor_indirect, b.phasor_indirect)):
        np.testing.assert_allclose(x, y, rtol=0, atol=1e-12 * scale)
    np.testing.assert_allclose(a.transient, b.transient, rtol=0, atol=1e-12 * a.transient.max())
    np.testing.assert_allclose(a.ambient_power_per_irradiance, b.ambient_power_per_irradiance, rtol=1e-12)
    np.testing.assert_array_equal(a.radial_m, b.radial_m)
    followers = a.phasor.shape[-1] * a.phasor.shape[-2] * spp * 3 // 4
    assert a.rays_traced - 2 * followers <= b.rays_traced <= a.rays_traced - followers   # b: the compiled loop


def test_camera_ray_share_keeps_64_sub_pixel_positions_and_none_without_bounces() -> None:
    from tofhil.sim.render import camera_ray_share

    assert [camera_ray_share(n, 2) for n in (1, 16, 64, 128, 192, 256, 384, 1024)] == [1, 1, 1, 2, 2, 4, 4, 4]
    assert camera_ray_share(1024, 0) == 1


def test_rotation_of_ray_rows_is_the_numpy_expression() -> None:
    """The compiled row rotation (every subpixel ray of a posed camera) is bit-identical to
    ``v @ R.T`` written as the numpy expression it replaced, and it is a rotation."""
    from tofhil.sim.render import _rotate

    c, s = math.cos(0.3), math.sin(0.3)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
    v = np.random.default_rng(0).normal(size=(500, 3))
    out = _rotate(v, R)
    np.testing.assert_array_equal(out, v[:, 0:1] * R[:, 0] + v[:, 1:2] * R[:, 1] + v[:, 2:3] * R[:, 2])
    np.testing.assert_allclose(np.linalg.norm(out, axis=1), np.linalg.norm(v, axis=1), rtol=1e-14)
    np.testing.assert_allclose(out, v @ R.T, rtol=0, atol=1e-14)


def test_packet_loop_with_misses_and_a_partial_last_packet(monkeypatch: pytest.MonkeyPatch) -> None:
    """The compiled loop traces Embree packets of 8 samples: a frame whose sample count is not
    a multiple of 8 (13 x 7 pixels, 3 samples) with background pixels in the packets (a small
    plane, so many rays and bounces leave the scene) gives what the bounce-by-bounce
    wavefront loop over embreex gives, ray for ray."""
    cam = {"width": 13, "height": 7, "fx": 12.0, "fy": 12.0, "cx": 6.0, "cy": 3.0, "pixel_pitch_m": 96e-6}
    d = plane_scene(distance=1.2, camera=cam, size=1.0, offset=(0.02, 0.0, 0.0))
    d["objects"].append({"name": "floor", "type": "plane", "size": [1.0, 2.0], "material": "white",
                         "pose": {"position": [0.0, 0.4, 1.0], "rotation_deg": [90.0, 0.0, 0.0]}})
    scene = scene_from_dict(d)
    out = {}
    for mode in ("1", "0"):
        monkeypatch.setenv("TOFHIL_RENDER_WAVEFRONT", mode)
        out[mode] = render(scene, samples_per_pixel=3, bounces=2, separate_direct=True, seed=11)
    a, b = out["1"], out["0"]
    assert np.isinf(a.radial_m).mean() > 0.1 and np.isfinite(a.radial_m).mean() > 0.5
    assert np.abs(a.phasor_indirect).max() > 0
    scale = np.abs(a.phasor).max()
    for x, y in ((a.phasor_direct, b.phasor_direct), (a.phasor_indirect, b.phasor_indirect)):
        np.testing.assert_allclose(x, y, rtol=0, atol=1e-12 * scale)
    np.testing.assert_array_equal(a.radial_m, b.radial_m)
    assert a.rays_traced == b.rays_traced


def test_compiled_subpixel_rays_are_the_camera_models() -> None:
    """Sub-pixel rays made in the compiled pass are the camera model's ``pixel_rays`` (OpenCV
    undistortion) rotated to the world, weighted by the pixel's weight times cos^4, and the
    Sobol' points digitally shifted per pixel are the numpy expression
    ``((sobol ^ shift) + 1/2) / 2^32``."""
    cam = CameraModel(width=9, height=5, fx=7.0, fy=7.5, cx=4.2, cy=1.9, dist=(-0.2, 0.05, 0.001, -0.002, 0.01))
    spp, dims = 4, 6
    rng = np.random.default_rng(2)
    sobol = rng.integers(0, 1 << 32, (spp, dims), dtype=np.uint32)
    shift = rng.integers(0, 1 << 32, (cam.width * cam.height, dims), dtype=np.uint32)
    U = np.empty((cam.width * cam.height * spp, dims))
    kernels.sobol_digital_shift(sobol, shift, U)
    np.testing.assert_array_equal(U, ((sobol[None] ^ shift[:, None]) + 0.5).reshape(-1, dims) / 2.0 ** 32)
    assert U.min() > 0.0 and U.max() < 1.0
    c, s = math.cos(0.4), math.sin(0.4)
    R = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    weight = rng.random(cam.width * cam.height) + 0.5
    p0 = 7                                     # a chunk starting mid-row, every other pixel of it
    pixels = np.arange(p0, cam.width * cam.height, 2)
    Uc = U.reshape(-1, spp, dims)[pixels].reshape(-1, dims)
    dirs, beta = np.empty((len(Uc), 3)), np.empty(len(Uc))
    kernels.subpixel_rays(pixels, spp, cam.width, Uc, cam.fx, cam.fy, cam.cx, cam.cy, np.asarray(cam.dist), 20, R,
                          True, weight, dirs, beta)
    pix = np.repeat(pixels, spp)
    d_cam = cam.pixel_rays(pix % cam.width + Uc[:, 0] - 0.5, pix // cam.width + Uc[:, 1] - 0.5)
    np.testing.assert_allclose(dirs, d_cam @ R.T, rtol=0, atol=1e-15)
    np.testing.assert_allclose(beta, weight[pix] * d_cam[:, 2] ** 4, rtol=1e-15)
    # Samples that share a camera ray (groups of 2 here, U's camera columns alike within a
    # group): the group's first ray copied, bit for bit the ray computed for each.
    Ug = Uc.reshape(-1, 2, dims).copy()
    Ug[:, 1, :4] = Ug[:, 0, :4]
    Ug = Ug.reshape(-1, dims)
    each, shared = (np.empty((len(Ug), 3)), np.empty(len(Ug))), (np.empty((len(Ug), 3)), np.empty(len(Ug)))
    for (d, b), share in ((each, 1), (shared, 2)):
        kernels.subpixel_rays(pixels, spp, cam.width, Ug, cam.fx, cam.fy, cam.cx, cam.cy, np.asarray(cam.dist), 20,
                              R, True, weight, d, b, False, share)
    np.testing.assert_array_equal(shared[0], each[0])
    np.testing.assert_array_equal(shared[1], each[1])
    assert not np.array_equal(each[0][0::2], each[0][2::2])   # (groups differ: a copy across them would show)
