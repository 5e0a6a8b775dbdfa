"""Sensor model against closed forms: radiometric conversion, phase wrap, noise statistics,
saturation, quantisation, determinism. Inputs are analytic phasors of a plane (no renderer)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tofhil.camera import CameraModel, load_camera_preset
from tofhil.depth import depth_from_raw
from tofhil.errors import InputFileError
from tofhil.sim.sensor import OpticalSignal, SensorConfig, SensorModel

C = 299_792_458.0
H_PLANCK = 6.62607015e-34
F44 = 44.0e6


def _camera(w: int = 32, h: int = 24) -> CameraModel:
    return CameraModel.from_fov(w, h, 60.0)


def _plane_signal(cam: CameraModel, radial_m: np.ndarray | float, power_w: float | np.ndarray,
                  freqs=(F44,), ambient_w: float = 0.0, harmonics=(1,)) -> OpticalSignal:
    """A single return per pixel at radial distance d: S_h = P exp(i 2 pi h f 2d / c)."""
    d = np.broadcast_to(np.asarray(radial_m, dtype=float), cam.shape)
    p = np.broadcast_to(np.asarray(power_w, dtype=float), cam.shape)
    ph = np.stack([np.stack([p * np.exp(1j * 2 * np.pi * h * f * 2 * d / C) for h in harmonics])
                   for f in freqs])
    return OpticalSignal(freq_hz=np.array(freqs), harmonics=harmonics, phasor_w=ph, dc_w=p,
                         ambient_w=np.full(cam.shape, ambient_w))


def _sensor(cam: CameraModel, **kw) -> SensorModel:
    d = {"freq_hz": [F44], "read_noise_e": 0.0, "dark_current_e_per_s": 0.0} | kw
    return SensorModel(SensorConfig.from_dict(d, camera=cam), cam)


def test_noise_free_taps_follow_the_radiometric_closed_form() -> None:
    cam = _camera()
    d = np.linspace(0.3, 3.0, cam.width)[None, :].repeat(cam.height, 0)
    p = 2.0e-12  # 2 pW on the pixel
    t_int, qe, lam, gain, contrast, frac, dark, amb = 5e-4, 0.4, 940e-9, 0.25, 0.7, 0.5, 3000.0, 0.5e-12
    sens = _sensor(cam, integration_time_s=t_int, quantum_efficiency=qe, wavelength_m=lam,
                   conversion_gain_dn_per_e=gain, modulation_contrast=contrast, tap_fraction=frac,
                   dark_current_e_per_s=dark, adc_bits=16, full_well_e=1e6)
    frame = sens.expose(_plane_signal(cam, d, p, ambient_w=amb), noise=False)
    # Independent computation: photons/s = P lambda / (h c), electrons = QE * T.
    e_per_w = qe * t_int * lam / (H_PLANCK * C)
    b = frac * e_per_w * (p + amb) + dark * t_int
    a = frac * contrast * e_per_w * p
    phi = 4 * np.pi * F44 * d / C
    for k, th in enumerate(np.radians([0, 90, 180, 270])):
        np.testing.assert_allclose(frame.taps[0, k], gain * (b + a * np.cos(phi - th)), rtol=2e-6)
    # The noise-free mode is exact: demodulation returns the true distance.
    depth = depth_from_raw(frame)
    np.testing.assert_allclose(depth.distance_m, d, atol=2e-5)
    assert frame.taps.dtype == np.float32 and frame.meta["units"] == "DN"


def test_phase_wraps_at_the_ambiguity_range() -> None:
    cam = _camera(8, 6)
    sens = _sensor(cam, adc_bits=16)
    r_amb = C / (2 * F44)  # 3.4067 m
    near = sens.expose(_plane_signal(cam, 0.8, 1e-11), noise=False)
    far = sens.expose(_plane_signal(cam, 0.8 + r_amb, 1e-11), noise=False)
    np.testing.assert_allclose(far.taps, near.taps, rtol=1e-6)
    np.testing.assert_allclose(depth_from_raw(far).distance_m, 0.8, atol=1e-5)
    # Just short of the ambiguity range reads just short of it, not zero.
    edge = sens.expose(_plane_signal(cam, r_amb - 0.01, 1e-11), noise=False)
    np.testing.assert_allclose(depth_from_raw(edge).distance_m, r_amb - 0.01, atol=1e-4)


@pytest.mark.parametrize("mean_e", [40.0, 300.0, 8000.0])  # exact Poisson and normal regimes
def test_shot_noise_variance_equals_the_mean_in_electrons(mean_e: float) -> None:
    cam = _camera(160, 120)
    # Unit gain, no read noise: tap DN = electrons. Contrast 0 gives equal taps, all = mean.
    cfg = dict(conversion_gain_dn_per_e=1.0, modulation_contrast=0.0, adc_bits=20, full_well_e=1e6)
    sens = _sensor(cam, **cfg)
    p = mean_e / (0.5 * sens.config.electrons_per_watt)
    taps = sens.expose(_plane_signal(cam, 1.0, p), seed=3, noise=True).taps.astype(np.float64)
    x = taps.ravel()  # 4 * 19200 independent samples
    assert x.mean() == pytest.approx(mean_e, rel=5 * math.sqrt(mean_e / x.size) / mean_e + 1e-3)
    # Rounding to integer DN adds 1/12 DN^2 of quantisation noise only in the normal regime
    # (exact Poisson counts are integers already); sample variance s.e. is sqrt(2/n).
    extra = 1 / 12 if mean_e >= 1000 else 0.0
    assert x.var() == pytest.approx(mean_e + extra, rel=5 * math.sqrt(2 / x.size))


def test_read_noise_and_dark_offset() -> None:
    cam = _camera(160, 120)
    sens = _sensor(cam, conversion_gain_dn_per_e=1.0, read_noise_e=7.0, black_level_dn=100.0, adc_bits=12)
    dark = sens.expose(_plane_signal(cam, 1.0, 0.0), seed=1, noise=True).taps.astype(np.float64)
    assert dark.mean() == pytest.approx(100.0, abs=0.2)
    assert dark.var() == pytest.approx(49.0 + 1 / 12, rel=0.05)  # + rounding to DN


def test_saturation_clips_at_full_well() -> None:
    cam = _camera(8, 6)
    fw, gain = 15000.0, 0.1
    sens = _sensor(cam, full_well_e=fw, conversion_gain_dn_per_e=gain, adc_bits=14)
    huge = _plane_signal(cam, 1.0, 1e-3)  # far more than the well holds
    for noise in (False, True):
        taps = sens.expose(huge, seed=2, noise=noise).taps
        np.testing.assert_allclose(taps, fw * gain, rtol=1e-6)
    # The ADC clips too when the full well exceeds its range.
    small_adc = _sensor(cam, full_well_e=fw, conversion_gain_dn_per_e=gain, adc_bits=8)
    assert small_adc.expose(huge, noise=False).taps.max() == 255.0


def test_quantisation_to_adc_bits() -> None:
    cam = _camera(16, 12)
    sens = _sensor(cam, adc_bits=10, conversion_gain_dn_per_e=0.05, read_noise_e=3.0)
    taps = sens.expose(_plane_signal(cam, 1.2, 5e-12), seed=0, noise=True).taps
    assert np.all(taps == np.round(taps)) and taps.min() >= 0 and taps.max() <= 1023


def test_same_seed_identical_frames_different_seed_or_frame_differs() -> None:
    cam = _camera(16, 12)
    sens = _sensor(cam, read_noise_e=4.0)
    sig = _plane_signal(cam, 1.0, 1e-11)
    a = sens.expose(sig, seed=7, frame_index=2).taps
    b = sens.expose(sig, seed=7, frame_index=2).taps
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, sens.expose(sig, seed=8, frame_index=2).taps)
    assert not np.array_equal(a, sens.expose(sig, seed=7, frame_index=3).taps)


def test_noisy_mean_converges_to_the_noise_free_taps() -> None:
    cam = _camera(16, 12)
    sens = _sensor(cam, read_noise_e=5.0, conversion_gain_dn_per_e=0.5, adc_bits=16)
    sig = _plane_signal(cam, 1.3, 2e-11)
    exact = sens.expose(sig, noise=False).taps.astype(np.float64)
    mean = np.mean([sens.expose(sig, seed=1, frame_index=i).taps for i in range(200)], axis=0)
    sd = np.sqrt(exact / 0.5 * 0.25 + 0.25 * 25 + 1 / 12)  # DN: shot + read + rounding
    assert np.all(np.abs(mean - exact) < 5 * sd / np.sqrt(200))


def test_frame_metadata_from_the_scene() -> None:
    cam = _camera(8, 6)
    sens = _sensor(cam, frame_period_s=0.04, temperature_c=31.5, integration_time_s=2e-4)
    f = sens.expose(_plane_signal(cam, 1.0, 1e-11), frame_index=5, noise=False)
    assert f.sequence == 5 and f.timestamp_s == pytest.approx(0.2) and f.temperature_c == 31.5
    assert f.integration_time_s == 2e-4
    assert math.isnan(_sensor(cam).expose(_plane_signal(cam, 1.0, 1e-11), noise=False).temperature_c)


def test_third_harmonic_gives_the_cyclic_wiggling_error() -> None:
    # c_k = B + A [cos(phi - th_k) + a3 cos(3 phi - 3 th_k + psi)]. With 4 taps the 3rd
    # harmonic aliases onto the conjugate fundamental: S = A (e^{i phi} + a3 e^{-i(3 phi + psi)}),
    # so the phase error is arg(1 + a3 exp(-i(4 phi + psi))): 4 cycles per ambiguity range.
    cam = _camera(64, 2)
    r_amb = C / (2 * F44)
    d = np.linspace(0.05, r_amb - 0.05, 64)[None, :].repeat(2, 0)
    a3, psi = 0.08, 0.6
    sens = _sensor(cam, adc_bits=20, full_well_e=1e7)
    for harmonics in ((1, 3), (1,)):  # rendered or synthesised 3rd harmonic: same for one path
        sig = _plane_signal(cam, d, 1e-9, harmonics=harmonics)
        sig.waveform = {1: 1.0, 3: a3 * np.exp(1j * psi)}
        dist = depth_from_raw(sens.expose(sig, noise=False)).distance_m
        phi = 4 * np.pi * F44 * d / C
        err_phase = np.angle(1 + a3 * np.exp(-1j * (4 * phi + psi)))
        np.testing.assert_allclose(dist - d, err_phase * C / (4 * np.pi * F44), atol=2e-5)
        assert np.ptp(dist - d) > 0.05  # centimetre-scale wiggling, not a constant offset


def test_fixed_pattern_is_seeded_and_has_the_stated_spread() -> None:
    cam = _camera(160, 120)
    fp = {"dsnu_e": 30.0, "prnu": 0.02, "seed": 4}
    sens = _sensor(cam, conversion_gain_dn_per_e=1.0, adc_bits=20, black_level_dn=1000.0, fixed_pattern=fp,
                   full_well_e=1e6)
    gain, off = sens.fixed_pattern()
    assert off.std() == pytest.approx(30.0, rel=0.03) and gain.std() == pytest.approx(0.02, rel=0.03)
    again = _sensor(cam, conversion_gain_dn_per_e=1.0, fixed_pattern=fp).fixed_pattern()
    np.testing.assert_array_equal(again[1], off)
    other = _sensor(cam, fixed_pattern=fp | {"seed": 5}).fixed_pattern()
    assert not np.array_equal(other[1], off)
    # Dark frame, noise off: taps = black level + offset exactly.
    dark = sens.expose(_plane_signal(cam, 1.0, 0.0), noise=False).taps[0]
    np.testing.assert_allclose(dark, 1000.0 + off, rtol=1e-6)


def test_taps_at_pixels_are_the_whole_frame_taps_there_for_any_pixel_set() -> None:
    """The fixed pattern at a pixel set is kept for the next call with the same set: a sensor
    asked for one set, then another, then the first again gives the whole frame's taps there."""
    cam = _camera(40, 30)
    sens = _sensor(cam, fixed_pattern={"dsnu_e": 30.0, "prnu": 0.02, "seed": 4}, full_well_e=1e6)
    sig = _plane_signal(cam, np.linspace(0.5, 2.0, cam.width)[None, :].repeat(cam.height, 0), 2e-12)
    whole = sens.taps_dn(sig, noise=False).reshape(1, 4, 1, -1)
    rng = np.random.default_rng(3)
    a, b = (np.sort(rng.choice(cam.width * cam.height, 200, replace=False)) for _ in range(2))
    for index in (a, b, a, b.copy()):
        np.testing.assert_array_equal(sens._noise_free_taps(sig, index), whole[..., index])


