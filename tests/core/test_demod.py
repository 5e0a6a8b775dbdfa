"""Demodulation checked against the closed-form tap model c_k = B + A cos(phi - theta_k)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tofhil import C_M_PER_S
from tofhil.camera import CameraModel
from tofhil.demod import (TapConvention, ambiguity_range_m, differential_offset, differential_phasor,
                          differential_to_taps, distance_to_phase, equally_spaced_phases, offset,
                          phase_to_distance, phasor, taps_from_signal, wrapped_phase)
from tofhil.depth import depth_from_raw
from tofhil.frames import RawFrame

amplitudes = st.floats(0.01, 1e4)
phases = st.floats(0.0, 2 * np.pi - 1e-9)


@settings(max_examples=200, deadline=None)
@given(k=st.integers(3, 16), a=amplitudes, phi=phases, b_over_a=st.floats(1.0, 10.0),
       start=st.floats(-np.pi, np.pi))
def test_k_tap_estimator_recovers_amplitude_phase_offset(k, a, phi, b_over_a, start):
    theta = equally_spaced_phases(k, start)
    b = a * b_over_a
    c = b + a * np.cos(phi - theta)  # closed form, written independently of taps_from_signal
    s = phasor(c[:, None, None], theta)[0, 0]
    assert abs(s) == pytest.approx(a, rel=1e-9, abs=1e-9)
    dphi = np.angle(s * np.exp(-1j * phi))
    assert abs(dphi) < 1e-9
    assert offset(c[:, None, None])[0, 0] == pytest.approx(b, rel=1e-12)


def test_four_phase_matches_holmlund_ab_formula():
    # Holmlund's 4-phase AB values: I = A0 - A2, Q = A1 - A3 (theta = 0, 90, 180, 270 deg):
    # phi = atan2(A1 - A3, A0 - A2), A = sqrt(I^2 + Q^2) / 2.
    rng = np.random.default_rng(1)
    a, phi, b = rng.uniform(1, 100, 50), rng.uniform(0, 2 * np.pi, 50), rng.uniform(100, 200, 50)
    theta = np.radians([0, 90, 180, 270])
    c = b[None] + a[None] * np.cos(phi[None] - theta[:, None])
    s = phasor(c[:, None, :], theta)[0]
    i, q = c[0] - c[2], c[1] - c[3]
    np.testing.assert_allclose(np.abs(s), np.hypot(i, q) / 2, rtol=1e-12)
    np.testing.assert_allclose(np.mod(np.arctan2(q, i), 2 * np.pi), wrapped_phase(s), atol=1e-12)


def test_estimator_refuses_unequal_or_too_few_phases():
    with pytest.raises(ValueError, match="K >= 3"):
        phasor(np.zeros((2, 1, 1)), np.radians([0, 180]))
    with pytest.raises(ValueError, match="equally spaced"):
        phasor(np.zeros((4, 1, 1)), np.radians([0, 90, 180, 260]))


@settings(max_examples=100, deadline=None)
@given(m=st.integers(2, 6), a=amplitudes, phi=phases, b_over_a=st.floats(1.0, 10.0),
       ambient=st.floats(0.0, 1e3))
def test_two_tap_differential_readout(m, a, phi, b_over_a, ambient):
    # Tap A samples theta_m, tap B theta_m + pi, both with the same offset and ambient.
    theta = np.pi * np.arange(m) / m
    b = a * b_over_a + ambient
    tap_a = (b + a * np.cos(phi - theta))[:, None, None]
    tap_b = (b + a * np.cos(phi - theta - np.pi))[:, None, None]
    s = differential_phasor(tap_a, tap_b, theta)[0, 0]
    assert abs(s) == pytest.approx(a, rel=1e-9)
    assert abs(np.angle(s * np.exp(-1j * phi))) < 1e-9
    assert differential_offset(tap_a, tap_b)[0, 0] == pytest.approx(b, rel=1e-12)
    taps, th = differential_to_taps(tap_a, tap_b, theta)
    s2 = phasor(taps, th)[0, 0]
    assert abs(s2 - s) < 1e-9 * max(1.0, a)


def test_phase_wraps_at_half_wavelength():
    f = 44e6
    r = ambiguity_range_m(f)
    assert r == pytest.approx(C_M_PER_S / (2 * f))
    d = np.array([0.1, r - 1e-6, r + 0.1, 2 * r + 0.25])
    phi = distance_to_phase(d, f)
    back = phase_to_distance(phi, f)
    np.testing.assert_allclose(back, np.mod(d, r), atol=1e-9)
    # Through the full tap pipeline: a target just beyond c/2f reads near zero.
    theta = equally_spaced_phases(4)
    taps = taps_from_signal(np.ones(4)[None, None], phi[None, None], 2 * np.ones(4)[None, None], theta)
    s = phasor(taps[0], theta)
    np.testing.assert_allclose(phase_to_distance(wrapped_phase(s), f)[0], np.mod(d, r), atol=1e-9)


def test_tap_convention_converts_device_order_and_sign():
    rng = np.random.default_rng(2)
    a, phi, b = 50.0, rng.uniform(0, 2 * np.pi), 300.0
    theta = np.radians([0, 90, 180, 270])
    canonical = b + a * np.cos(phi - theta)
    # A device that stores taps in order 2, 0, 3, 1 and reports the negated correlation.
    device = (b - a * np.cos(phi - theta))[[2, 0, 3, 1]]
    conv = TapConvention(theta_rad=tuple(theta), order=(1, 3, 0, 2), sign=-1)
    taps, th = conv.to_canonical(device[:, None, None])
    s = phasor(taps, th)[0, 0]
    s_ref = phasor(canonical[:, None, None], theta)[0, 0]
    assert abs(s - s_ref) < 1e-9


def test_depth_from_raw_plane_single_frequency():
    cam = CameraModel.from_fov(32, 24, 60.0)
    f = 44e6
    d_true = np.full(cam.shape, 1.234)
    theta = equally_spaced_phases(4)
    taps = taps_from_signal(np.full(cam.shape, 100.0)[None], distance_to_phase(d_true, f)[None],
                            np.full(cam.shape, 500.0)[None], theta)
    frame = RawFrame(taps=taps.astype(np.float32), freq_hz=[f], theta_rad=theta, integration_time_s=1e-3, camera=cam)
    depth = depth_from_raw(frame)
    np.testing.assert_allclose(depth.distance_m, d_true, atol=1e-5)
    np.testing.assert_allclose(depth.amplitude, 100.0, rtol=1e-5)
    np.testing.assert_allclose(depth.intensity, 500.0, rtol=1e-5)
    assert depth.valid.all() and depth.kind == "radial"


@pytest.mark.parametrize("freqs,k", [([44e6], 4), ([80e6, 100e6], 4), ([10e6, 20e6], 4), ([44e6], 3),
                                     ([80e6, 100e6], 5), ([80e6, 100e6], 8), ([20e6, 30e6, 50e6], 4),
                                     ([80e6, 100e6, 120e6], 3), ([60e6, 80e6, 100e6], 6),
                                     # the search's other trip counts: 5-8 and > 8 wrap counts
                                     ([50e6, 60e6, 70e6], 4), ([90e6, 100e6, 110e6], 4)])
@pytest.mark.parametrize("start_deg", [0.0, 37.0])
def test_fused_path_agrees_with_general_path(freqs, k, start_deg):
    """The fused kernel (approximate arctangent, one pass over the taps) against the numpy
    path (np.arctan2), for odd and even K and one to three frequencies."""
    from tofhil.fastdepth import fused_supported
    from tofhil.unwrap import frequency_plan

    rng = np.random.default_rng(3)
    cam = CameraModel.from_fov(64, 48, 60.0)
    theta = equally_spaced_phases(k, np.radians(start_deg))
    rmax = frequency_plan(freqs).unambiguous_range_m
    d = rng.uniform(0.0, rmax, cam.shape)
    amp = rng.uniform(20, 400, (len(freqs),) + cam.shape)
    phase = np.stack([distance_to_phase(d, f) for f in freqs])
    taps = taps_from_signal(amp, phase, np.full(amp.shape, 900.0), theta)
    taps = (taps + rng.normal(0, 3.0, taps.shape)).astype(np.float32)
    frame = RawFrame(taps=taps, freq_hz=freqs, theta_rad=theta, integration_time_s=1e-3, camera=cam)
    assert fused_supported(taps, theta)
    fast = depth_from_raw(frame)
    slow = depth_from_raw(frame, fused=False)
    diff = np.abs(fast.distance_m - slow.distance_m)
    diff = np.minimum(diff, rmax - diff)
    np.testing.assert_array_equal(fast.valid, slow.valid)  # one definition of validity
    same = ~(fast.unwrap_conflict | slow.unwrap_conflict)
    assert same.mean() > 0.95
    assert np.quantile(diff[same], 0.999) < 2e-6 * rmax  # arctangent to ~2e-7 rad + float32 rounding
    np.testing.assert_allclose(fast.amplitude, slow.amplitude, rtol=1e-5, atol=1e-3)
    np.testing.assert_allclose(fast.intensity, slow.intensity, rtol=1e-6)
    assert (fast.unwrap_conflict != slow.unwrap_conflict).mean() < 0.002
    # and the fused result is the truth within the noise
    err = np.abs(fast.distance_m - d)
    err = np.minimum(err, rmax - err)
    assert np.median(err[same]) < 0.01


@pytest.mark.parametrize("freqs", [[20e6], [20e6, 30e6], [20e6, 30e6, 50e6]])
def test_bad_taps_are_invalid_in_both_paths(freqs):
    """NaN, +-inf and saturated taps (at the frame's declared ADC limits) make the pixel
    invalid in the fused kernel and in the numpy path alike; the other pixels agree."""
    from tofhil.demod import TapLimits, bad_tap_pixels

    cam = CameraModel.from_fov(40, 30, 60.0)
    theta = equally_spaced_phases(4)
    d = np.full(cam.shape, 1.5)
    amp = np.full((len(freqs),) + cam.shape, 300.0)
    phase = np.stack([distance_to_phase(d, f) for f in freqs])
    taps = taps_from_signal(amp, phase, np.zeros(amp.shape), theta).astype(np.float32)
    hostile = {(3, 4): np.nan, (5, 6): np.inf, (7, 8): -np.inf, (9, 10): 2047.0, (11, 12): -2048.0}
    for (r, c), v in hostile.items():
        taps[-1, 1, r, c] = v
    frame = RawFrame(taps=taps, freq_hz=freqs, theta_rad=theta, integration_time_s=1e-3, camera=cam,
                     meta={"saturation_dn": 2047.0, "saturation_low_dn": -2048.0})
    expected_bad = np.zeros(cam.shape, bool)
    for rc in hostile:
        expected_bad[rc] = True
    np.testing.assert_array_equal(bad_tap_pixels(taps, TapLimits(2047.0, -2048.0)), expected_bad)
    for fused in (True, False):
        depth = depth_from_raw(frame, fused=fused)
        np.testing.assert_array_equal(depth.valid, ~expected_bad)
        np.testing.assert_allclose(depth.distance_m[depth.valid], 1.5, atol=1e-4)
    # Without declared limits a tap at 2047 is a measurement (its pixel may still be flagged by
    # unwrapping, the frequencies disagree); NaN and inf taps are never one.
    frame.meta = {}
    for fused in (True, False):
        valid = depth_from_raw(frame, fused=fused).valid
        assert not any(valid[rc] for rc in list(hostile)[:3])
        assert valid.sum() >= valid.size - len(hostile)


def test_detect_clipping_finds_pinned_extremes_only():
    from tofhil.demod import detect_clipping

    rng = np.random.default_rng(0)
    tmax = rng.uniform(0, 1000, (30, 40))
    tmin = rng.uniform(-1000, 0, (30, 40))
    assert detect_clipping(tmax, tmin).high_dn is None and detect_clipping(tmax, tmin).low_dn is None
    tmax[:2, :3] = 2047.0
    tmin[5, :5] = -2048.0
    lim = detect_clipping(tmax, tmin)
    assert lim.high_dn == 2047.0 and lim.low_dn == -2048.0


@pytest.mark.parametrize("k", [3, 4])
def test_one_frequency_loop_equals_block_kernel(k):
    """One frequency takes a single-loop kernel (no block buffers); it must give exactly the
    numbers of the general block kernel, bad taps included."""
    import math

    from tofhil.demod import TapLimits, estimator_weights
    from tofhil.fastdepth import _fused, fused_depth

    rng = np.random.default_rng(5)
    theta = equally_spaced_phases(k, np.radians(11.0))
    shape = (1, 30, 40)
    phase = rng.uniform(0, 2 * np.pi, shape)
    taps = taps_from_signal(rng.uniform(5, 400, shape), phase, np.full(shape, 900.0), theta)
    taps = (taps + rng.normal(0, 3.0, taps.shape)).astype(np.float32)
    taps[0, 1, 3, 4], taps[0, 0, 5, 6], taps[0, k - 1, 7, 8], taps[0, 2, 9, 10] = np.nan, np.inf, 2047.0, -2048.0
    taps[0, :, 11, 12] = 900.0     # zero amplitude: phase of (0, 0)
    limits = TapLimits(2047.0, -2048.0)
    d, amp, inten, conf, rng_m, valid = fused_depth(taps, theta, np.array([44e6]), 0.5, limits)
    wts = estimator_weights(theta)
    n = 30 * 40
    ref = [np.empty(n, np.float32) for _ in range(3)] + [np.empty(n, np.uint8) for _ in range(2)]
    c = np.zeros(14, np.float32)
    c[8], c[9], c[11] = rng_m, 1.0 / rng_m, 1.0 / k
    r = np.array([rng_m], np.float32)
    lo, hi = limits.bounds(np.float32)
    _fused(taps.reshape(1, k, n), wts.real.astype(np.float32), wts.imag.astype(np.float32), lo, hi, c, r,
           np.ones(1, np.float32), np.zeros((3, 3), np.float32), *ref)
    for got, want in zip((d, amp, inten, conf, valid), ref):
        np.testing.assert_array_equal(got.reshape(-1).view(want.dtype), want)
    assert not valid[3, 4] and not valid[9, 10] and valid.sum() == n - 4
    assert math.isclose(rng_m, 299792458.0 / (2 * 44e6), rel_tol=1e-12)
