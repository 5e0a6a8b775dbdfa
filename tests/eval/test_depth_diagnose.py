"""Diagnosis of depth (+ amplitude) sessions: the phasor A exp(i 4 pi f d / c) stands in for S.

Synthetic: a session rendered by the twin with a hidden effect is diagnosed twice, from its
raw taps and from its depth and amplitude alone (the raw taps dropped, as a camera that
delivers depth would). At one modulation frequency the phasor of the depth is the measured
S up to noise, so the depth-only diagnosis must name the same cause with parameters within
the same tolerances as the raw-tap one (tests/eval/test_diagnose.py's ``CASES``), with
several frames (noise from their scatter) and with one frame (noise from the spatial
scatter, a pixel-block split).

Also: the depth split's noise estimate against a known noise; offset-only effects are no
candidates; the ambiguity post-step.
"""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

from tofhil.camera import CameraModel
from tofhil.eval.diagnose.depth_heldout import (OFFSET_ONLY_EFFECTS, depth_phasor, observable_candidates,
                                       spatial_noise_variance, split_depth_session)
from tofhil.eval.diagnose.run import diagnose
from tofhil.frames import DepthFrame
from tofhil.session import SessionWriter, open_session
from tofhil.sim.pipeline import simulate_session
from tofhil.sim.scene import load_scene
from tests.eval.test_diagnose import CASES, _check_params


@pytest.fixture(scope="module")
def bench_scene():
    scene = load_scene("bench_demo")
    return dataclasses.replace(scene, camera=scene.camera.scaled(0.5))


def depth_only_copy(src, dst, frames: int | None = None):
    """The session without its raw taps: depth, amplitude and validity only."""
    with open_session(src) as s:
        n = s.n_frames if frames is None else frames
        with SessionWriter(dst, s.camera, device={"model": "depth-only copy"},
                           sensor_config=s.sensor_config) as w:
            for i in range(n):
                w.append(depth=s.depth_frame(i))
    return dst


@pytest.mark.slow
@pytest.mark.parametrize("effect,frames", [("range_offset", 4), ("wiggling", 4), ("range_offset", 1)])
def test_depth_only_session_is_diagnosed_as_the_raw_tap_one(tmp_path, bench_scene, effect, frames):
    draw, tolerances = CASES[effect]
    rng = np.random.default_rng(list(CASES).index(effect) + 100)
    hidden = draw(rng)
    raw = tmp_path / "raw.h5"
    simulate_session(bench_scene, raw, frames=4, seed=int(rng.integers(1000)), noise=True, effects={effect: hidden})
    depth = depth_only_copy(raw, tmp_path / "depth.h5", frames)
    res_raw = diagnose(raw, bench_scene, max_effects=2)
    res_depth = diagnose(depth, bench_scene, max_effects=2)
    assert res_raw.causes == [effect]
    assert res_depth.causes == res_raw.causes, (res_depth.causes, res_depth.params, res_depth.evidence)
    _check_params(res_depth.params[effect], hidden, tolerances)
    assert "phasor" in res_depth.to_json()["data_path"]
    assert ("scatter of one frame" in res_depth.data.noise) == (frames == 1)
    assert "ambient" in res_depth.observability.unobservable


def test_spatial_noise_estimate_recovers_a_known_noise():
    """A tilted plane with a smooth amplitude and white noise of known size: the estimate
    (MAD of the high-pass, corrected by 1.25) finds the depth noise and the amplitude noise."""
    rng = np.random.default_rng(0)
    h, w = 120, 160
    v, u = np.mgrid[0:h, 0:w].astype(float)
    d = 1.0 + 0.002 * u + 0.001 * v
    amp = 1000.0 * (1.0 - 0.001 * u)
    sigma_d, sigma_a = 0.002, 15.0
    f = np.array([60e6])
    s = depth_phasor(d + rng.normal(0, sigma_d, d.shape), amp + rng.normal(0, sigma_a, d.shape), f)
    var_t, var_r = spatial_noise_variance(s, np.ones((h, w), bool))
    k = 4 * math.pi * f[0] / 299_792_458.0
    est_d = math.sqrt(var_t[0]) / np.median(amp) / k
    assert est_d == pytest.approx(sigma_d, rel=0.1)
    assert math.sqrt(var_r[0]) == pytest.approx(sigma_a, rel=0.1)