def test_defaults_from_the_camera_preset() -> None:
    cam = load_camera_preset("holmlund_thesis")
    cfg = SensorConfig.from_dict({}, camera=cam)
    assert cfg.freq_hz == (44.0e6,) and cfg.taps == 4 and cfg.wavelength_m == 850e-9
    np.testing.assert_allclose(np.degrees(cfg.theta_rad), [0, 90, 180, 270])
    # Default conversion gain maps the full well onto the ADC's full scale.
    assert cfg.full_well_e * cfg.conversion_gain_dn_per_e == pytest.approx(2 ** cfg.adc_bits - 1)
    assert SensorConfig.from_dict(cfg.to_dict(), camera=cam) == cfg


@pytest.mark.parametrize("block, field", [
    ({"freq_hz": [44e6], "full_wel_e": 1}, "sensor.full_wel_e"),
    ({"freq_hz": [44e6], "quantum_efficiency": 1.5}, "sensor.quantum_efficiency"),
    ({"freq_hz": [44e6], "adc_bits": 12.5}, "sensor.adc_bits"),
    ({"freq_hz": [44e6], "taps": 4, "theta_deg": [0, 120, 240]}, "sensor.theta_deg"),
    ({"freq_hz": [44e6], "theta_deg": [0, 90, 200, 270]}, "sensor.theta_deg"),
    ({"freq_hz": ["fast"]}, "sensor.freq_hz[0]"),
    ({}, "sensor.freq_hz"),
    ({"freq_hz": [44e6], "fixed_pattern": {"dsnu": 3}}, "sensor.fixed_pattern.dsnu"),
    ({"freq_hz": [44e6], "integration_time_s": -1}, "sensor.integration_time_s"),
])
def test_bad_sensor_block_names_file_and_field(block: dict, field: str) -> None:
    with pytest.raises(InputFileError) as err:
        SensorConfig.from_dict(block, source="scenes/x.yaml", camera=_camera())
    assert err.value.file == "scenes/x.yaml" and err.value.field == field and err.value.expected


