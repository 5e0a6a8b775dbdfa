"""The closed-form radiometry of a plane against the twin's renderer and against hand-written physics."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tofhil.camera import CameraModel
from tofhil.sim.radiometry import Plane, aperture_area_m2, plane_relative_amplitude, plane_view
from tofhil.sim.render import render
from tofhil.sim.scene import BeamProfile, load_scene


def _closed_form_of(scene, camera, plane):
    e = scene.emitter
    return plane_view(camera, plane, power_w=e.power_w, profile=e.profile, emitter_offset_m=e.offset_m,
                      emitter_axis=e.axis, aperture_m2=aperture_area_m2(camera, scene.radiometric_f_number))


def test_bundled_wall_render_equals_the_closed_form():
    """The bundled `wall` scene (white wall at 1 m, cos^2 beam, emitter 15 mm beside the lens):
    pixel-centre rays give the closed form to float32 precision, the path lengths too."""
    scene = load_scene("wall")
    cam = scene.camera.scaled(0.25)  # 40 x 30: seconds, same lens
    res = render(scene, camera=cam, samples_per_pixel=1, bounces=0, subpixel=False)
    view = _closed_form_of(scene, cam, Plane(1.0, albedo=0.8))
    np.testing.assert_allclose(res.power_w, view.power_w, rtol=1e-4)
    # Phase of the first harmonic = 2 pi f L / c with L the emitter -> wall -> pixel path.
    f = float(res.freq_hz[0])
    phase = np.angle(res.phasor[0, 0])
    expect = np.angle(np.exp(1j * 2 * np.pi * f * view.path_m / 299_792_458.0))
    assert np.max(np.abs(np.angle(np.exp(1j * (phase - expect))))) < 1e-4


def test_pixel_integrated_render_agrees_within_its_noise():
    """With 16 sub-pixel samples the render integrates over each pixel; the closed form (pixel
    centre) is within the sampling spread of a smooth field (well under 1 %)."""
    scene = load_scene("wall")
    cam = scene.camera.scaled(0.25)  # 40 x 30: seconds, same lens
    res = render(scene, camera=cam, samples_per_pixel=16, bounces=0, subpixel=True, seed=3)
    view = _closed_form_of(scene, cam, Plane(1.0, albedo=0.8))
    ratio = res.power_w / view.power_w
    assert abs(np.median(ratio) - 1) < 2e-3 and np.max(np.abs(ratio - 1)) < 0.01


def test_on_axis_value_and_falloff_are_the_textbook_laws():
    cam = CameraModel(width=41, height=31, fx=40.0, fy=40.0, cx=20.0, cy=15.0, pixel_pitch_m=10e-6)
    n, power, rho, a_ap = 3.0, 0.5, 0.6, 2e-6
    prof = BeamProfile("cos_n", n=n)
    for dist in (0.5, 1.0, 2.0):
        v = plane_view(cam, Plane(dist, albedo=rho), power_w=power, profile=prof, aperture_m2=a_ap)
        # Axis: I0 = P (n+1) / (2 pi); E = I0 / D^2; L = rho E / pi; P_pix = L A_ap / (fx fy).
        i0 = power * (n + 1) / (2 * math.pi)
        assert v.power_w[15, 20] == pytest.approx(rho / math.pi * i0 / dist ** 2 * a_ap / (40.0 * 40.0), rel=1e-12)
        # Off axis, fronto-parallel, co-located: cos^n (beam) * cos (incidence) * cos^2 (r = D/cos)
        # * cos^4 (lens) = cos^(n+7) relative to the axis.
        c = cam.ray_z
        np.testing.assert_allclose(v.power_w / v.power_w[15, 20], c ** (n + 7), rtol=1e-12)
        np.testing.assert_allclose(v.path_m, 2 * dist / c, rtol=1e-12)
    # Tilted plane, relative amplitude: the axis pixel sees cos(tilt) less light at the
    # distance D / cos(tilt) along the ray.
    t = math.radians(25)
    rel = plane_relative_amplitude(cam, Plane.tilted(1.0, 25.0, albedo=1.0), prof)
    assert rel[15, 20] == pytest.approx(math.cos(t) * math.cos(t) ** 2, rel=1e-12)


def test_a_plane_that_misses_the_view_is_refused():
    cam = CameraModel(width=41, height=31, fx=20.0, fy=20.0, cx=20.0, cy=15.0)
    from tofhil.errors import TofhilError

    with pytest.raises(TofhilError, match="field of view"):
        plane_view(cam, Plane.tilted(1.0, 80.0), power_w=1.0)