def test_one_frame_depth_session_splits_into_pixel_blocks_and_bins_large_images(tmp_path, bench_scene):
    cam = CameraModel.from_fov(320, 240, 60.0)
    rng = np.random.default_rng(1)
    d = np.full(cam.shape, 1.5) + rng.normal(0, 0.002, cam.shape)
    amp = np.full(cam.shape, 500.0)
    path = tmp_path / "one.h5"
    with SessionWriter(path, cam) as wr:
        wr.append(depth=DepthFrame(distance_m=d, kind="radial", camera=cam, amplitude=amp))
    with open_session(path) as s:
        data = split_depth_session(s, bench_scene, max_pixels=5000)
    assert data.camera.width == 320 // 4 and data.camera.height == 240 // 4   # 76800 px -> 4 x 4 bins
    assert data.binned_by == 4 and data.bin_px == 1   # (the twin of a depth session is not binned alike)
    assert data.n_train_frames == data.n_test_frames == 1
    assert not (data.train_pixels & data.test_pixels).any()
    assert data.train_pixels.sum() > 0.4 * data.usable.sum() and data.test_pixels.sum() > 0.4 * data.usable.sum()
    # the frequencies come from the scene when the session records none
    np.testing.assert_allclose(data.freq_hz, bench_scene.sensor.freq_hz)
    cands, dropped = observable_candidates(None, data, depth_only=True, unobservable={"range_offset": "why"})
    assert set(dropped) == set(OFFSET_ONLY_EFFECTS) | {"range_offset"}
    assert not set(dropped) & set(cands)


def test_depth_session_without_amplitude_is_refused_with_the_field_named(tmp_path, bench_scene):
    from tofhil.errors import TofhilError

    cam = CameraModel.from_fov(40, 30, 60.0)
    path = tmp_path / "noamp.h5"
    with SessionWriter(path, cam) as wr:
        wr.append(depth=DepthFrame(distance_m=np.ones(cam.shape), kind="radial", camera=cam))
    with open_session(path) as s, pytest.raises(TofhilError, match="depth/amplitude"):
        split_depth_session(s, bench_scene)


class _TwoNamesOneCause:
    """A forward model with two effects that act identically (a gain on S), and a third that
    does something else: the data cannot tell the first two apart."""

    def __init__(self, base: np.ndarray) -> None:
        from tofhil.eval.diagnose.selection import EffectSpec, FitParam

        self.base = base
        spec = EffectSpec((FitParam("g", 0.0, -0.5, 0.5, 0.05),))
        self._lib = {"a": spec, "b": spec, "c": spec}

    def library(self):
        return self._lib

    def predict(self, active):
        s = self.base.copy()
        for name in ("a", "b"):
            s = s * (1.0 + active.get(name, {}).get("g", 0.0))
        g = active.get("c", {}).get("g", 0.0)
        return s + g * np.abs(self.base).mean() * 1j  # a constant phase-like shift
    

