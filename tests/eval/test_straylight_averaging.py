"""Averaging frames in the complex domain (issue 17): the mean, its noise, the corrections on
it, compare's per-region noise floor and its tap calibration on both sides.

Noise is checked against the closed form: ``K = 4`` taps with independent noise ``sigma``
give ``Re S = (c0 - c2) / 2``, so each component of ``S`` has variance ``sigma^2 / 2`` and the
phase of the mean of ``N`` frames has ``sigma_phi = sigma / (A sqrt(2 N))``.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from tests import straylight_synthetic as syn
from tofhil import C_M_PER_S
from tests.cli_in_process import run_cli as run
from tofhil.demod import phasor
from tofhil.eval.corrections import correct_mean, correct_raw
from tofhil.eval.compare import recorded_tap_calibration, tap_calibration_plan
from tofhil.eval.corrections.averaging import mean_signal, session_mean_signal
from tofhil.eval.calibration.taps import TapCalibration
from tofhil.frames import DepthFrame
from tofhil.session import SessionWriter, open_session

SQUARE_ROI = f"{syn.SQUARE[1].start},{syn.SQUARE[0].start},{syn.SQUARE[1].stop},{syn.SQUARE[0].stop}"
SQUARE_REGION = "roi_" + SQUARE_ROI.replace(",", "_")


@pytest.fixture(scope="module")
def noisy(tmp_path_factory):
    """A wall with a 5 % square, no stray light, 24 frames with tap noise 0.01 (offset 50)."""
    d = tmp_path_factory.mktemp("avg")
    s, _ = syn.scene_signal(square_rho=0.05, card=False)
    return d, syn.write_session(d / "noisy.h5", s, n_frames=24, noise=0.01, offset=50.0, seed=3), s


def test_mean_is_the_phasor_of_the_mean_taps_and_its_noise_is_the_closed_form(noisy):
    _, path, s = noisy
    with open_session(path) as ses:
        ms = session_mean_signal(ses, 24)
        taps = np.mean([ses.raw_frame(i).taps.astype(np.float64) for i in range(24)], axis=0)
        np.testing.assert_allclose(ms.s, phasor(taps, ses.theta_rad), rtol=0, atol=1e-12)
        noise = ms.distance_noise_m()
    sigma_phi = 0.01 / (np.abs(s) * np.sqrt(2 * 24))
    expected = C_M_PER_S * sigma_phi / (4 * np.pi * syn.FREQ[0])
    # The per-pixel estimate from 24 frames scatters by ~1/sqrt(2 * 23); its RMS over a region
    # matches the closed form to a few per cent.
    for region in (syn.SQUARE, (slice(0, 20), slice(0, 40))):
        got = np.sqrt(np.mean(noise[region] ** 2))
        assert got == pytest.approx(np.sqrt(np.mean(expected[region] ** 2)), rel=0.05)


def test_one_held_out_frame_gets_its_noise_from_the_other_frames_scatter(noisy):
    """A mean of one frame has no scatter of its own; the other (fit) frames of the session,
    each about their own mean, give the sensor's per-frame noise: the closed form for N = 1."""
    _, path, s = noisy
    with open_session(path) as ses:
        alone = mean_signal(lambda i: ses.raw_frame(5), 1)
        pooled = mean_signal(lambda i: ses.raw_frame(5), 1, others=(lambda i: ses.raw_frame(2 * i), 12))
        np.testing.assert_array_equal(pooled.s, alone.s)  # the mean is the scored frame's alone
    assert np.isnan(alone.distance_noise_m()).all() and pooled.dof == 11
    # per frame, each component of S has variance sigma^2 / 2 (the square's and the wall's alike)
    for region in (syn.SQUARE, (slice(0, 20), slice(0, 40))):
        assert np.sqrt(np.mean(pooled.var_perp[0][region])) == pytest.approx(0.01 / np.sqrt(2), rel=0.05)
    # the distance noise of the one frame, where its amplitude is well above the noise (the
    # wall: a single frame of the 5 % square is too dim for the first-order phase noise)
    wall = (slice(0, 20), slice(0, 40))
    expected = C_M_PER_S * 0.01 / (np.abs(s[wall]) * np.sqrt(2)) / (4 * np.pi * syn.FREQ[0])
    got = pooled.distance_noise_m()[wall]
    assert np.sqrt(np.mean(got ** 2)) == pytest.approx(np.sqrt(np.mean(expected ** 2)), rel=0.05)


