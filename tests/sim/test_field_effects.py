"""The smooth fields over the sensor (``gain_field``, ``offset_field``) against their definition,
computed here from the pixel coordinates alone: the amplitude ratio is the polynomial, the tap
offset rises by the field in electrons, the phase does not move, and a prediction on some pixels
is the whole frame's at those pixels."""

from __future__ import annotations

import dataclasses

import numpy as np

from tofhil.camera import CameraModel
from tofhil.depth import depth_from_raw
from tofhil.sim.effects import EffectContext, apply_signal_effects, parse_effects
from tofhil.sim.sensor import OpticalSignal, SensorConfig, SensorModel

C = 299_792_458.0
F = 44.0e6


def _cam(w: int = 32, h: int = 24) -> CameraModel:
    return CameraModel.from_fov(w, h, 60.0)


def _signal(cam: CameraModel, d: float = 1.3, p: float = 1e-11, ambient: float = 0.0) -> OpticalSignal:
    s = np.full(cam.shape, p * np.exp(1j * 4 * np.pi * F * d / C))[None, None]
    return OpticalSignal(freq_hz=[F], harmonics=(1,), phasor_w=s, dc_w=np.full(cam.shape, p),
                         ambient_w=np.full(cam.shape, ambient))


def _sensor(cam: CameraModel) -> SensorModel:
    cfg = SensorConfig.from_dict({"freq_hz": [F], "read_noise_e": 0, "dark_current_e_per_s": 0,
                                  "adc_bits": 20, "full_well_e": 1e7}, camera=cam)
    return SensorModel(cfg, cam)


def _poly(c: dict[str, float], x: np.ndarray, y: np.ndarray, suffix: str = "") -> np.ndarray:
    # the documented basis written out: Legendre P0 = 1, P1 = t, P2 = (3 t^2 - 1) / 2 in x and y
    p2x, p2y = 1.5 * x * x - 0.5, 1.5 * y * y - 0.5
    terms = {"mean": 1.0, "linear_x": x, "linear_y": y, "quad_xx": p2x, "quad_xy": x * y, "quad_yy": p2y,
             "cubic_xxy": p2x * y, "cubic_xyy": x * p2y, "quartic_xxyy": p2x * p2y}
    return sum(c.get(k + suffix, 0.0) * t for k, t in terms.items())


def _xy(cam: CameraModel) -> tuple[np.ndarray, np.ndarray]:
    # the documented coordinates: -1 at the first column (row), +1 at the last
    x = np.linspace(-1.0, 1.0, cam.width)[None, :].repeat(cam.height, 0)
    y = np.linspace(-1.0, 1.0, cam.height)[:, None].repeat(cam.width, 1)
    return x, y


def test_gain_field_scales_the_emitter_light_by_the_polynomial_and_keeps_the_phase() -> None:
    cam = _cam()
    x, y = _xy(cam)
    c = {"mean": 0.05, "linear_x": 0.2, "linear_y": -0.1, "quad_xx": 0.08, "quad_xy": -0.05, "quad_yy": 0.03,
         "cubic_xxy": 0.04, "cubic_xyy": -0.02, "quartic_xxyy": 0.03}
    expected = 1 + _poly(c, x, y)
    sig = _signal(cam, ambient=3e-12)
    ctx = EffectContext(camera=cam, sensor=_sensor(cam).config)
    out = apply_signal_effects(sig, parse_effects({"gain_field": c}), ctx)
    np.testing.assert_allclose(np.abs(out.phasor_w[0, 0]) / np.abs(sig.phasor_w[0, 0]), expected, rtol=1e-12)
    np.testing.assert_allclose(out.dc_w / sig.dc_w, expected, rtol=1e-12)
    np.testing.assert_array_equal(out.ambient_w, sig.ambient_w)  # ambient light is not the emitter's
    sensor = _sensor(cam)
    d0 = depth_from_raw(sensor.expose(sig, noise=False)).distance_m
    d1 = depth_from_raw(sensor.expose(out, noise=False)).distance_m
    np.testing.assert_allclose(d1, d0, atol=1e-5)