def test_two_causes_that_act_alike_are_reported_as_ambiguous():
    from tofhil.eval.diagnose.heldout import HeldOutData
    from tofhil.eval.diagnose.ambiguity import ROUND_SCORE, ambiguities
    from tofhil.eval.diagnose.selection import greedy_select

    rng = np.random.default_rng(3)
    h, w = 32, 32
    base = (100.0 + 20 * rng.random((1, h, w))) * np.exp(1j * rng.uniform(0, 6, (1, h, w)))
    truth = base * 1.1
    noise = lambda: rng.normal(0, 1.0, base.shape) + 1j * rng.normal(0, 1.0, base.shape)  # noqa: E731
    usable = np.ones((h, w), bool)
    from tofhil.eval.diagnose.heldout import block_checkerboard

    board = block_checkerboard((h, w), 8)
    data = HeldOutData(camera=CameraModel.from_fov(w, h, 60.0), freq_hz=np.array([20e6]),
                       theta_rad=np.arange(4) * np.pi / 2, integration_time_s=1e-3,
                       s_train=truth + noise(), s_test=truth + noise(), var_train=np.full(base.shape, 1.0),
                       var_test=np.full(base.shape, 1.0), usable=usable, train_pixels=board, test_pixels=~board,
                       n_train_frames=1, n_test_frames=1)
    model = _TwoNamesOneCause(base)
    sel = greedy_select(model, data, max_effects=1)
    assert sel.causes and sel.causes[0] in ("a", "b")
    found = [a for a in ambiguities(sel, sel.causes, model, data, block_px=8).items if a.test == ROUND_SCORE]
    pairs = [set(a.readings) for a in found]
    assert {"a", "b"} in pairs
    assert not any("c" in p for p in pairs)  # the effect that acts otherwise is told apart
    assert "cannot tell them apart" in found[0].text
    assert found[0].separating.to_json()["kind"] in ("acquisition", "bench_change")


def _every_nth_pixel_of_capture(name: str, step: int, first: int, tmp_path):
    """Frame 0 of a real capture (``tests/real_data.CAPTURES``), every ``step``-th pixel from
    ``first``, as a small depth session, and its twin scene from scene-from-capture at the
    capture's stated frequency: (session path, scene result)."""
    from tests.real_data import CAPTURES, need
    from tofhil.drivers.importers.dispatch import import_file
    from tofhil.sim.from_capture import scene_from_capture

    cap = CAPTURES[name]
    full = import_file(need(cap.file), tmp_path / "full.h5").out
    with open_session(full) as s:
        d = s.depth_frame(0)
        cam = s.camera.scaled(1.0 / step)
    pick = (slice(first, None, step), slice(first, None, step))
    small = tmp_path / "small.h5"
    with SessionWriter(small, cam) as w:
        w.append(depth=DepthFrame(distance_m=np.asarray(d.radial_m)[pick], kind="radial", camera=cam,
                                  amplitude=np.asarray(d.amplitude)[pick], valid=d.valid[pick]))
    scene = scene_from_capture(small, tmp_path / f"{name}.yaml", freq_hz=[cap.freq_hz], wavelength_m=cap.wavelength_m)
    return small, scene


@pytest.mark.slow
def test_real_near_plane_capture_is_diagnosed_end_to_end(tmp_path):
    """The ADI near-plane capture (binned 4 x 4): import, scene-from-capture, diagnose. The
    diagnosis runs on the depth path, writes its files, and never names what the scene cannot
    observe (its planes' poses were fitted to the same depth)."""
    from tofhil.eval.diagnose.run import run_diagnosis

    small, scene = _every_nth_pixel_of_capture("near", 4, 1, tmp_path)
    res = run_diagnosis(small, scene.scene_path, tmp_path / "diag", max_effects=1)
    out = json.loads((tmp_path / "diag" / "diagnosis.json").read_text())
    assert (tmp_path / "diag" / "report.html").is_file()
    assert "phasor" in out["data_path"] and "spatial scatter" in out["noise"]
    assert set(out["observability"]["unobservable"]) >= {"range_offset", "pose", "ambient"}
    assert not {"range_offset", "pose", "ambient"} & set(res.causes)
    assert not {"range_offset", "pose", "ambient"} & {c["effect"] for c in res.ranked}
    # a range pattern or a field-angle error named on planes fitted to the same depth is said to
    # be indistinguishable from a surface shape the planes lack
    from tofhil.sim.effects import EFFECTS

    pairs = [a["effects"] for a in out["observability"]["ambiguous"]]
    assert all([c, "surface shape"] in pairs for c in res.causes if EFFECTS[c].mimicked_by_shape)
    assert all(p[0] in res.causes for p in pairs if p[1] == "surface shape")


