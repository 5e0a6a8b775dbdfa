"""Stray-light corrections on synthetic complex images built here, independently of the code.

Scenes are phasor images ``S = A exp(i 4 pi f d / c)`` of a wall, a dark square on it and a
bright card near the lens; stray light is applied with scipy's own FFT convolution (not
the module's), so the corrections are checked against an independent forward model.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import convolve2d, fftconvolve
from scipy.stats import norm

from tofhil import C_M_PER_S
from tofhil.errors import InputFileError, TofhilError
from tofhil.eval.corrections import psf_calibration as pc
from tofhil.eval.corrections import straylight as sl
from tofhil.sim.straylight import (GaussianLobe, Ghost, StrayLightOperator, StrayLightPSF, convolve,
                                   gaussian_kernel)

F_HZ = 20e6  # ambiguity range 7.5 m: no wrapping for the distances used here
H, W = 48, 64


def phasor_of(amplitude: np.ndarray, distance_m: np.ndarray) -> np.ndarray:
    return amplitude * np.exp(1j * 4 * np.pi * F_HZ * distance_m / C_M_PER_S)


def distance_of(s: np.ndarray) -> np.ndarray:
    return np.mod(np.angle(s), 2 * np.pi) * C_M_PER_S / (4 * np.pi * F_HZ)


def scene(square_reflectance: float | None, card: bool, wall: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(S, radial distance, dark-square mask): wall at 2 m, square on it, card at 0.3 m."""
    amp = np.zeros((H, W))
    dist = np.full((H, W), 2.0)
    sq = np.zeros((H, W), bool)
    sq[18:30, 36:50] = True
    if wall:
        amp[:] = 1.0 / 2.0 ** 2  # inverse square law, reflectance 1
        if square_reflectance is not None:
            amp[sq] = square_reflectance / 2.0 ** 2
    if card:
        c = (slice(8, 22), slice(6, 18))
        amp[c] = 1.0 / 0.3 ** 2
        dist[c] = 0.3
    return phasor_of(amp, dist), dist, sq


def gauss(sigma_h: float, sigma_v: float) -> np.ndarray:
    """Unit-sum Gaussian integrated over each pixel, on the full (2H-1, 2W-1) grid."""
    y = np.arange(-(H - 1), H)[:, None]
    x = np.arange(-(W - 1), W)[None, :]
    g = (norm.cdf(y + 0.5, scale=sigma_v) - norm.cdf(y - 0.5, scale=sigma_v)) * \
        (norm.cdf(x + 0.5, scale=sigma_h) - norm.cdf(x - 0.5, scale=sigma_h))
    return g / g.sum()


# The "true" optics: two Gaussians off the dictionary's widths, a veil and a ghost.
TRUE_KERNEL = 0.04 * gauss(2.3, 2.3) + 0.05 * gauss(13.0, 13.0) + 0.03 * np.ones((2 * H - 1, 2 * W - 1)) / (H * W)
GHOST = 0.01
W_SCATTERED = 0.04 + 0.05 + 0.03 + GHOST  # fraction of a pixel's light that leaves it


def apply_optics(s: np.ndarray, conserve: bool = False) -> np.ndarray:
    """S_meas = S + k * S + ghost mirrored through the centre (independent implementation).

    With ``conserve`` the scattered light leaves its pixel: S_meas = (1 - W) S + ...
    """
    scatter = fftconvolve(s, TRUE_KERNEL, mode="full")[H - 1:2 * H - 1, W - 1:2 * W - 1]
    keep = 1.0 - W_SCATTERED if conserve else 1.0
    return keep * s + scatter + GHOST * s[::-1, ::-1]


def test_the_inverse_filter_uses_the_simulators_kernel():
    # One Gaussian for simulation and correction: the kernel is the pixel-integrated unit
    # Gaussian of scipy's normal distribution (independent construction).
    y = np.arange(-(H - 1), H)[:, None]
    x = np.arange(-(W - 1), W)[None, :]
    g = (norm.cdf(y + 0.5, scale=2.0) - norm.cdf(y - 0.5, scale=2.0)) * \
        (norm.cdf(x + 0.5, scale=3.0) - norm.cdf(x - 0.5, scale=3.0))
    assert np.allclose(gaussian_kernel((H, W), 3.0, 2.0), g, atol=1e-15)
    rng = np.random.default_rng(1)
    s = rng.normal(size=(H, W)) + 1j * rng.normal(size=(H, W))
    direct = convolve2d(s, g, mode="full")[H - 1:2 * H - 1, W - 1:2 * W - 1]
    assert np.allclose(convolve(s, g), direct, atol=1e-12)


