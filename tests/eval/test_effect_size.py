"""The minimum effect size for naming a cause (eval/diagnose/verdict.py ``EffectSize``).

A misfit far above noise can come with a gain no ToF engineer would act on: with a low noise,
a 0.2 mm range shift over many pixels is hugely significant, yet it is not worth naming. The
fake forward model of test_selection shifts the phase; the depth that shift makes is computed
independently, through ``tofhil.demod.distance_to_phase``.
"""

from __future__ import annotations

import numpy as np
import pytest

from tests.eval.fake_heldout import heldout_from_signal
from tests.eval.test_selection import FakeModel
from tofhil.demod import distance_to_phase
from tofhil.eval.diagnose import verdict as V
from tofhil.eval.diagnose.selection import greedy_select

SIGMA = 2e-5  # per component; the signal is ~1.4: a depth noise of ~10 um at 20 MHz


def _shifted(depth_m: float):
    phi = float(distance_to_phase(depth_m, 20e6))
    model = FakeModel()
    return model, heldout_from_signal(model.predict({"shift": {"phi": phi}}), SIGMA, seed=3)


@pytest.mark.parametrize("depth_mm, named", [(0.2, False), (2.0, True)])
def test_a_significant_but_tiny_range_shift_is_not_named(depth_mm, named):
    model, data = _shifted(depth_mm * 1e-3)
    sizes = V.EffectSize(data)
    # the noise is far below the absolute minimum, so the minimum is the 0.5 mm
    assert sizes.noise["depth"] < 1e-4
    assert sizes.minimum["depth"] == pytest.approx(V.MIN_DEPTH_GAIN_M)
    plain = greedy_select(model, data, max_effects=1, candidates=["shift"])
    assert plain.causes == ["shift"]  # significant in misfit either way
    sel = greedy_select(model, data, max_effects=1, candidates=["shift"], effect_size=sizes)
    assert (sel.causes == ["shift"]) is named
    g = sizes.compare(model.predict({}), model.predict(plain.params))["depth"]
    # the gain is the shift itself: the base model is off by it everywhere, the fit by noise
    assert g.before == pytest.approx(depth_mm * 1e-3, rel=0.02)
    assert g.after < 1.5 * sizes.noise["depth"]
    if not named:
        assert "shift" in sel.too_small and "needs 0.5 mm" in sel.too_small["shift"]


def test_the_systematic_part_removed_is_the_hidden_pattern_however_strong_the_noise():
    # a column pattern of 5.8 mm rms range error (the demo's clock skew) under 20 mm pixel noise:
    # the RMSE falls by ~s^2 / 2 sigma only (0.8 mm, below the 2 mm minimum), the squares by
    # exactly the pattern's variance
    h, w, f = 96, 128, 20e6
    pattern_m = 5.8e-3 * np.sqrt(2.0) * np.sin(2 * np.pi * np.arange(w) / 16.0)[None, :].repeat(h, 0)
    k = float(distance_to_phase(1.0, f))  # rad per metre of range
    truth = np.exp(1j * k * pattern_m)[None]
    data = heldout_from_signal(truth, sigma=20e-3 * k, seed=5)  # depth noise sigma / (A k) = 20 mm
    sizes = V.EffectSize(data)
    assert sizes.noise["depth"] == pytest.approx(20e-3, rel=0.05)
    # the minimum is a tenth of what the capture reaches: the pixel noise with every frame averaged
    reach = np.sqrt(data.n_test_frames / (data.n_train_frames + data.n_test_frames))
    assert sizes.minimum["depth"] == pytest.approx(2e-3 * reach, rel=0.05)
    g = sizes.compare(np.ones_like(truth), truth)["depth"]
    rms_pattern = float(np.sqrt(np.mean(pattern_m[data.test_pixels] ** 2)))
    assert g.systematic == pytest.approx(rms_pattern, rel=0.15)
    assert g.before - g.after < sizes.minimum["depth"]  # what the old measure compared: "too small"
    assert g.enough and not g.worse
    # the other way round the same pattern is added: worse, and by as much
    back = sizes.compare(truth, np.ones_like(truth))["depth"]
    assert back.worse and back.systematic == pytest.approx(-g.systematic, rel=0.15)
    # a correction shrunk to a fifth of the pattern takes 0.36 of its variance off the residual
    # (2 x 0.2 - 0.2^2): what it changes, and what the cause is worth, is the fifth
    shrunk = sizes.compare(np.ones_like(truth), np.exp(1j * k * 0.2 * pattern_m)[None])["depth"]
    assert np.sqrt(shrunk.before ** 2 - shrunk.after ** 2) == pytest.approx(0.6 * rms_pattern, rel=0.15)
    assert shrunk.systematic == pytest.approx(0.2 * rms_pattern, rel=0.05)
    # a change of the prediction far below the noise is no loss however the noise falls
    tiny = sizes.compare(truth, truth * np.exp(1j * k * 0.02 * pattern_m))["depth"]
    assert not tiny.worse and not tiny.enough