def test_complex_correction_of_the_mean_equals_the_mean_of_corrected_frames(noisy, tmp_path):
    # The corrections are linear in S: correcting the mean = averaging the corrected frames.
    _, path, _ = noisy
    with open_session(path) as ses:
        raw_mean, _ = correct_mean(ses, "uniform", {"w": 1e-4}, n=6)
        per_frame = [phasor(correct_raw(ses.raw_frame(i), "uniform", {"w": 1e-4})[0].taps.astype(np.float64),
                            ses.theta_rad) for i in range(6)]
        ms = mean_signal(ses.raw_frame, 6, correct=lambda x: x - 1e-4 * x.sum(axis=(-2, -1), keepdims=True))
    np.testing.assert_allclose(phasor(raw_mean.taps.astype(np.float64), raw_mean.theta_rad), np.mean(per_frame, 0),
                               rtol=0, atol=2e-5)  # float32 taps of the written frames
    np.testing.assert_allclose(ms.s, np.mean(per_frame, 0), rtol=0, atol=2e-5)


def test_30_noisy_frames_through_compare_reach_what_the_noise_floor_allows(tmp_path, capsys):
    """Issue 17: a lens of another form than the model (tests/straylight_lenses.py), the
    1 % square, 30 frames with tap noise; one PSF calibrated on a card over black. The
    correction must remove >= 90 % of what the noise floor allows: 1 - RMSE_after / RMSE_before
    >= 0.9 (1 - floor_after / RMSE_before)."""
    from tests import straylight_lenses as L
    from tofhil.eval.corrections import psf_calibration as pc

    lens = L.lenses()["gauss_other"]
    psf = pc.calibrate_psf_target(L.calibration_capture(lens), L.CX, L.CY, rounds=2)
    psf.save(tmp_path / "lens.json")
    s, _ = syn.scene_signal(square_rho=0.01, card=True)
    sigma, n = 0.0005, 30
    a = syn.write_session(tmp_path / "a.h5", lens(s), n_frames=n, noise=sigma, offset=50.0, seed=1)
    b = syn.write_session(tmp_path / "b.h5", s, n_frames=1, offset=50.0)
    out = tmp_path / "r"
    assert run("compare", a, b, "--out", out, "--frames", n, "--roi", SQUARE_ROI, "--no-objects",
               "--min-relative-amplitude", 0, "--correct", f"psf:psf={tmp_path / 'lens.json'}") == 0
    console = " ".join(capsys.readouterr().out.split())  # the console wraps long lines
    m = json.loads((out / "metrics.json").read_text())
    before = m["variants"]["measured"]["regions"][SQUARE_REGION]
    after = [v for k, v in m["variants"].items() if k != "measured"][0]["regions"][SQUARE_REGION]
    # Scored on held-out frames: the odd 15 of the 30 (the even ones are the fit's).
    k = n // 2
    assert m["frames"]["a"] == k and m["heldout"]["scored_frames"] == list(range(1, n, 2))
    # The floor of the measured mean (of k frames) is the closed form at the measured amplitude.
    sigma_phi = sigma / (np.abs(lens(s)[syn.SQUARE]) * np.sqrt(2 * k))
    assert before["noise_floor_m"] == pytest.approx(
        np.sqrt(np.mean((C_M_PER_S * sigma_phi / (4 * np.pi * syn.FREQ[0])) ** 2)), rel=0.05)
    e0, e1, floor = before["depth_residual_m"]["rmse"], after["depth_residual_m"]["rmse"], after["noise_floor_m"]
    assert e0 > 10 * floor  # the stray light's error is real, far above the noise
    assert 1 - e1 / e0 >= 0.9 * (1 - floor / e0), (e0, e1, floor)
    assert SQUARE_REGION in console and "depth RMSE*" in console and "noise floor" in console
    assert "noise floor" in (out / "report.html").read_text()


@pytest.fixture(scope="module")
def flat_cal(tmp_path_factory):
    """A tap calibration with 3 % tap gain errors, and a twin and a capture that carry them."""
    d = tmp_path_factory.mktemp("flat")
    rng = np.random.default_rng(5)
    gain = 1 + 0.03 * rng.standard_normal((1, 4, syn.H, syn.W))
    cal = TapCalibration(np.zeros_like(gain), gain)
    cal.save(d / "cal.npz")
    return d, cal


