"""Direct ToF (pulsed emitter, SPAD histogram sensor) against closed forms: round-trip time,
Poisson first-photon pile-up and Coates' inverse, the low-flux limit, photon conservation,
two surfaces as two peaks."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tofhil import C_M_PER_S
from tofhil.camera import CameraModel
from tofhil.errors import TofhilError
from tofhil.sim.direct_tof import (DirectToFConfig, coates_correction, expected_photons, find_peaks,
                                   record_probabilities, render_direct, render_edges_m, sample_histogram,
                                   signal_photons)
from tofhil.sim.scene import scene_from_dict
from tofhil.sim.sensor import H_PLANCK


def _scene(objects: list[dict], direct: dict, power_w: float = 0.3) -> object:
    return scene_from_dict({
        "camera": {"width": 5, "height": 5, "fx": 300.0, "fy": 300.0, "cx": 2.0, "cy": 2.0, "pixel_pitch_m": 24e-6,
                   "f_number": 1.2},
        "emitter": {"power_w": power_w, "profile": {"type": "cos_n", "n": 1.0}},
        "materials": {"white": {"reflectance": 0.8}},
        "objects": objects,
        "sensor": {"freq_hz": [20e6], "taps": 4},
        "direct_tof": direct,
    })


def _plane(z: float, size: float = 4.0, x: float = 0.0) -> dict:
    return {"name": f"plane{z}", "type": "plane", "size": [size, size], "material": "white",
            "pose": {"position": [x, 0.0, z]}}


DIRECT = {"pulse": {"shape": "gaussian", "fwhm_s": 0.3e-9}, "bin_width_s": 100e-12, "bins": 120, "t0_s": 5e-9,
          "jitter_s": 30e-12, "pulse_energy_j": 1e-9, "repetition_hz": 1e6, "cycles_per_frame": 10_000,
          "dark_count_rate_hz": 0.0, "dead_time_s": 20e-9, "oversample": 16}


def _gaussian_lambda(total: float, centre_bin: float, sigma_bins: float, bins: int, bg: float = 0.0) -> np.ndarray:
    i = np.arange(bins)
    g = np.exp(-0.5 * ((i + 0.5 - centre_bin) / sigma_bins) ** 2)
    return total * g / g.sum() + bg


def test_plane_peak_at_the_round_trip_time() -> None:
    """A plane 1.1 m away: every pixel's peak at 2 r / c (emitter at the camera), within 1/20 bin."""
    d = 1.1
    scene = _scene([_plane(d)], DIRECT)
    res = render_direct(scene, samples_per_pixel=1, bounces=0, subpixel=False)
    cfg = scene.direct_tof
    lam = expected_photons(scene, res, cfg)
    N = cfg.cycles_per_frame
    peaks = find_peaks(cfg, *coates_correction(N * record_probabilities(lam, cfg.dead_bins), N, cfg.dead_bins))
    expect_t = 2 * res.radial_m / C_M_PER_S
    assert res.radial_m[2, 2] == pytest.approx(d, rel=1e-9)
    err_bins = (peaks.time_s[0] - expect_t) / cfg.bin_width_s
    assert np.all(np.abs(err_bins) < 0.05), err_bins
    assert np.all(peaks.count == 1)                      # one surface: one peak


def test_low_flux_without_dead_time_is_the_transient_times_the_efficiency() -> None:
    """Summed over bins, the expected photons per cycle are PDE * E_p / (h c / lambda) times the
    rendered share of the emitter's power on the pixel; at low flux the record probability per
    bin equals the mean photons per bin."""
    scene = _scene([_plane(1.1)], dict(DIRECT, pulse_energy_j=1e-11))
    res = render_direct(scene, samples_per_pixel=1, bounces=0, subpixel=False)
    cfg = scene.direct_tof
    lam = signal_photons(cfg, res.transient, res.transient_edges_m, 0.3, scene.sensor.wavelength_m)
    photons = cfg.pde * 1e-11 / (H_PLANCK * C_M_PER_S / scene.sensor.wavelength_m)
    assert np.allclose(lam.sum(axis=0), photons * res.power_w / 0.3, rtol=1e-9)
    assert lam.max() < 1e-3                              # the low-flux regime
    P = record_probabilities(lam, cfg.dead_bins)
    assert np.allclose(P, lam, rtol=2e-3, atol=0)        # 1 - exp(-l) ~ l, pile-up ~ sum(l) << 1


def test_pileup_matches_the_first_photon_poisson_model_and_coates_recovers_the_shape() -> None:
    """High flux (3 photons per cycle), dead time longer than the histogram: the recorded
    histogram is exp(-sum_{j<i} l_j) (1 - exp(-l_i)) (computed here independently), its mean is
    early, and Coates' correction of sampled counts recovers l within its statistical error."""
    bins = 80
    lam = _gaussian_lambda(3.0, 40.0, 3.0, bins, bg=0.002)[:, None]
    before = np.concatenate([[0.0], np.cumsum(lam[:-1, 0])])
    closed = np.exp(-before) * (1 - np.exp(-lam[:, 0]))
    P = record_probabilities(lam, dead_bins=bins)[:, 0]
    assert np.allclose(P, closed, rtol=1e-12, atol=1e-15)
    t = np.arange(bins) + 0.5
    assert np.sum(t * P) / P.sum() < np.sum(t * lam[:, 0]) / lam.sum() - 1.0   # piled up: > 1 bin early
    N = 200_000
    counts = sample_histogram(np.repeat(lam, 16, axis=1), N, bins, np.random.default_rng(1))
    assert np.all(counts.sum(axis=0) <= N)               # one count per cycle at most
    lam_hat, var = coates_correction(counts, N, bins)
    z = (lam_hat - lam) / np.sqrt(var)
    signal = lam[:, 0] > 0.05                             # bins still armed often enough to measure
    assert abs(np.mean(z[signal])) < 0.15
    assert np.std(z[signal]) == pytest.approx(1.0, abs=0.15)
    # The uncorrected histogram's shape is wrong where the corrected one is right.
    uncorrected = counts.mean(axis=1) / N
    assert np.max(np.abs(uncorrected - lam[:, 0])) > 0.5 * lam.max()
    assert np.max(np.abs(lam_hat.mean(axis=1) - lam[:, 0])[signal]) < 0.1 * lam.max()