def test_a_channel_that_gains_a_systematic_part_is_flagged_not_a_veto():
    gain = V.ChannelGain("depth", before=6e-3, after=3e-3, noise=1e-3, minimum=0.5e-3, pixels=100)
    loss = V.ChannelGain("amplitude", before=10.0, after=10.2, noise=5.0, minimum=0.5, pixels=100,
                         square_change_se=0.1)
    # the same growth of the squares within 3 standard errors of the held-out noise: a rounding
    noise = V.ChannelGain("amplitude", before=10.0, after=10.2, noise=5.0, minimum=0.5, pixels=100,
                          square_change_se=2.0)
    # exact, but a systematic part of 0.2 DN, below half the 0.5 DN minimum
    rounding = V.ChannelGain("amplitude", before=10.0, after=10.002, noise=5.0, minimum=0.5, pixels=100)
    assert gain.enough and gain.systematic == pytest.approx(np.sqrt(27e-6))
    assert not gain.worse and loss.worse and not noise.worse and not rounding.worse
    assert V.EffectSize.worth_naming({"depth": gain, "amplitude": rounding})
    # a channel made worse is accounted by the caller (the explanation is partial), not a veto
    assert V.EffectSize.worth_naming({"depth": gain, "amplitude": loss})
    assert "amplitude" in V.EffectSize.why_not({"amplitude": loss})
    # the Azure Kinect's wiggling (session 3): 6.39 -> 6.42 mm adds a 0.62 mm systematic part and
    # gains nothing: not worth naming, for want of a gain
    kinect = V.ChannelGain("depth", before=6.39e-3, after=6.42e-3, noise=1e-3, minimum=0.5e-3, pixels=100)
    assert kinect.worse and not V.EffectSize.worth_naming({"depth": kinect, "amplitude": rounding})
    assert "6.39 -> 6.42 mm" in kinect.describe()


def test_amplitude_minimum_is_a_share_of_its_level_and_noise():
    s = np.full((1, 16, 16), 100.0 + 0j)
    data = heldout_from_signal(s, 1.0, seed=0)
    sizes = V.EffectSize(data)
    # noise 1 DN per component: 0.1 x ~1 DN against 1 % of ~100 DN
    assert sizes.noise["amplitude"] == pytest.approx(1.0, rel=0.1)
    assert sizes.minimum["amplitude"] == pytest.approx(1.0, rel=0.05)
    g = sizes.compare(s, s * 1.05)["amplitude"]
    assert g.worse and not g.enough


@pytest.mark.parametrize("depth_mm, spread_mm, sigma_mm, ratio, kind", [
    (-10.0, 2.0, 2.0, 1.0, "missing object"),      # the capture nearer: a surface the twin lacks
    (+10.0, 2.0, 2.0, 1.0, "misplaced object"),    # the twin nearer
    (0.5, 12.0, 2.0, 1.0, "wrong shape"),          # no offset, a spread far above the pixel noise
    (0.3, 1.0, 2.0, 0.5, "wrong material"),        # depth right, amplitude half the twin's
    (-0.2, 0.5, 0.0, 1.0, "no consistent"),        # a noiseless (saturated) pixel: 0.2 mm is no object
    (1.0, 2.0, 2.0, 1.05, "no consistent"),        # everything within 3 pixel noises
])
def test_residual_region_says_what_it_looks_like(depth_mm, spread_mm, sigma_mm, ratio, kind):
    r = V.ResidualRegion(50, (0, 0, 10, 5), 9.0, {"wall": 1.0}, depth_mm, 0.0, spread_mm, sigma_mm, ratio, 0.1)
    assert r.kind.startswith(kind)
    assert r.to_json()["kind"] == r.kind and "on wall 100 %" in r.describe()