def _write_with_gain(path, s, gain, n_frames=1):
    from tofhil.demod import taps_from_signal
    from tofhil.frames import RawFrame

    with SessionWriter(path, syn.CAMERA, device={"model": "synthetic"}) as w:
        for i in range(n_frames):
            taps = taps_from_signal(np.abs(s)[None], np.angle(s)[None], np.full((1, syn.H, syn.W), 50.0), syn.THETA)
            w.append(RawFrame(taps=(taps * gain).astype(np.float32), freq_hz=syn.FREQ, theta_rad=syn.THETA,
                              integration_time_s=1e-3, camera=syn.CAMERA, sequence=i))
    return path


def test_compare_applies_one_tap_calibration_to_both_sides_or_refuses(flat_cal, tmp_path, capsys):
    d, cal = flat_cal
    s, _ = syn.scene_signal(square_rho=0.05, card=True)
    a = _write_with_gain(tmp_path / "a.h5", s, cal.gain)
    b = _write_with_gain(tmp_path / "b.h5", s, cal.gain)  # the twin models the same fixed pattern
    # --flat on both sides: A and B become the same signal (the residual vanishes).
    assert run("compare", a, b, "--out", tmp_path / "r1", "--flat", d / "cal.npz", "--no-objects") == 0
    m = json.loads((tmp_path / "r1" / "metrics.json").read_text())
    assert m["tap_calibration"]["applied_here"] == {"A": True, "B": True}
    assert m["variants"]["measured"]["regions"]["all"]["depth_residual_m"]["rmse"] < 1e-5
    # A corrected with the calibration (recorded in its header): compare gives B the same one.
    corrected = tmp_path / "a_taps.h5"
    assert run("correct", a, "--method", f"taps:flat={d / 'cal.npz'}", "--out", corrected) == 0
    with open_session(corrected) as sc, open_session(b) as sb:
        assert recorded_tap_calibration(sc) == str((d / "cal.npz").resolve())
        plan = tap_calibration_plan({"A": (sc, corrected), "B": (sb, b)}, recorded_tap_calibration(sc), "A")
        assert plan["A"] is None and np.array_equal(plan["B"].gain, cal.gain)
        # The same pixels through the plan: calibrated A (float32 taps) equals calibrated B.
        sa_mean = session_mean_signal(sc, 1, flat=plan["A"]).s
        np.testing.assert_allclose(session_mean_signal(sb, 1, flat=plan["B"]).s, sa_mean, atol=1e-4)
    capsys.readouterr()
    # ... or refuses when B cannot get it (depth only), naming B's file; nothing written.
    depth_only = tmp_path / "depth.h5"
    with SessionWriter(depth_only, syn.CAMERA) as w:
        w.append(None, DepthFrame(distance_m=syn.wall_distance(), kind="radial", camera=syn.CAMERA,
                                  amplitude=np.ones(syn.CAMERA.shape)))
    for args in ((corrected, depth_only), (a, depth_only, "--flat", d / "cal.npz")):
        assert run("compare", *args, "--out", tmp_path / "r3", "--no-objects") == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and str(depth_only) in err and "tap calibration" in err
        assert not (tmp_path / "r3").exists()
    # A correction's own flat= would calibrate A only: refused, pointing at --flat.
    assert run("compare", a, b, "--out", tmp_path / "r4", "--correct", f"uniform:w=1e-5,flat={d / 'cal.npz'}") == 2
    assert "--flat" in capsys.readouterr().err
    assert not (tmp_path / "r4").exists()


def test_correct_average_writes_the_corrected_mean(noisy, tmp_path):
    _, path, _ = noisy
    out = tmp_path / "mean.h5"
    assert run("correct", path, "--method", "uniform:w=1e-4", "--average", "--out", out) == 0
    with open_session(out) as o, open_session(path) as ses:
        assert o.n_frames == 1
        ref, _ = correct_mean(ses, "uniform", {"w": 1e-4})
        np.testing.assert_allclose(o.raw_frame(0).taps, ref.taps, rtol=1e-6)