def test_uniform_subtraction_inverts_a_uniform_veil_exactly():
    # S_meas = S + v * sum(S): sum(S_meas) = (1 + N v) sum(S), so w = v / (1 + N v) is exact.
    s, _, _ = scene(0.1, card=True)
    v = 2e-5
    meas = s + v * s.sum()
    corr = sl.subtract_uniform(meas, v / (1 + s.size * v))
    assert np.allclose(corr, s, atol=1e-12)


def test_inverse_gaussian_filter_recovers_a_compact_scene():
    # A compact object far from the edges: (almost) nothing scatters off the sensor, so
    # the unregularised inverse of delta + w G is exact.
    s = np.zeros((H, W), complex)
    s[20:28, 25:37] = phasor_of(np.ones((8, 12)), np.full((8, 12), 1.3))
    k = 0.2 * gauss(1.5, 1.0)
    k[H - 1, W - 1] += 1
    meas = fftconvolve(s, k, mode="full")[H - 1:2 * H - 1, W - 1:2 * W - 1]
    corr = sl.inverse_filter_gaussian(meas, 1.5, 1.0, 0.2, 0.0)
    assert np.abs(corr - s).max() < 1e-9
    # Regularisation trades exactness for stability: with mu > 0 it no longer inverts.
    assert np.abs(sl.inverse_filter_gaussian(meas, 1.5, 1.0, 0.2, 0.5) - s).max() > 1e-3


def _plane_gauss(sigma: float) -> np.ndarray:
    """Unit integral over the infinite plane (what a lobe weight means), on the full grid."""
    y = np.arange(-(H - 1), H)[:, None]
    x = np.arange(-(W - 1), W)[None, :]
    return (norm.cdf(y + 0.5, scale=sigma) - norm.cdf(y - 0.5, scale=sigma)) * \
        (norm.cdf(x + 0.5, scale=sigma) - norm.cdf(x - 0.5, scale=sigma))


def test_deconvolve_inverts_a_known_psf():
    psf = StrayLightPSF(gaussians=(GaussianLobe(0.04, 2.3, 2.3), GaussianLobe(0.05, 13.0, 13.0)), veil=0.03,
                        ghosts=(Ghost(GHOST),), conserve=False)
    s, _, _ = scene(0.05, card=True)
    k = 0.04 * _plane_gauss(2.3) + 0.05 * _plane_gauss(13.0) + 0.03 * np.ones((2 * H - 1, 2 * W - 1)) / (H * W)
    meas = s + fftconvolve(s, k, mode="full")[H - 1:2 * H - 1, W - 1:2 * W - 1] + GHOST * s[::-1, ::-1]
    op = StrayLightOperator(psf, (H, W))  # ghost through the image centre
    assert np.allclose(op.apply(s), meas, atol=1e-12 * np.abs(s).max())
    corr = sl.deconvolve(meas, psf, iterations=60, tol=1e-14)
    assert np.abs(corr - s).max() < 1e-10 * np.abs(s).max()


def test_deconvolve_refuses_a_psf_that_scatters_everything():
    psf = StrayLightPSF(gaussians=(GaussianLobe(1.2, 3, 3),), conserve=False)
    with pytest.raises(TofhilError, match="< 1"):
        sl.deconvolve(np.ones((H, W), complex), psf)


def _square_error(s_corr: np.ndarray, dist: np.ndarray, sq: np.ndarray) -> float:
    return float(np.mean(np.abs(distance_of(s_corr[sq]) - dist[sq])))


