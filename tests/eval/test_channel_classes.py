"""Classes of real camera behaviour that act on one calibration channel, hidden in twin sessions
with noise and ADC quantisation (random parameters per seed): the diagnosis reads the residual
by channel and names the family whose channel it is, and nothing else.

The classes: a calibration phase on one frequency of a two-frequency sensor, a tap gain
imbalance, a warm-up drift, and nothing hidden on two- and three-frequency sensors. Stuck and
hot pixels are in tests/eval/test_defects.py; the library's own forms in test_diagnose.py.
"""

from __future__ import annotations

import numpy as np
import pytest

from tests.eval import hidden_forms as hf


@pytest.fixture(scope="module")
def scene():
    return hf.small_dark_square(80)


def _diagnose(path, scene, **kw):
    from tofhil.eval.diagnose.run import diagnose

    return diagnose(path, scene, max_effects=3, **kw)


def _no_channel_worse(res) -> None:
    assert not any(c["worse"] for c in res.channels.values()), res.channels


@pytest.mark.parametrize("seed", [1, 2])
def test_a_phase_on_one_frequency_is_that_frequency_s_calibration(tmp_path, scene, seed):
    """44 + 60 MHz, the 60 MHz channel alone 0.06-0.15 rad off (it said "the scene does not
    match", and a nearer surface over the whole wall)."""
    rng = np.random.default_rng(seed)
    two = hf.with_frequencies(scene, (44e6, 60e6))
    change = hf.frequency_phase_offset(rng)
    path = hf.write_session(two, tmp_path / "f.h5", change, frames=6, seed=30 + seed)
    res = _diagnose(path, two)
    before = {r["name"]: r for r in res.channel_table["before"]["readings"]}
    assert before["60 MHz phase"]["significant"] and before["phase inconsistency"]["significant"]
    assert abs(before["60 MHz phase"]["value"] - change.phase_rad) < 0.01
    assert res.causes == ["frequency_calibration"], (res.causes, res.verdict.text)
    assert abs(res.params["frequency_calibration"]["phase_1_rad"] - change.phase_rad) < 0.01
    assert res.verdict.kind == "explained" and res.verdict.excess_removed > 0.9
    _no_channel_worse(res)
    assert not res.channel_table["after"]["significant"], res.channel_table["after"]


@pytest.mark.parametrize("seed", [3, 4])
def test_a_tap_gain_imbalance_is_the_tap_calibration_not_a_pose(tmp_path, scene, seed):
    """Taps 1 and 3 with 2-5 % more gain (it said pose + wiggling: a pose cannot make a pattern
    that alternates with the tap index)."""
    rng = np.random.default_rng(seed)
    g1, g3 = 1 + rng.uniform(0.02, 0.05), 1 + rng.uniform(0.02, 0.05)
    path = hf.write_session(scene, tmp_path / "t.h5", None, frames=6, seed=40 + seed,
                            tap_change=hf.tap_gain_imbalance(rng, gains=(1.0, g1, 1.0, g3)))
    res = _diagnose(path, scene)
    assert "tap" in res.channel_table["before"]["significant"]
    assert res.causes == ["tap_calibration"], (res.causes, res.verdict.text)
    p = res.params["tap_calibration"]
    assert abs(p["gain_1"] - g1) < 0.005 and abs(p["gain_3"] - g3) < 0.005 and abs(p["gain_2"] - 1) < 0.005
    assert res.verdict.excess_removed > 0.9
    _no_channel_worse(res)


def test_a_warm_up_drift_is_the_drift_and_no_static_effect(tmp_path, scene):
    """The range moves 12-25 mm over the frames as the camera warms up and the light falls 1 %
    a frame (it said "explained by stray_light + range_offset": the static mean fits)."""
    rng = np.random.default_rng(5)
    path = hf.write_session(scene, tmp_path / "w.h5", None, frames=6, seed=45,
                            frame_change=hf.warm_up_drift(rng))
    res = _diagnose(path, scene)
    before = {r["name"]: r for r in res.channel_table["before"]["readings"]}
    assert before["range trend"]["significant"] and before["signal trend"]["significant"]
    assert res.drift is not None and res.drift["named"]
    assert res.causes == [], (res.causes, res.verdict.notes)
    assert "drift" in res.verdict.text


@pytest.mark.parametrize("freqs", [(44e6, 60e6), (40e6, 60e6, 100e6)])
def test_nothing_hidden_on_multi_frequency_sensors_names_nothing(tmp_path, scene, freqs):
    multi = hf.with_frequencies(scene, freqs)
    path = hf.write_session(multi, tmp_path / "n.h5", None, frames=6, seed=50 + len(freqs))
    res = _diagnose(path, multi)
    assert res.causes == [] and res.verdict.kind == "within noise", (res.causes, res.verdict.text)
    assert res.defects["pixels"] == 0
    assert res.gain["depth_rmse_m"]["before"] < 0.05


