"""Multi-frequency unwrapping against known distances over the whole unambiguous range."""

from __future__ import annotations

import numpy as np
import pytest

from tofhil import C_M_PER_S
from tofhil.demod import distance_to_phase, equally_spaced_phases, phasor, taps_from_signal, wrapped_phase
from tofhil.unwrap import frequency_plan, unwrap


def _phases(d, freqs, rng=None, phase_noise=0.0):
    ph = np.stack([distance_to_phase(d, f) for f in freqs])
    if rng is not None and phase_noise > 0:
        ph = np.mod(ph + rng.normal(0, phase_noise, ph.shape), 2 * np.pi)
    return ph


def test_frequency_plan_oak_80_100():
    plan = frequency_plan([80e6, 100e6])
    assert plan.multiples == (4, 5)
    assert plan.base_hz == pytest.approx(20e6)
    assert plan.unambiguous_range_m == pytest.approx(C_M_PER_S / (2 * 20e6))
    assert plan.unambiguous_range_m == pytest.approx(7.4948, abs=1e-4)


@pytest.mark.parametrize("freqs", [[80e6, 100e6], [10e6, 20e6], [44e6, 55e6], [60e6, 80e6, 100e6],
                                   [20e6, 50e6, 70e6]])
def test_noise_free_unwrapping_covers_whole_range(freqs):
    rng_m = frequency_plan(freqs).unambiguous_range_m
    d = np.linspace(0.0, rng_m * (1 - 1e-6), 20001).reshape(1, -1)
    res = unwrap(_phases(d, freqs), freqs)
    err = np.abs(res.distance_m - d)
    err = np.minimum(err, rng_m - err)  # 0 and R are the same point on the circle
    assert err.max() < 1e-8
    assert not res.conflict.any()


def test_noisy_unwrapping_and_conflict_flag():
    freqs = [80e6, 100e6]
    rng = np.random.default_rng(7)
    rmax = frequency_plan(freqs).unambiguous_range_m
    d = rng.uniform(0, rmax, (200, 200))
    # Realistic noise: 2 deg phase noise; nothing may unwrap wrongly (a wrong wrap count is an
    # error of about a metre), and the spread is that of the weighted mean of the two
    # frequencies: sigma_i = sigma_phi * R_i / (2 pi), weights f_i^2.
    sigma_phi = np.radians(2.0)
    res = unwrap(_phases(d, freqs, rng, sigma_phi), freqs)
    err = res.distance_m - d
    err = (err + rmax / 2) % rmax - rmax / 2
    s1, s2 = (sigma_phi * C_M_PER_S / (2 * f) / (2 * np.pi) for f in freqs)
    w1, w2 = 16.0, 25.0
    expected_sigma = np.hypot(w1 * s1, w2 * s2) / (w1 + w2)
    assert np.abs(err).max() < 10 * expected_sigma
    assert err.std() == pytest.approx(expected_sigma, rel=0.05)
    assert res.conflict.mean() < 1e-3
    # Heavy noise (12 deg): some pixels unwrap wrongly; the flag must catch nearly all of them
    # while leaving most good pixels unflagged. (Far beyond this, the combined phase error
    # M2*dphi1 - M1*dphi2 exceeds a whole cycle and no detector can tell.)
    res = unwrap(_phases(d, freqs, rng, np.radians(12.0)), freqs)
    err = np.abs(res.distance_m - d)
    err = np.minimum(err, rmax - err)
    wrong = err > 0.3
    assert wrong.mean() > 0.003  # the test has teeth: errors do occur at this noise
    assert res.conflict[wrong].mean() > 0.9
    assert res.conflict[~wrong].mean() < 0.3


def test_disagreeing_frequencies_are_flagged():
    freqs = [80e6, 100e6]
    d = np.full((1, 4), 3.0)
    ph = _phases(d, freqs)
    ph[1, :, 2:] = np.mod(ph[1, :, 2:] + np.pi * 0.3, 2 * np.pi)  # a second path corrupts f2 only
    res = unwrap(ph, freqs)
    assert not res.conflict[0, :2].any()
    assert res.conflict[0, 2:].all()


def test_unwrapping_through_taps_with_amplitude_weights():
    freqs = np.array([80e6, 100e6])
    theta = equally_spaced_phases(4)
    d = np.linspace(0.05, 7.4, 64).reshape(8, 8)
    amp = np.stack([np.full(d.shape, 100.0), np.full(d.shape, 50.0)])
    taps = taps_from_signal(amp, _phases(d, freqs), np.full((2,) + d.shape, 400.0), theta)
    s = phasor(taps, theta)
    res = unwrap(wrapped_phase(s), freqs, amplitude=np.abs(s))
    np.testing.assert_allclose(res.distance_m, d, atol=1e-9)