@pytest.mark.parametrize("target_only,conserve", [(False, False), (False, True), (True, False), (True, True)])
def test_calibrated_psf_from_one_scene_fixes_dark_squares_of_every_reflectance(target_only, conserve):
    # Calibrate on a card in front of a far/black background (no wall) ...
    cal_true, _, _ = scene(None, card=True, wall=False)
    cal_meas = apply_optics(cal_true, conserve)
    if target_only:
        psf = pc.calibrate_psf_target(cal_meas, cx=(W - 1) / 2, cy=(H - 1) / 2)
    else:
        psf = pc.calibrate_psf(cal_meas, cal_true, cx=(W - 1) / 2, cy=(H - 1) / 2)
    # Largest on-sensor column sum of the true operator (light leaving the sensor is lost).
    w_true = fftconvolve(np.ones((H, W)), TRUE_KERNEL[::-1, ::-1], mode="full")[H - 1:2 * H - 1, W - 1:2 * W - 1].max() + GHOST
    if target_only:  # h is found relative to the measured target: h / direct
        w_true /= (1.0 - W_SCATTERED) if conserve else 1.0
    else:
        assert psf.keep == pytest.approx(1.0 - W_SCATTERED if conserve else 1.0, abs=0.005)
    assert psf.info["scattered_fraction"] == pytest.approx(w_true, rel=0.05)
    # ... and correct wall + dark square + card scenes it never saw.
    for rho in (0.5, 0.2, 0.05, 0.01):
        s, dist, sq = scene(rho, card=True)
        meas = apply_optics(s, conserve)
        before = _square_error(meas, dist, sq)
        after = _square_error(sl.deconvolve(meas, psf), dist, sq)
        assert before > 0.005, "the stray light must cause a visible error for the test to mean anything"
        assert after <= 0.1 * before, (rho, before, after)


def test_psf_file_roundtrip_and_bad_files(tmp_path):
    cal_true, _, _ = scene(None, card=True, wall=False)
    psf = pc.calibrate_psf(apply_optics(cal_true), cal_true, cx=(W - 1) / 2, cy=(H - 1) / 2)
    p = tmp_path / "psf.json"
    assert psf.save(p) == p
    back = sl.load_psf(p)
    s, _, _ = scene(0.1, card=True)
    assert back == psf  # every physical field survives the file
    assert np.allclose(StrayLightOperator(back, (H, W)).apply(s), StrayLightOperator(psf, (H, W)).apply(s))
    assert back.info["basis"] == psf.info["basis"]
    with pytest.raises(TofhilError, match="refusing to overwrite"):
        psf.save(p)
    bad = tmp_path / "bad.json"
    bad.write_text('{"format": "something else"}')
    with pytest.raises(InputFileError, match="format"):
        sl.load_psf(bad)
    old = tmp_path / "old.npz"
    np.savez(old, kernel=np.ones((3, 3)), format="tofhil.straylight_psf.v1")
    with pytest.raises(InputFileError, match="older tofhil"):
        sl.load_psf(old)
    with pytest.raises(InputFileError, match="no such file"):
        sl.load_psf(tmp_path / "missing.json")


def test_correct_raw_resynthesises_taps_with_the_corrected_signal_and_the_same_offset():
    from tofhil.camera import CameraModel
    from tofhil.demod import equally_spaced_phases, offset, phasor, taps_from_signal
    from tofhil.eval.corrections import correct_raw
    from tofhil.frames import RawFrame

    cam = CameraModel.from_fov(W, H, 60.0)
    theta = equally_spaced_phases(4)
    s, dist, sq = scene(0.05, card=True)
    meas = s + 3e-5 * s.sum()  # a uniform veil
    b = np.full((1, H, W), 40.0)
    raw = RawFrame(taps=taps_from_signal(np.abs(meas)[None], np.angle(meas)[None], b, theta),
                   freq_hz=[F_HZ], theta_rad=theta, integration_time_s=1e-3, camera=cam)
    w = 3e-5 / (1 + s.size * 3e-5)
    out, depth = correct_raw(raw, "uniform", {"w": w})
    s_out = phasor(out.taps.astype(np.float64), theta)[0]
    assert np.allclose(s_out, s, atol=1e-4)  # float32 taps
    assert np.allclose(offset(out.taps), 40.0, atol=1e-4)
    assert np.abs(depth.radial_m[sq] - dist[sq]).max() < 1e-3