def test_shorter_dead_time_rearms_and_coates_inverts_it() -> None:
    """Dead time of 5 bins: the expectation follows P_i = (1 - sum_{i-5}^{i-1} P) (1 - e^-l_i),
    checked against a cycle-by-cycle simulation of a non-paralysable SPAD."""
    bins, d = 30, 5
    lam = _gaussian_lambda(2.0, 12.0, 2.0, bins, bg=0.05)
    rng = np.random.default_rng(7)
    cycles = 40_000
    photons = rng.random((cycles, bins)) < -np.expm1(-lam)          # a photon in the bin (or more)
    rec = np.zeros(bins)
    armed_at = np.zeros(cycles, dtype=np.int64)                      # first bin the SPAD is armed again
    for i in range(bins):
        hit = photons[:, i] & (armed_at <= i)
        rec[i] = hit.sum()
        armed_at[hit] = i + d
    P = record_probabilities(lam[:, None], d)[:, 0]
    assert np.allclose(rec / cycles, P, atol=4 * np.sqrt(P / cycles).max())
    lam_hat, _ = coates_correction(rec[:, None], cycles, d)
    assert np.allclose(lam_hat[:, 0], lam, atol=0.05)


def test_counts_conserve_the_detected_photons() -> None:
    """Dead time >= histogram: each cycle records its first photon or none, so the expected
    histogram sums to N (1 - exp(-sum l)) exactly and sampled sums scatter binomially around it."""
    bins = 60
    lam = _gaussian_lambda(0.7, 30.0, 2.0, bins, bg=0.001)[:, None]
    N = 5000
    total = lam.sum()
    expect = N * -math.expm1(-total)
    assert (N * record_probabilities(lam, bins)).sum() == pytest.approx(expect, rel=1e-12)
    sums = sample_histogram(np.repeat(lam, 400, axis=1), N, bins, np.random.default_rng(3)).sum(axis=0)
    p = -math.expm1(-total)
    assert np.mean(sums) == pytest.approx(expect, abs=4 * math.sqrt(N * p * (1 - p) / 400))
    assert np.var(sums) == pytest.approx(N * p * (1 - p), rel=0.2)


def test_two_surfaces_give_two_peaks_at_their_path_lengths() -> None:
    """A pixel that sees the edge of a near card (0.9 m) over a far wall (1.6 m) has two peaks,
    at 2 x 0.9 m and 2 x 1.6 m of path; its neighbours see one surface each."""
    direct = dict(DIRECT, bins=160, t0_s=4e-9, oversample=8)
    scene = _scene([_plane(1.6), {"name": "card", "type": "plane", "size": [1.0, 1.0], "material": "white",
                                  "pose": {"position": [-0.5, 0.0, 0.9]}}], direct)
    cam = CameraModel(width=3, height=1, fx=300.0, fy=300.0, cx=1.0, cy=0.0, pixel_pitch_m=24e-6)
    res = render_direct(scene, camera=cam, samples_per_pixel=64, bounces=0, subpixel=True, seed=2)
    cfg = scene.direct_tof
    lam = expected_photons(scene, res, cfg)
    N = cfg.cycles_per_frame
    peaks = find_peaks(cfg, *coates_correction(N * record_probabilities(lam, cfg.dead_bins), N, cfg.dead_bins))
    assert peaks.count[0].tolist() == [1, 2, 1]
    assert peaks.distance_m[0, 0, 0] == pytest.approx(0.9, abs=0.005)
    assert peaks.distance_m[0, 0, 2] == pytest.approx(1.6, abs=0.005)
    assert sorted(peaks.distance_m[:2, 0, 1]) == pytest.approx([0.9, 1.6], abs=0.01)


def test_render_edges_cover_the_histogram_and_the_pulse() -> None:
    cfg = DirectToFConfig.from_dict(DIRECT)
    e = render_edges_m(cfg) / C_M_PER_S
    assert e[0] <= cfg.t0_s - 3 * 0.3e-9 / 2.355 and e[-1] >= cfg.edges_s[-1]
    assert np.allclose(np.diff(e), cfg.bin_width_s / cfg.oversample)


@pytest.mark.parametrize("block, field", [
    ({"bins": 1}, "direct_tof.bins"),
    ({"bin_width_s": -1e-12}, "direct_tof.bin_width_s"),
    ({"pulse": {"shape": "square"}}, "direct_tof.pulse.shape"),
    ({"pulse": {"shape": "table", "times_s": [0, 1e-9], "values": [1]}}, "direct_tof.pulse.values"),
    ({"repetition_hz": 1e9}, "direct_tof.repetition_hz"),
    ({"bin_widht_s": 1e-10}, "direct_tof.bin_widht_s"),
])
def test_bad_blocks_name_their_field(block: dict, field: str) -> None:
    with pytest.raises(TofhilError) as e:
        _scene([_plane(1.0)], block)
    assert e.value.field == field