def test_gain_field_clips_at_zero_light() -> None:
    cam = _cam()
    out = apply_signal_effects(_signal(cam), parse_effects({"gain_field": {"linear_x": 2.0}}),
                               EffectContext(camera=cam))
    x, _ = _xy(cam)
    assert np.all(out.dc_w >= 0) and np.all(out.dc_w[x < -0.5] == 0) and np.all(out.dc_w[x > 0] > 0)


def test_offset_field_adds_its_electrons_to_every_tap_and_keeps_the_phase() -> None:
    cam = _cam()
    x, y = _xy(cam)
    c = {"mean_e": 4000.0, "linear_x_e": 1500.0, "linear_y_e": -800.0, "quad_xx_e": 300.0, "quad_xy_e": 200.0,
         "quad_yy_e": -250.0, "cubic_xxy_e": 150.0, "cubic_xyy_e": 100.0, "quartic_xxyy_e": -120.0}
    field_e = _poly(c, x, y, "_e")
    assert field_e.min() > 0
    sensor = _sensor(cam)
    sig = _signal(cam)
    out = apply_signal_effects(sig, parse_effects({"offset_field": c}), EffectContext(camera=cam, sensor=sensor.config))
    base, on = sensor.expose(sig, noise=False), sensor.expose(out, noise=False)
    rise_dn = (np.asarray(on.taps, float) - np.asarray(base.taps, float))[0]  # [K, H, W]
    np.testing.assert_allclose(rise_dn, np.broadcast_to(field_e * sensor.config.conversion_gain_dn_per_e, rise_dn.shape),
                               rtol=1e-3, atol=1.0)
    np.testing.assert_allclose(depth_from_raw(on).distance_m, depth_from_raw(base).distance_m, atol=1e-4)


def test_offset_field_never_makes_unmodulated_light_negative() -> None:
    cam = _cam()
    sensor = _sensor(cam)
    sig = _signal(cam, ambient=1e-13)
    out = apply_signal_effects(sig, parse_effects({"offset_field": {"mean_e": -1e5}}),
                               EffectContext(camera=cam, sensor=sensor.config))
    np.testing.assert_array_equal(out.ambient_w, 0.0)


def test_a_prediction_on_some_pixels_is_the_whole_frame_at_those_pixels() -> None:
    cam = _cam()
    sensor = _sensor(cam)
    rng = np.random.default_rng(3)
    pixels = np.sort(rng.choice(cam.width * cam.height, 40, replace=False))
    eff = parse_effects({"gain_field": {"linear_y": 0.3, "quad_xy": 0.2}, "offset_field": {"mean_e": 500.0, "quad_xx_e": 90.0}})
    ctx = EffectContext(camera=cam, sensor=sensor.config)
    whole = apply_signal_effects(_signal(cam), eff, ctx)
    some = apply_signal_effects(_signal(cam).at(pixels), eff, dataclasses.replace(ctx, pixels=pixels.reshape(1, -1)))
    np.testing.assert_allclose(some.phasor_w.reshape(-1), whole.phasor_w.reshape(-1)[pixels], rtol=1e-12)
    np.testing.assert_allclose(some.ambient_w.reshape(-1), whole.ambient_w.reshape(-1)[pixels], rtol=1e-12)


def test_the_basis_is_nearly_orthogonal_on_a_full_frame() -> None:
    from tofhil.sim.effects.fields import basis

    cam = _cam(64, 48)
    b = basis(EffectContext(camera=cam), cam.shape).reshape(9, -1)
    gram = b @ b.T / b.shape[1]
    corr = gram / np.sqrt(np.outer(np.diag(gram), np.diag(gram)))
    assert np.max(np.abs(corr - np.eye(9))) < 0.05