def test_two_frequencies_are_exposed_independently() -> None:
    cam = _camera(8, 6)
    sens = _sensor(cam, freq_hz=[80e6, 100e6], adc_bits=16)
    f = sens.expose(_plane_signal(cam, 5.2, 1e-11, freqs=(80e6, 100e6)), noise=False)
    # Unwrapping the two frequencies recovers 5.2 m, beyond both single ambiguity ranges.
    np.testing.assert_allclose(depth_from_raw(f).distance_m, 5.2, atol=1e-4)


def test_a_binned_fixed_pattern_that_does_not_fit_the_camera_is_one_line(tmp_path, tofhil_cli):
    """A scene whose ``sensor.fixed_pattern.binned`` names a sensor that does not bin to its
    camera: one line naming the field, exit 2 (it was a ValueError's traceback)."""
    from tofhil.sim.scene import load_scene, scene_to_yaml

    text = scene_to_yaml(load_scene("dark_square")).replace("seed: 1", "seed: 1, binned: [2, 100, 100]", 1)
    assert "binned: [2, 100, 100]" in text
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    r = tofhil_cli("simulate", path, "--out", tmp_path / "x.h5", "--frames", "2")
    assert r.returncode == 2 and "sensor.fixed_pattern.binned" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "x.h5").exists()