@pytest.mark.slow
def test_real_kinect_names_no_cause_whose_held_out_gain_is_too_small(tmp_path):
    """The Azure Kinect recording (every 8th pixel): session 3 named a wiggling (h3 0.0016)
    whose held-out depth RMSE went 6.39 -> 6.42 mm. Every named cause must lower some channel's
    held-out RMSE by its stated minimum, in the channel's own units; a channel it leaves worse is
    said (the explanation is partial: never "explained", and the worse figure in the notes), not
    hidden; what was fitted but too small says so, with its figures."""
    from tofhil.eval.diagnose import verdict as V
    from tofhil.eval.diagnose.run import run_diagnosis

    small, scene = _every_nth_pixel_of_capture("kinect", 8, 3, tmp_path)  # 80 x 72: no binning
    res = run_diagnosis(small, scene.scene_path, tmp_path / "diag", max_effects=1)
    out = json.loads((tmp_path / "diag" / "diagnosis.json").read_text())
    es = out["effect_size"]
    assert "0.5 mm" in es["rule"] and set(es["channels"]) == {"depth", "amplitude"}
    depth = es["channels"]["depth"]
    assert depth["minimum_gain"] >= V.MIN_DEPTH_GAIN_M * 1e3 and depth["unit"] == "mm"
    if res.causes:
        assert any(c["enough"] for c in es["channels"].values())
        g = out["gain"]["depth_rmse_m"]
        if any(c["worse"] for c in es["channels"].values()) or g["after"] > g["before"] * 1.005:
            # a channel left worse: said, and the verdict is partial
            assert res.verdict.kind == "partly explained"
            assert any("worse" in n for n in res.verdict.notes + [res.verdict.text])
    for text in es["fitted_too_small"].values():
        assert "systematic part removed" in text and "needs" in text and "RMSE" in text
    # each residual region says what it looks like, on which object
    for r in out["residual_regions"]:
        assert r["kind"] and r["objects"]


def test_amplitude_model_error_does_not_bias_a_fitted_level():
    """A scene with one reflectance per object leaves a multiplicative texture (log scatter e)
    in the measured amplitude. A level fitted against that error must come out at the
    texture's median (1 by construction here), not pulled low: weighing the difference
    against e times the *measured* amplitude gave exp(-1.5 e^2) (the ADI office's x0.55)."""
    from scipy.optimize import minimize_scalar

    from tofhil.eval.diagnose.heldout import HeldOutData

    rng = np.random.default_rng(4)
    h, w, e = 30, 40, 0.6
    phase = np.exp(1j * rng.uniform(0, 2 * np.pi, (1, h, w)))
    twin = 100.0 * phase
    s = twin * np.exp(e * rng.standard_normal((1, h, w)))
    board = ((np.arange(h)[:, None] // 4 + np.arange(w)[None] // 4) % 2) == 0
    var = np.full((1, h, w), 1.0)  # the instrument: 1 % of the amplitude
    data = HeldOutData(camera=CameraModel.from_fov(w, h, 60.0), freq_hz=np.array([30e6]),
                       theta_rad=np.arange(4) * np.pi / 2, integration_time_s=1e-3, s_train=s, s_test=s,
                       var_train=var, var_test=var, usable=np.ones((h, w), bool), train_pixels=board,
                       test_pixels=~board, n_train_frames=1, n_test_frames=1, phase_ref=phase,
                       radial_var_scale=np.ones((1, h, w)), amplitude_model_error=e)
    best = minimize_scalar(lambda k: data.chi2(k * twin, "train"), bounds=(0.2, 3.0), method="bounded").x
    assert best == pytest.approx(1.0, abs=0.06)
    # the depth part is untouched: a phase error costs what it did
    r = data.whitened(twin * np.exp(1j * 0.01), "test")
    np.testing.assert_allclose(r.imag, (np.abs(s) * np.sin(0.01))[:, ~board], rtol=1e-9)
