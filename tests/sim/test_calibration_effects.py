"""The generic calibration forms, against closed forms: a phase and a gain on one modulation
frequency alone, and a gain and an offset per tap of the readout."""

from __future__ import annotations

import dataclasses

import numpy as np

from tofhil.camera import CameraModel
from tofhil.demod import phasor
from tofhil.sim.effects import EFFECTS, EffectContext
from tofhil.sim.sensor import OpticalSignal, SensorConfig, SensorModel

C = 299_792_458.0


def _signal(freqs: tuple[float, ...], d_m: float = 1.3, harmonics: tuple[int, ...] = (1, 3)) -> OpticalSignal:
    h, w = 6, 8
    f = np.asarray(freqs)[:, None, None, None]
    hh = np.asarray(harmonics, dtype=float)[None, :, None, None]
    ph = np.exp(1j * 2 * np.pi * hh * f * 2 * d_m / C) * np.ones((1, 1, h, w))
    return OpticalSignal(freq_hz=np.asarray(freqs), harmonics=harmonics, phasor_w=1e-9 * ph * np.where(hh == 1, 1.0, 0.1),
                         dc_w=np.full((h, w), 1.2e-9), ambient_w=np.zeros((h, w)))


def test_a_phase_on_one_frequency_turns_that_frequency_alone_harmonic_by_harmonic():
    sig = _signal((44e6, 60e6, 80e6))
    eff = EFFECTS["frequency_calibration"]
    vals = eff.validate({"phase_1_rad": 0.12, "gain_2": 0.9})
    out = eff.apply_signal(sig, vals, EffectContext(camera=None, sensor=None))
    np.testing.assert_array_equal(out.phasor_w[0], sig.phasor_w[0])
    # a delay of the reference turns harmonic h by h * phase (a time shift), and nothing else
    np.testing.assert_allclose(out.phasor_w[1, 0] / sig.phasor_w[1, 0], np.exp(0.12j), rtol=1e-12)
    np.testing.assert_allclose(out.phasor_w[1, 1] / sig.phasor_w[1, 1], np.exp(0.36j), rtol=1e-12)
    np.testing.assert_allclose(out.phasor_w[2] / sig.phasor_w[2], 0.9, rtol=1e-12)
    np.testing.assert_array_equal(out.dc_w, sig.dc_w)


def test_frequency_calibration_needs_the_frequency_it_acts_on():
    eff = EFFECTS["frequency_calibration"]
    assert eff.form_params("", 4, n_freq=1) == {}
    assert set(eff.form_params("", 4, n_freq=2)) == {"phase_1_rad", "gain_1"}
    assert set(eff.form_params("", 4, n_freq=3)) == set(eff.params)
    one = _signal((44e6,))
    out = eff.apply_signal(one, eff.validate({"phase_1_rad": 0.3}), EffectContext(camera=None, sensor=None))
    np.testing.assert_array_equal(out.phasor_w, one.phasor_w)


def test_tap_gains_make_the_alternating_part_no_light_can_make():
    """Taps 1 and 3 with gain 1 + e: the demodulated S gains (e/2) and a term i e A sin(phi)
    (closed form for 4 taps at 0, 90, 180, 270 deg), and the alternating part (1/4) sum (-1)^k
    c_k moves by -e B / 2."""
    cam = CameraModel.from_fov(8, 6, 60.0)
    cfg = SensorConfig.from_dict({"freq_hz": [44e6], "read_noise_e": 0, "dark_current_e_per_s": 0,
                                  "adc_bits": 24, "full_well_e": 1e9}, camera=cam)
    sensor = SensorModel(cfg, cam)
    taps = sensor.taps_dn(_signal((44e6,)), noise=False).astype(np.float64)
    eff = EFFECTS["tap_calibration"]
    e = 0.04
    out = eff.apply_taps(taps, eff.validate({"gain_1": 1 + e, "gain_3": 1 + e}), EffectContext(camera=cam, sensor=cfg))
    theta = sensor.theta_rad
    s0, s1 = phasor(taps, theta)[0], phasor(out, theta)[0]
    b = taps.mean(axis=1)[0]
    a, phi = np.abs(s0), np.angle(s0)
    np.testing.assert_allclose(s1 - s0, 1j * e * a * np.sin(phi), rtol=1e-9, atol=1e-9 * np.abs(s0).max())
    def alternating(c):
        return np.tensordot((-1.0) ** np.arange(4), c, axes=([0], [1]))[0] / 4
    np.testing.assert_allclose(alternating(out) - alternating(taps), -e * b / 2, rtol=1e-6)  # float32 taps


def test_tap_offsets_add_per_tap_and_tap_gains_scale_the_noise_too():
    eff = EFFECTS["tap_calibration"]
    taps = np.random.default_rng(0).normal(100.0, 3.0, (1, 4, 50, 60)).astype(np.float32)
    out = eff.apply_taps(taps, eff.validate({"gain_1": 1.0, "gain_2": 1.5, "gain_3": 1.0, "offset_3_dn": 7.0}), EffectContext(camera=None, sensor=None))
    assert out.dtype == np.float32
    np.testing.assert_array_equal(out[:, [0, 1]], taps[:, [0, 1]])
    np.testing.assert_allclose(out[:, 2].std() / taps[:, 2].std(), 1.5, rtol=1e-5)
    np.testing.assert_allclose(out[:, 3] - taps[:, 3], 7.0, rtol=1e-5)
    assert not eff.observable("gain_3", 3) and eff.observable("gain_2", 3)


def test_the_twin_applies_the_readout_to_frames_and_to_its_predictions():
    """The taps stage acts in simulation (noisy frames) and in the noise-free prediction alike."""
    from tests.eval import hidden_forms as hf
    from tofhil.sim.twin import Twin

    scene = hf.small_dark_square(40)
    twin = Twin(scene)
    eff = twin.effects({"tap_calibration": {"gain_1": 1.05, "gain_3": 1.0, "offset_2_dn": 3.0}})
    base = twin.expected_taps(twin.effects({})).astype(np.float64)
    with_gain = twin.expected_taps(eff).astype(np.float64)
    np.testing.assert_allclose(with_gain[:, 1], np.float32(base[:, 1] * 1.05), rtol=2e-6)
    np.testing.assert_allclose(with_gain[:, 2] - base[:, 2], 3.0, atol=1e-3)
    frame = next(iter(twin.frames(eff, noise=False)))
    np.testing.assert_allclose(frame.taps, with_gain, rtol=1e-6)
    pixels = np.zeros(scene.camera.shape, bool)
    pixels[3:5, 4:9] = True
    at = twin.expected_taps_at(eff, pixels)
    np.testing.assert_allclose(at[..., 0, :], with_gain[..., pixels], rtol=1e-6)
    assert dataclasses.is_dataclass(frame)
