"""The compiled noise-free taps equal the sensor model written out as numpy expressions,
bit for bit: harmonics (rendered and synthesised), ambient, fixed pattern, dark current,
full well, black level and the ADC's range."""

from __future__ import annotations

import numpy as np

from tofhil.camera import CameraModel
from tofhil.sim.sensor import FixedPatternConfig, OpticalSignal, SensorConfig, SensorModel

C = 299_792_458.0


def _reference(sm: SensorModel, sig: OpticalSignal) -> np.ndarray:
    """E = gain * max(e_w (B + m sum_h Re(a_h S_h e^{-i h theta})), 0) + dark, clipped at the
    full well, plus the offset, times the conversion gain, plus black, within the ADC."""
    cfg = sm.config
    th = np.asarray(cfg.theta_rad)
    mod = np.zeros((len(cfg.freq_hz), th.size) + sig.shape)
    for h, a in sig.waveform.items():
        s = a * sig.harmonic(h)
        mod += (s[:, None] * np.exp(-1j * h * th)[None, :, None, None]).real
    gain, off = sm.fixed_pattern()
    photo = cfg.tap_fraction * cfg.electrons_per_watt * ((sig.dc_w + sig.ambient_w) + cfg.modulation_contrast * mod)
    e = gain[None] * np.maximum(photo, 0) + cfg.dark_current_e_per_s * cfg.integration_time_s
    dn = (np.minimum(e, cfg.full_well_e) + off[None]) * cfg.conversion_gain_dn_per_e + cfg.black_level_dn
    return np.clip(dn, 0, cfg.adc_max_dn).astype(np.float32)


def test_noise_free_taps_match_the_model():
    cam = CameraModel.from_fov(24, 18, 60.0)
    rng = np.random.default_rng(5)
    d = rng.uniform(0.3, 3.0, cam.shape)
    p = rng.uniform(0.0, 2e-11, cam.shape)
    p[0, :4] = 5e-10  # saturating pixels (the full well is ~2.7e-11 W here)
    freqs = (44e6, 60e6)
    ph = np.stack([np.stack([p * np.exp(1j * 2 * np.pi * h * f * 2 * d / C) for h in (1, 3)]) for f in freqs])
    sig = OpticalSignal(freq_hz=np.array(freqs), harmonics=(1, 3), phasor_w=ph, dc_w=p,
                        ambient_w=np.full(cam.shape, 1e-13),
                        waveform={1: 1.0 + 0.0j, 3: 0.05 * np.exp(0.7j), 5: 0.02 + 0.01j})  # 5: synthesised
    cfg = SensorConfig(freq_hz=freqs, theta_rad=(0.0, np.pi / 2, np.pi, 3 * np.pi / 2), black_level_dn=30.0,
                       fixed_pattern=FixedPatternConfig(dsnu_e=20.0, prnu=0.02, seed=3))
    sm = SensorModel(cfg, cam)
    taps = sm.taps_dn(sig, noise=False)
    ref = _reference(sm, sig)
    assert taps.dtype == np.float32 and taps.shape == (2, 4) + cam.shape
    # the model's numbers to float32 (the reference sums the harmonics in complex form)
    assert np.allclose(taps, ref, rtol=1e-6, atol=1e-3)
    # bit-identical to the noisy path's own expressions with the noise left out
    mu = sm.expected_electrons(sig)
    assert (mu > cfg.full_well_e).any() and (mu < 0.5 * cfg.full_well_e).any()  # the full well is reached
    manual = np.clip((np.minimum(mu, cfg.full_well_e) + sm.fixed_pattern()[1][None]) * cfg.conversion_gain_dn_per_e
                     + cfg.black_level_dn, 0.0, cfg.adc_max_dn).astype(np.float32)
    assert np.array_equal(taps, manual)