@pytest.mark.parametrize("seed,freqs", [(5, (44e6,)), (6, (44e6, 60e6))])
def test_a_panel_outside_the_view_is_light_from_an_unseen_reflector(tmp_path, scene, seed, freqs):
    """A white panel beside the camera, outside the view, sending a second path onto the wall
    (it said "partly explained by lens_distortion + wiggling"; then reflectance + wiggling: a
    gain and a range offset took up the extra light's mean). The panel is an extended,
    oriented surface in closed form; the library's form is one small patch."""
    rng = np.random.default_rng(seed)
    sc = hf.with_frequencies(scene, freqs)
    change = hf.outside_panel_multipath(rng, sc.camera)
    path = hf.write_session(sc, tmp_path / "p.h5", change, frames=6, seed=50 + seed)
    res = _diagnose(path, sc)
    assert res.causes == ["unseen_reflector"], (res.causes, res.verdict.text)
    assert res.verdict.excess_removed > 0.9, res.verdict.text
    _no_channel_worse(res)
    # found on the panel's side of the view (azimuth 0 = +x)
    az = res.params["unseen_reflector"]["azimuth_deg"]
    assert (abs(az) < 45) if change.side > 0 else (abs(az) > 135), az


def test_a_cause_that_moves_a_clean_channel_is_not_named(tmp_path, scene):
    """The final model's readings against the base twin's: a range offset on a session with
    nothing hidden moves both frequencies' phases, clean before; without it they are clean
    again, so it is the one that moved them (and one that moves nothing is left named)."""
    from tofhil.eval.diagnose.decide import moved_clean_channels as _moved_clean_channels
    from tofhil.eval.diagnose.run import _held_out_data
    from tofhil.eval.diagnose.selection import Selection
    from tofhil.eval.diagnose.twin_model import TwinModel
    from tofhil.sim.from_capture import capture_scene_facts

    two = hf.with_frequencies(scene, (44e6, 60e6))
    path = hf.write_session(two, tmp_path / "n.h5", None, frames=6, seed=77)
    data, _ = _held_out_data(path, two, capture_scene_facts(two), block_px=8, max_frames=None)
    model = TwinModel(two, data)
    base = model.predict({})
    params = {"range_offset": {"path_m": 0.01}, "reflectance": {"scale": 1.0}}
    sel = Selection(causes=list(params), params=params, baseline_chi2_test=0.0, final_chi2_test=0.0)
    moved = _moved_clean_channels(model, data, sel, base)
    assert list(moved) == ["range_offset"], moved
    assert any("44 MHz: phase" in t for t in moved["range_offset"]) and any("60 MHz: phase" in t
                                                                            for t in moved["range_offset"])


@pytest.mark.parametrize("seed", [6, 7])
def test_a_linear_illumination_gradient_is_a_gain_field(tmp_path, scene, seed):
    """The emitter's light rising 20-50 % across the field in a random direction (it was read as
    the emitter moved sideways plus a fixed-pattern delay: nothing radial or physical in the
    library has a linear gain): the gain field, at the drawn slope."""
    rng = np.random.default_rng(seed)
    change = hf.gain_gradient(rng)
    path = hf.write_session(scene, tmp_path / "g.h5", change, frames=6, seed=60 + seed)
    res = _diagnose(path, scene)
    assert "gain_field" in res.causes, (res.causes, res.verdict.text)
    p = res.params["gain_field"]
    ax, ay = change.slope_xy
    assert np.hypot(p["linear_x"] - ax, p["linear_y"] - ay) < 0.1 * np.hypot(ax, ay), (p, change.slope_xy)
    assert res.verdict.excess_removed > 0.9


@pytest.mark.parametrize("seed", [8, 9])
def test_a_warm_corner_is_an_offset_field_not_a_reflector(tmp_path, scene, seed):
    """Unmodulated charge rising toward one corner (it was read as light from an unseen
    reflector, a stray-light veil or tap offsets): the offset field, highest at that corner."""
    rng = np.random.default_rng(seed)
    change = hf.warm_corner(rng)
    path = hf.write_session(scene, tmp_path / "o.h5", change, frames=6, seed=80 + seed)
    res = _diagnose(path, scene)
    assert res.causes == ["offset_field"], (res.causes, res.verdict.text)
    p = res.params["offset_field"]
    sx, sy = change.corner

    def at(x: float, y: float) -> float:  # the fitted field at a point (docs/effects.md's basis)
        px, py = (1.0, x, 1.5 * x * x - 0.5), (1.0, y, 1.5 * y * y - 0.5)
        names = {"mean": (0, 0), "linear_x": (1, 0), "linear_y": (0, 1), "quad_xx": (2, 0), "quad_xy": (1, 1),
                 "quad_yy": (0, 2), "cubic_xxy": (2, 1), "cubic_xyy": (1, 2), "quartic_xxyy": (2, 2)}
        return sum(p[k + "_e"] * px[i] * py[j] for k, (i, j) in names.items())

    corners = {(cx, cy): at(cx, cy) for cx in (-1, 1) for cy in (-1, 1)}
    assert max(corners, key=corners.get) == (sx, sy), corners
    assert res.verdict.excess_removed > 0.9
    _no_channel_worse(res)
