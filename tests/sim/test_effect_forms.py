"""The flexible scalar forms of the effect library (issue 10): wiggling with the odd
harmonics up to the 7th and their aliasing onto K taps, the monotone spline in log amplitude,
and the emitter's illumination profile. Each is checked against a closed form computed here,
not against the effect's own output."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tofhil.camera import CameraModel
from tofhil.demod import phasor
from tofhil.sim.effects import (AMPLITUDE_KNOTS_LOG10_E, EFFECTS, EffectContext, harmonic_aliases, monotone_spline,
                                stick_breaking)
from tofhil.sim.sensor import OpticalSignal


def _taps(phi: np.ndarray, theta: np.ndarray, harmonics: dict[int, complex]) -> np.ndarray:
    """c_k = sum_h Re(a_h exp(i psi_h) exp(i h (phi - theta_k))), written out by hand."""
    return sum((c * np.exp(1j * h * (phi[None] - theta[:, None]))).real for h, c in harmonics.items())


@pytest.mark.parametrize("k", [3, 4, 5, 8])
def test_a_harmonic_reaches_k_taps_exactly_when_it_aliases(k):
    """The K-tap estimate of a pure harmonic h is zero unless h = +-1 mod K (closed form:
    sum_k exp(i (1 -+ h) theta_k) vanishes otherwise)."""
    theta = 2 * np.pi * np.arange(k) / k
    phi = np.linspace(0, 2 * np.pi, 37)
    for h in range(2, 10):
        s = (2.0 / k) * np.sum(_taps(phi, theta, {h: 1.0}) * np.exp(1j * theta)[:, None], axis=0)
        assert (np.abs(s).max() > 0.5) == harmonic_aliases(h, k), (h, k)


def _signal(phi: np.ndarray) -> OpticalSignal:
    n = phi.size
    return OpticalSignal(freq_hz=np.array([20e6]), harmonics=(1,), phasor_w=np.exp(1j * phi)[None, None, None, :],
                         dc_w=np.ones((1, n)), ambient_w=np.zeros((1, n)))


def test_wiggling_orders_3_5_7_give_the_closed_form_phase_error_on_4_taps():
    """K = 4: S / exp(i phi) = 1 + a3 exp(-i(4 phi + psi3)) + a5 exp(i(4 phi + psi5))
    + a7 exp(-i(8 phi + psi7)). The effect only adds waveform coefficients; the taps and the
    estimator here are written out independently."""
    rng = np.random.default_rng(3)
    a = {h: rng.uniform(0.02, 0.08) for h in (3, 5, 7)}
    psi = {h: rng.uniform(-math.pi, math.pi) for h in (3, 5, 7)}
    values = {f"h{h}_amplitude": a[h] for h in a} | {f"h{h}_phase_rad": psi[h] for h in psi}
    phi = np.linspace(-math.pi, math.pi, 181)
    out = EFFECTS["wiggling"].apply_signal(_signal(phi), EFFECTS["wiggling"].validate(values), None)  # type: ignore[arg-type]
    theta = np.arange(4) * np.pi / 2
    taps = _taps(phi, theta, out.waveform)
    s = phasor(taps[None, :, None, :], theta)[0, 0]
    s /= phasor(_taps(phi, theta, {1: 1.0})[None, :, None, :], theta)[0, 0]  # the estimator's scale
    expected = 1 + a[3] * np.exp(-1j * (4 * phi + psi[3])) + a[5] * np.exp(1j * (4 * phi + psi[5])) \
        + a[7] * np.exp(-1j * (8 * phi + psi[7]))
    np.testing.assert_allclose(s, expected, atol=1e-12)


def test_wiggling_forms_and_taps():
    """The simple form fits the 3rd harmonic; the flexible form every order up to the 7th the
    taps see (h = +-1 mod K): with 3 taps the 3rd harmonic cancels and the 2nd and 4th (a duty
    cycle off 50 %) are seen; with 4 taps the even ones cancel."""
    w = EFFECTS["wiggling"]
    assert set(w.form_params("")) == {"h3_amplitude", "h3_phase_rad"}
    assert set(w.form_params("harmonics", 4)) == {f"h{h}_{q}" for h in (3, 5, 7) for q in ("amplitude", "phase_rad")}
    assert set(w.form_params("harmonics", 3)) == {f"h{h}_{q}" for h in (2, 4, 5, 7) for q in ("amplitude", "phase_rad")}
    assert w.form_params("", 3) == {}


def test_stick_breaking_and_the_spline_are_monotone_for_any_parameters():
    rng = np.random.default_rng(0)
    knots = np.asarray(AMPLITUDE_KNOTS_LOG10_E)
    x = np.linspace(knots[0] - 1, knots[-1] + 1, 400)
    for _ in range(200):
        q = rng.uniform(0, 1, knots.size - 2)
        w = stick_breaking(q)
        assert np.all(w >= 0) and w.sum() == pytest.approx(1.0)
        level, span = rng.uniform(-0.1, 0.1, 2)
        y = monotone_spline(x, knots, level, span, q)
        d = np.diff(y) * np.sign(span)
        assert np.all(d >= -1e-15)
        assert y[0] == pytest.approx(level) and y[-1] == pytest.approx(level + span)
    # the off values of the shape fractions give equal shares: linear in log amplitude
    p = EFFECTS["amplitude_dependent"].params
    q0 = np.array([p[f"spline_q{j}"].off for j in (1, 2, 3)])
    np.testing.assert_allclose(stick_breaking(q0), 0.25)
    xi = np.linspace(knots[0], knots[-1], 50)
    np.testing.assert_allclose(monotone_spline(xi, knots, 0.01, 0.04, q0),
                               0.01 + 0.04 * (xi - knots[0]) / (knots[-1] - knots[0]), atol=1e-15)


def test_amplitude_spline_shifts_the_phase_by_twice_the_radial_error():
    """Radial error e(A) -> optical path 2 e: the phase turns by 4 pi f e / c."""
    from tofhil import C_M_PER_S
    from tofhil.sim.sensor import SensorConfig

    sensor = SensorConfig(freq_hz=(20e6,), theta_rad=tuple(np.arange(4) * np.pi / 2))
    e_per_amp = sensor.tap_fraction * sensor.modulation_contrast * sensor.electrons_per_watt
    amp_e = 10.0 ** np.linspace(1.5, 5.5, 30)
    sig = OpticalSignal(freq_hz=np.array([20e6]), harmonics=(1,), phasor_w=(amp_e / e_per_amp)[None, None, None, :],
                        dc_w=np.ones((1, 30)), ambient_w=np.zeros((1, 30)))
    values = EFFECTS["amplitude_dependent"].validate({"error_m": 0.0, "spline_level_m": -0.02, "spline_span_m": 0.05,
                                                      "spline_q1": 0.5, "spline_q2": 0.2, "spline_q3": 0.9})
    ctx = EffectContext(camera=CameraModel(30, 1, 20.0, 20.0, 15.0, 0.5), sensor=sensor)
    out = EFFECTS["amplitude_dependent"].apply_signal(sig, values, ctx)
    err = np.angle(out.phasor_w[0, 0, 0]) * C_M_PER_S / (4 * np.pi * 20e6)
    # by hand: shares 0.5, 0.5*0.2, 0.4*0.9, 0.04 of the span over the 4 intervals
    knots = np.asarray(AMPLITUDE_KNOTS_LOG10_E)
    at_knots = -0.02 + 0.05 * np.array([0.0, 0.5, 0.6, 0.96, 1.0])
    np.testing.assert_allclose(err, np.interp(np.log10(amp_e), knots, at_knots), atol=1e-12)


def test_illumination_scales_the_emitter_light_only_by_cos_dn_and_the_polynomial():
    cam = CameraModel(40, 30, 30.0, 30.0, 19.5, 14.5)
    v, u = np.mgrid[0:30, 0:40].astype(float)
    t2 = ((u - cam.cx) / cam.fx) ** 2 + ((v - cam.cy) / cam.fy) ** 2
    cos_alpha = cam.fx / np.sqrt(cam.fx ** 2 + (u - cam.cx) ** 2 + (v - cam.cy) ** 2 * (cam.fx / cam.fy) ** 2)
    s = OpticalSignal(freq_hz=np.array([20e6]), harmonics=(1,), phasor_w=np.exp(0.3j) * np.ones((1, 1, 30, 40)),
                      dc_w=2.0 * np.ones((30, 40)), ambient_w=0.5 * np.ones((30, 40)))
    eff = EFFECTS["illumination"]
    out = eff.apply_signal(s, eff.validate({"dn": 2.5, "b4": -3.0, "b6": 4.0}), EffectContext(camera=cam))
    g = cos_alpha ** 2.5 * (1 - 3.0 * t2 ** 2 + 4.0 * t2 ** 3)
    np.testing.assert_allclose(out.phasor_w[0, 0], np.exp(0.3j) * g, atol=1e-14)
    np.testing.assert_allclose(out.dc_w, 2.0 * g, atol=1e-14)
    np.testing.assert_allclose(out.ambient_w, 0.5)  # scene ambient is not the emitter's
    assert set(eff.form_params("")) == {"dn"} and set(eff.form_params("radial")) == {"dn", "b4", "b6"}
