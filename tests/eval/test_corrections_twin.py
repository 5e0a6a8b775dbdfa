"""The twin correction and corrections that know their limits, against closed forms.

The forward models here are written out independently of the code under test: the
stray light of a Gaussian lobe as a dense matrix of pixel-integrated Gaussians (erf), the
taps of a two-path pixel from ``c_k = B + sum_j A_j cos(phi_j - theta_k)``.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.special import erf

from tofhil import C_M_PER_S
from tofhil.camera import CameraModel
from tofhil.eval.corrections import METHODS, correct_raw, parse_method_spec
from tofhil.eval.corrections.context import (FLAG_MULTIPATH, FLAG_RESTORED, FLAG_STRAY_LIGHT, FLAG_UNTRUSTED,
                                             CorrectionContext)
from tofhil.eval.corrections.twin import TwinPrediction
from tofhil.depth import depth_from_raw
from tofhil.errors import TofhilError
from tofhil.frames import RawFrame
from tofhil.sim.straylight import StrayLightPSF

H, W = 30, 40
WEIGHT, SIGMA = 0.06, 2.5
THETA = np.deg2rad([0.0, 90.0, 180.0, 270.0])
FREQ = 20e6


def _camera() -> CameraModel:
    return CameraModel(width=W, height=H, fx=40.0, fy=40.0, cx=(W - 1) / 2, cy=(H - 1) / 2)


def _ctx(saturated: np.ndarray | None = None, frames: int = 1) -> CorrectionContext:
    return CorrectionContext(_camera(), np.array([FREQ]), THETA, 1e-3, None, "<test>", saturated, frames)


def _stray_matrix() -> np.ndarray:
    """``M[p, q]``: the light of pixel q landing on pixel p, (1 - w) delta + w G (energy kept
    on the sensor only where G lands on it), G the pixel-integrated Gaussian."""
    def g1(d: np.ndarray) -> np.ndarray:
        s = SIGMA * math.sqrt(2.0)
        return 0.5 * (erf((d + 0.5) / s) - erf((d - 0.5) / s))

    y, x = np.divmod(np.arange(H * W), W)
    m = WEIGHT * g1(x[:, None] - x[None, :]) * g1(y[:, None] - y[None, :])
    return m + (1.0 - WEIGHT) * np.eye(H * W)


def _scene() -> tuple[np.ndarray, tuple[int, int]]:
    """A dim background of varied phase and one bright source pixel, ``S[1, H, W]``."""
    rng = np.random.default_rng(3)
    s = (20 + 5 * rng.random((H, W))) * np.exp(1j * rng.uniform(0.5, 1.5, (H, W)))
    src = (12, 15)
    s[src] = 3.0e4 * np.exp(0.2j)  # a card near the lens: 1000 x the background
    return s[None], src


def _psf() -> StrayLightPSF:
    return StrayLightPSF.from_params({"weight": WEIGHT, "sigma_px": SIGMA})


def test_bright_source_with_known_psf_is_corrected_exactly() -> None:
    s_true, _ = _scene()
    meas = (_stray_matrix() @ s_true.reshape(-1)).reshape(s_true.shape)
    ctx = _ctx()
    out = METHODS["psf"].func(meas, ctx, psf=_psf(), iterations=60)
    np.testing.assert_allclose(out, s_true, rtol=0, atol=1e-6 * np.abs(s_true).max())
    # the stray light it removed was far above the background: the correction matters
    assert np.abs(meas - s_true).max() > 10 * np.abs(s_true[0, 0, 0])
    assert ctx.flags is None or not ctx.flags.any()


def test_saturated_source_restored_from_the_twin_is_corrected_exactly() -> None:
    s_true, src = _scene()
    meas = (_stray_matrix() @ s_true.reshape(-1)).reshape(s_true.shape)
    clipped = meas.copy()
    clipped[0][src] *= 0.2  # clipped taps: the source's signal reads far too small
    sat = np.zeros((H, W), bool)
    sat[src] = True
    # the twin knows the scene: its prediction is the unclipped measurement
    twin = TwinPrediction(full=meas, no_stray=s_true, direct=s_true, ideal=s_true, noise=np.ones(meas.shape),
                          off=("stray_light",), off_all=("stray_light",), scale_reason=None, scene="<closed form>")
    ctx = _ctx(sat)
    out = METHODS["psf"].func(clipped, ctx, psf=_psf(), iterations=60, twin=twin)
    good = ~sat
    np.testing.assert_allclose(out[0][good], s_true[0][good], rtol=0, atol=1e-6 * np.abs(s_true).max())
    assert ctx.flags[src] & FLAG_RESTORED and not (ctx.flags & FLAG_UNTRUSTED).any()

    # Without the twin the same correction is wrong near the source, and says where.
    ctx2 = _ctx(sat)
    wrong = METHODS["psf"].func(clipped, ctx2, psf=_psf(), iterations=60)
    err = np.abs(wrong[0] - s_true[0]) / np.abs(s_true[0])
    untrusted = (ctx2.flags & FLAG_UNTRUSTED).astype(bool)
    assert untrusted.any() and not untrusted[src]
    # every pixel marked is one the correction got wrong by more than 1 % of its signal ...
    assert err[untrusted].min() > 0.01
    # ... and the pixels it left unmarked are (nearly all) right to within a few per cent
    assert np.percentile(err[good & ~untrusted], 99) < 0.03
    assert any("clipped" in n for n in ctx2.notes)


@pytest.mark.parametrize("method,params", [("uniform", {"w": 1e-4}),
                                           ("gaussian-inverse", {"sigma_h": 2.5, "sigma_v": 2.5, "w": 0.06, "mu": 0.0})])
def test_thesis_methods_mark_what_clipped_sources_leave_wrong(method: str, params: dict) -> None:
    s_true, src = _scene()
    meas = (_stray_matrix() @ s_true.reshape(-1)).reshape(s_true.shape)
    meas[0][src] *= 0.2
    sat = np.zeros((H, W), bool)
    sat[src] = True
    ctx = _ctx(sat)
    METHODS[method].func(meas, ctx, **params)
    assert (ctx.flags & FLAG_UNTRUSTED).any()
    assert ctx.info["clipped_sources"]["pixels"] == 1


def _taps(phasors: list[tuple[float, float]], b: float = 500.0) -> np.ndarray:
    """Taps of one pixel lit by paths (amplitude, optical path L): c_k = B + sum A cos(phi - theta_k)."""
    c = np.full(THETA.shape, b)
    for a, length in phasors:
        c = c + a * np.cos(2 * np.pi * FREQ * length / C_M_PER_S - THETA)
    return c


def test_two_path_pixel_is_corrected_to_its_direct_path() -> None:
    d1, a1 = 1.20, 300.0   # direct return: radial distance 1.2 m
    l2, a2 = 3.10, 120.0   # a second path, 3.1 m long (a bounce off a side wall)
    taps = np.empty((1, 4, H, W))
    taps[0] = _taps([(a1, 2 * d1), (a2, l2)])[:, None, None]
    raw = RawFrame(taps=taps.astype(np.float32), freq_hz=np.array([FREQ]), theta_rad=THETA, integration_time_s=1e-3,
                   camera=_camera(), meta={})
    phase = lambda L: np.exp(2j * np.pi * FREQ * L / C_M_PER_S)  # noqa: E731
    direct = np.full((1, H, W), a1 * phase(2 * d1))
    full = direct + a2 * phase(l2)
    twin = TwinPrediction(full=full, no_stray=full, direct=direct, ideal=direct, noise=np.ones(full.shape),
                          off=("multipath",), off_all=("multipath",), scale_reason=None, scene="<closed form>")
    ctx = _ctx()
    before = depth_from_raw(raw)
    _, depth = correct_raw(raw, "twin", {"scene": twin}, context=ctx)
    assert abs(float(np.median(before.radial_m)) - d1) > 0.05  # the second path moves the pixel a lot
    np.testing.assert_allclose(depth.radial_m, d1, atol=2e-5)  # float32 taps
    assert (ctx.flags & FLAG_MULTIPATH).all() and not (ctx.flags & FLAG_STRAY_LIGHT).any()


def test_twin_method_spec_is_checked() -> None:
    assert parse_method_spec("twin:scene=x.yaml,remove=all") == ("twin", {"scene": "x.yaml", "remove": "all"})
    with pytest.raises(TofhilError, match="twin:remove"):
        parse_method_spec("twin:scene=x.yaml,remove=some")
    with pytest.raises(TofhilError, match="twin:scene"):
        parse_method_spec("twin")


def test_corner_multipath_removed_against_an_independent_render() -> None:
    """The corner (2 bounces): the twin correction, with the twin's multipath from an
    independent Monte Carlo render (another seed), removes >= 90 % of the multipath excess
    against the same corner rendered direct-only (bounces 0, no twin code involved)."""
    from tofhil.eval.corrections import context_for_frame
    from tofhil.eval.corrections.twin import predict
    from tofhil.sim.scene import load_scene
    from tofhil.sim.twin import Twin

    cam = {"width": 80, "height": 60, "fx": 58.333, "fy": 58.333, "cx": 39.5, "cy": 29.5, "pixel_pitch_m": 48.0e-6}
    def corner(bounces: int, seed: int):  # noqa: E306
        return load_scene("corner", {"camera": cam, "render": {"samples_per_pixel": 16, "bounces": bounces,
                                                               "seed": seed}})
    capture, twin_scene = Twin(corner(2, 1)), corner(2, 2)
    ref = depth_from_raw(next(iter(Twin(corner(0, 3)).frames(frames=1, noise=False))))
    cfg = capture.config.to_dict()
    before, after = [], []
    for f in capture.frames(frames=2, seed=5):
        ctx = context_for_frame(f, sensor_config=cfg)
        _, d = correct_raw(f, "twin", {"scene": twin_scene}, context=ctx)
        b = depth_from_raw(f)
        m = ref.valid & b.valid & d.valid
        before.append(b.radial_m[m] - ref.radial_m[m])
        after.append(d.radial_m[m] - ref.radial_m[m])
    excess_b, excess_a = np.median(np.concatenate(before)), np.median(np.concatenate(after))
    assert excess_b > 0.05  # light of the bounces arrives late: the corner reads far
    assert abs(excess_a) <= 0.1 * excess_b
    assert (ctx.flags & FLAG_MULTIPATH).mean() > 0.5 and ctx.info["twin"]["effects_removed"] == ["multipath"]
    # the capture records the sensor that made it, the twin's scene is that sensor: scale 1, not fitted
    assert ctx.info["twin"]["signal_scale"] == 1.0 and not ctx.info["twin"]["signal_scale_fit"]["fitted"]
    by_bounce = ctx.info["twin"]["multipath_share_by_bounce"]  # the light removed, by bounce (2 rendered)
    assert len(by_bounce) == 2 and by_bounce[0] > by_bounce[1] > 0 and sum(by_bounce) < 1
    # the twin's render is independent of the capture's: its multipath differs sample by sample
    p_twin = predict(twin_scene, ctx).indirect
    p_cap = predict(corner(2, 1), ctx).indirect
    assert np.abs(p_twin - p_cap).max() > 1e-3 * np.abs(p_cap).max()


def test_twin_signal_scale_is_the_diagnosis_one_fitted_on_the_fit_frames() -> None:
    """The device's scale against the twin's: the diagnosis's SignalScale, fitted on the fit
    frames' signal (``ctx.fit_signal``) when the caller split the frames, not on the signal
    corrected; 1 and not fitted when the session states the sensor that made it."""
    from tofhil.eval.diagnose.signal_scale import SignalScale

    rng = np.random.default_rng(8)
    direct = (50 + 10 * rng.random((1, H, W))) * np.exp(1j * rng.uniform(0.2, 1.2, (1, H, W)))
    stray = 0.2 * direct.mean() * np.ones((1, H, W))
    full = direct + stray
    twin = TwinPrediction(full=full, no_stray=direct, direct=direct, ideal=direct, noise=np.ones(full.shape),
                          off=("stray_light",), off_all=("stray_light",),
                          scale_reason="the session records no sensor configuration", scene="<closed form>")
    g_fit, g_scored = 1.25, 0.8  # the device's gain as the fit frames and as the scored frames show it
    ctx = _ctx()
    ctx.fit_signal = g_fit * full
    out = METHODS["twin"].func(g_scored * full, ctx, scene=twin)
    info = ctx.info["twin"]
    assert info["signal_scale"] == pytest.approx(g_fit) and info["signal_scale_fit"]["fitted"]
    assert "held out" in info["signal_scale_fit"]["fitted_on"]
    # the scale of the fit frames, not the scored frames', is what was removed
    np.testing.assert_allclose(out, g_scored * full - g_fit * stray, atol=1e-9)
    # without fit frames the scale is in-sample, and says so
    ctx1 = _ctx()
    out1 = METHODS["twin"].func(g_scored * full, ctx1, scene=twin)
    np.testing.assert_allclose(out1, g_scored * direct, atol=1e-9)
    assert "in-sample" in ctx1.info["twin"]["signal_scale_fit"]["fitted_on"]
    assert any("fitted as the median" in n and "in-sample" in n for n in ctx1.notes)
    # a session in the twin's own units: 1, not fitted, whatever the data say
    recorded = TwinPrediction(**{**twin.__dict__, "scale_reason": None})
    ctx2 = _ctx()
    ctx2.fit_signal = g_fit * full
    METHODS["twin"].func(g_scored * full, ctx2, scene=recorded)
    assert ctx2.info["twin"]["signal_scale"] == 1.0
    assert ctx2.info["twin"]["signal_scale_fit"] == {**SignalScale().to_json(), "fitted_on": None,
                                                     "text": SignalScale().text()}
