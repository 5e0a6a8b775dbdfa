"""The lens prescription (sim/optics.py) against closed form: lensmaker, paraxial image height,
a distortion-free ideal lens, cos^4, ghost energies (products of R and T), a filter's ghost
(focus shift 2 t / n, extra path 2 n t, magnification 1 + 2 t / (n f)); the general ghosts of
the stray-light operator; a scene with a lens renders through the twin."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tofhil import C_M_PER_S
from tofhil.camera import CameraModel
from tofhil.errors import InputFileError
from tofhil.sim.optics import (LensModel, LensSurface, Prescription, glass_index, lens_camera,
                               prescription_from_dict)
from tofhil.sim.straylight import Ghost, StrayLightOperator, StrayLightPSF


def _singlet(r1: float = 0.020, r2: float = -0.030, t: float = 0.003, n: float = 1.5) -> Prescription:
    return Prescription((LensSurface(radius_m=r1, thickness_m=t, n=n, stop=True),
                         LensSurface(radius_m=r2, thickness_m=0.03, n=1.0)))


def _ideal(f: float = 0.004, a: float = 1e-3, plate: tuple[float, float, float, float] | None = None,
           sensor_r: float = 0.0) -> Prescription:
    """Ideal lens (stop at the lens), optionally a plate (t, n, R1, R2) halfway to the focus."""
    if plate is None:
        return Prescription((LensSurface(focal_length_m=f, thickness_m=f, stop=True, semi_diameter_m=a),),
                            sensor_reflectance=sensor_r, ghost_threshold=0.0)
    t, n, r1, r2 = plate
    gap = f / 2
    rest = f - gap - t / n  # the plate moves the focus back by t (1 - 1/n)
    return Prescription((LensSurface(focal_length_m=f, thickness_m=gap, stop=True, semi_diameter_m=a),
                         LensSurface(thickness_m=t, n=n, reflectance=r1, name="filter1"),
                         LensSurface(thickness_m=rest, reflectance=r2, name="filter2")),
                        sensor_reflectance=sensor_r, ghost_threshold=0.0)


def test_glass_indices_match_the_catalogue_at_the_d_line() -> None:
    assert glass_index("N-BK7", 587.56e-9) == pytest.approx(1.5168, abs=2e-4)
    assert glass_index("fused_silica", 587.56e-9) == pytest.approx(1.4585, abs=2e-4)
    assert glass_index("N-BK7", 850e-9) < glass_index("N-BK7", 587.56e-9)  # normal dispersion


def test_singlet_focal_length_is_the_lensmakers() -> None:
    r1, r2, t, n = 0.020, -0.030, 0.003, 1.5
    f = 1.0 / ((n - 1) * (1 / r1 - 1 / r2 + (n - 1) * t / (n * r1 * r2)))
    m = LensModel(_singlet(r1, r2, t, n))
    assert m.efl_m == pytest.approx(f, rel=1e-6)
    # Back focal length: f (1 - (n - 1) t / (n r1)).
    assert m.bfl_m == pytest.approx(f * (1 - (n - 1) * t / (n * r1)), rel=1e-6)


def test_paraxial_image_height_is_f_theta() -> None:
    m = LensModel(_singlet())
    theta = np.array([1e-4, 5e-4])
    # The sensor is not at focus, but the chief ray's height is f theta to first order anyway
    # when the sensor is at the back focal plane: put it there.
    pres = _singlet()
    pres = Prescription((pres.surfaces[0], LensSurface(radius_m=-0.030, thickness_m=m.bfl_m, n=1.0)))
    m2 = LensModel(pres)
    assert m2.image_height(theta) == pytest.approx(m2.efl_m * theta, rel=1e-5)


def test_ideal_lens_has_no_distortion_cos4_falloff_and_path_f_over_cos() -> None:
    f, pitch = 0.004, 20e-6
    base = CameraModel(width=40, height=30, fx=1.0, fy=1.0, cx=19.5, cy=14.5, pixel_pitch_m=pitch)
    cam = lens_camera(base, _ideal(f))
    pin = CameraModel(width=40, height=30, fx=f / pitch, fy=f / pitch, cx=19.5, cy=14.5, pixel_pitch_m=pitch)
    assert cam.fx == pytest.approx(f / pitch, rel=1e-9)
    assert np.max(np.abs(cam.rays - pin.rays)) < 1e-7
    # The OpenCV model fitted for session files is the pinhole too (to float round-off on the sensor).
    fitted = CameraModel(width=40, height=30, fx=cam.fx, fy=cam.fy, cx=19.5, cy=14.5, dist=cam.dist)
    assert np.max(np.abs(fitted.rays - pin.rays)) < 1e-8
    m = LensModel(_ideal(f), pupil_samples=128)
    th = np.radians([0.0, 10.0, 20.0, 30.0])
    np.testing.assert_allclose(m.relative_illumination(th), np.cos(th) ** 4, rtol=1e-2)
    np.testing.assert_allclose(m.transmission(th), 1.0, rtol=1e-2)
    np.testing.assert_allclose(m.extra_path(th), f / np.cos(th), rtol=1e-6)


def test_ghost_energy_is_the_product_of_reflectances_and_transmissions() -> None:
    r1, r2, rs = 0.05, 0.07, 0.2
    m = LensModel(_ideal(plate=(0.5e-3, 1.5, r1, r2), sensor_r=rs, a=1e-4))
    by = {(g.i, g.j): g for g in m.ghosts}
    assert set(by) == {(1, 2), (1, 3), (2, 3)}  # the ideal lens reflects nothing
    assert by[1, 2].weight == pytest.approx(r1 * r2, rel=1e-9)
    assert by[1, 3].weight == pytest.approx(r1 * rs * (1 - r2) ** 2, rel=1e-9)
    assert by[2, 3].weight == pytest.approx(r2 * rs, rel=1e-9)
    # The direct light loses the coatings' reflections (and nothing else here).
    assert m.transmission(np.array([0.0]))[0] == pytest.approx((1 - r1) * (1 - r2) * (1 - rs), rel=2e-2)


def test_filter_ghost_focus_shift_path_and_magnification() -> None:
    f, t, n = 0.004, 0.5e-3, 1.5
    m = LensModel(_ideal(f, a=2e-5, plate=(t, n, 0.05, 0.05)))
    g = m.ghost(1, 2, field_theta=1e-3)
    assert g.focus_shift_m == pytest.approx(-2 * t / n, rel=1e-3)  # converges in front of the sensor
    assert g.extra_path_m == pytest.approx(2 * n * t, rel=1e-3)
    assert g.magnification == pytest.approx(1 + 2 * t / (n * f), rel=1e-3)
    # Its blur on the sensor: the marginal ray's slope (a / f) times the focus shift (RMS of a disk: r/2).
    assert g.sigma_m == pytest.approx(0.5 * (2e-5 / f) * 2 * t / n, rel=2e-2)


def test_general_ghost_operator_conserves_energy_and_delays_the_phasor() -> None:
    shape = (30, 40)
    s = np.zeros(shape)
    s[15, 20] = 1.0
    for m in (0.5, 1.2, -0.8):
        op = StrayLightOperator(StrayLightPSF(ghosts=(Ghost(0.1, 1.0, None, m),), conserve=False), shape)
        assert op.scatter(s).sum() == pytest.approx(0.1, rel=1e-6)
    # A mirror ghost with an extra path is the plain mirror ghost times exp(i 2 pi f L / c).
    rng = np.random.default_rng(0)
    img = rng.random(shape) + 1j * rng.random(shape)
    plain = StrayLightOperator(StrayLightPSF(ghosts=(Ghost(0.1, 2.0),), conserve=False), shape)
    delayed = StrayLightOperator(StrayLightPSF(ghosts=(Ghost(0.1, 2.0, None, -1.0, 0.3),), conserve=False), shape)
    fr = 20e6
    np.testing.assert_allclose(delayed.scatter(img, fr), plain.scatter(img) * np.exp(2j * np.pi * fr * 0.3 / C_M_PER_S),
                               atol=1e-12)
    np.testing.assert_allclose(delayed.scatter(img), plain.scatter(img), atol=1e-12)
    # Adjoint: <A x, y> = <x, A^H y>.
    y = rng.random(shape) + 1j * rng.random(shape)
    lhs = np.vdot(y, delayed.apply(img, fr))
    rhs = np.vdot(delayed.adjoint(y, fr), img)
    assert lhs == pytest.approx(rhs, rel=1e-10)


def test_general_ghost_round_trips_through_the_psf_file(tmp_path) -> None:
    psf = StrayLightPSF(ghosts=(Ghost(0.01, 3.0, None, 1.02, 0.0015), Ghost(0.002, 1.0)), veil=0.001, conserve=False)
    back = StrayLightPSF.load(psf.save(tmp_path / "p.json"))
    assert back.ghosts == psf.ghosts and back.veil == psf.veil and back.conserve is False


LENS_BLOCK = {
    "surfaces": [
        {"name": "L1", "radius_m": 0.0035, "thickness_m": 0.0016, "glass": "N-SF11", "semi_diameter_m": 0.0022,
         "reflectance": 0.005},
        {"name": "L1b", "radius_m": 0.012, "thickness_m": 0.0004, "reflectance": 0.005, "semi_diameter_m": 0.0018},
        {"name": "stop", "thickness_m": 0.0004, "stop": True, "semi_diameter_m": 0.0009},
        {"name": "filter", "thickness_m": 0.0005, "n": 1.5, "reflectance": 0.02},
        {"name": "filter_b", "thickness_m": "auto", "reflectance": 0.02},
    ],
    "sensor_reflectance": 0.2,
    "housing_veil": 0.002,
}


def _scene(lens: dict | None, **cam: object) -> dict:
    c = {"width": 40, "height": 30, "fx": 30.0, "fy": 30.0, "cx": 19.5, "cy": 14.5, "pixel_pitch_m": 60e-6,
         "wavelength_m": 850e-9, "pose": {"position": [0, 0, 0]}} | dict(cam)
    if lens is not None:
        c["lens"] = lens
    return {"camera": c, "emitter": {"power_w": 0.3},
            "materials": {"wall": {"reflectance": 0.8}},
            "objects": [{"name": "wall", "type": "plane", "size": [4, 4], "material": "wall",
                         "pose": {"position": [0, 0, 1.0]}}],
            "sensor": {"freq_hz": [20e6]}, "render": {"samples_per_pixel": 1, "bounces": 0}}


def test_a_scene_with_a_lens_renders_and_the_ghosts_add_delayed_light() -> None:
    from tofhil.sim.optics import LensCamera
    from tofhil.sim.scene import scene_from_dict
    from tofhil.sim.twin import Twin

    scene = scene_from_dict(_scene(LENS_BLOCK), source="lens.yaml")
    assert isinstance(scene.camera, LensCamera)
    assert scene.f_number == pytest.approx(scene.camera.model.f_number)
    dark = dict(LENS_BLOCK, sensor_reflectance=0.0, housing_veil=0.0,
                surfaces=[dict(s, reflectance=0.0) for s in LENS_BLOCK["surfaces"]])
    s_ghost = Twin(scene).signal()
    s_clean = Twin(scene_from_dict(_scene(dark), source="lens.yaml")).signal()
    p_ghost, p_clean = s_ghost.phasor_w[0, 0], s_clean.phasor_w[0, 0]
    assert np.all(np.isfinite(p_ghost))
    # Coatings take light off the direct path; the ghosts and the veil put some back elsewhere.
    coat = (1 - 0.005) ** 2 * (1 - 0.02) ** 2 * (1 - 0.2)
    assert np.abs(p_ghost).sum() > coat * np.abs(p_clean).sum()
    psf = scene.camera.model.stray_light(60e-6)
    assert len(psf.ghosts) >= 6 and all(g.extra_path_m > 0 for g in psf.ghosts)
    # Vignetting and the pixel's solid angle make the corners darker than the centre.
    assert np.abs(p_clean[0, 0]) < np.abs(p_clean[15, 20])


def test_bad_lens_blocks_name_the_field() -> None:
    from tofhil.sim.scene import scene_from_dict

    with pytest.raises(InputFileError, match=r"camera\.lens\.surfaces\[0\]\.glass"):
        prescription_from_dict({"surfaces": [{"glass": "unobtainium"}]}, source="x.yaml")
    with pytest.raises(InputFileError, match=r"camera\.lens\.surfaces\[1\]\.colour"):
        prescription_from_dict({"surfaces": [{}, {"colour": 1}]}, source="x.yaml")
    with pytest.raises(InputFileError, match=r"camera\.lens\.surfaces\[1\]\.semi_diameter_m"):
        prescription_from_dict({"surfaces": [{"radius_m": 0.01, "n": 1.5}, {"stop": True}]}, source="x.yaml")
    with pytest.raises(InputFileError, match=r"camera\.f_number"):
        scene_from_dict(_scene(LENS_BLOCK, f_number=2.0), source="x.yaml")
    with pytest.raises(InputFileError, match="covers the sensor"):
        scene_from_dict(_scene(LENS_BLOCK, width=1000, height=800, cx=499.5, cy=399.5), source="x.yaml")


def test_plain_cameras_are_untouched() -> None:
    from tofhil.sim.optics import apply_lens

    sentinel = object()
    assert apply_lens(sentinel, CameraModel(width=4, height=3, fx=1, fy=1, cx=1.5, cy=1)) is sentinel
    assert math.isfinite(LensModel(_singlet()).f_number)


def test_the_bundled_lens_scene_round_trips_and_renders(tmp_path) -> None:
    from tofhil.sim.render import render
    from tofhil.sim.scene import load_scene, scene_to_yaml

    scene = load_scene("dark_square_card_lens")
    m = scene.camera.model
    assert m.efl_m == pytest.approx(2.8e-3, rel=0.01) and m.f_number == pytest.approx(1.2, rel=0.01)
    path = tmp_path / "lens.yaml"
    path.write_text(scene_to_yaml(scene))
    again = load_scene(path)
    assert again.camera == scene.camera and again.f_number == scene.f_number
    res = render(scene, camera=scene.camera.scaled(0.25), samples_per_pixel=1, bounces=0)
    assert np.all(np.isfinite(res.radial_m)) and np.all(res.object_id >= 0)


def test_the_stray_light_effect_delays_each_channel_by_its_own_frequency() -> None:
    from tofhil.sim.effects import EFFECTS, EffectContext
    from tofhil.sim.sensor import OpticalSignal

    shape = (6, 8)
    cam = CameraModel(width=8, height=6, fx=10, fy=10, cx=3.5, cy=2.5)
    freq = np.array([20e6, 80e6])
    sig = OpticalSignal(freq, (1, 3), np.ones((2, 2) + shape, dtype=complex), np.ones(shape), np.zeros(shape))
    path = 0.5
    values = EFFECTS["stray_light"].validate(
        {"ghosts": [{"weight": 0.01, "sigma_px": 1.0, "magnification": 1.0, "extra_path_m": path}],
         "conserve": False})
    out = EFFECTS["stray_light"].apply_signal(sig, values, EffectContext(camera=cam))
    ghost = out.phasor_w - sig.phasor_w
    for fi, f in enumerate(freq):
        for hi, h in enumerate((1, 3)):
            ph = np.angle(ghost[fi, hi, 2, 3] * np.exp(-2j * np.pi * h * f * path / C_M_PER_S))
            assert abs(ph) < 1e-9
    # The unmodulated light gets the ghost undelayed (and no more than its weight).
    assert 0 < (out.dc_w - sig.dc_w).max() <= 0.01


def test_a_stop_in_front_of_an_ideal_lens_keeps_cos4_and_no_distortion() -> None:
    # The stop a distance d ahead of the lens is its own entrance pupil (seen as cos(theta)),
    # and a parallel bundle still meets at f tan(theta): cos^4, no distortion, for any d.
    f, d = 0.004, 0.002
    pres = Prescription((LensSurface(thickness_m=d, stop=True, semi_diameter_m=0.5e-3),
                         LensSurface(focal_length_m=f, thickness_m=f)))
    m = LensModel(pres, pupil_samples=128)
    assert m.entrance_pupil == pytest.approx((0.0, 0.5e-3))
    th = np.radians([0.0, 15.0, 30.0])
    np.testing.assert_allclose(m.image_height(th), f * np.tan(th), rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(m.relative_illumination(th), np.cos(th) ** 4, rtol=1e-2)
