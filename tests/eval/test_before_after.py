"""Before and after a correction per region: the "worse beyond its noise" rule and its reasons."""

from __future__ import annotations

import math

import numpy as np

from tofhil.eval.metrics.before_after import before_after, near_clipped_regions, region_change


def _region(median: float, rmse: float, n: int, noise: float) -> dict:
    return {"depth_residual_m": {"median": median, "rmse": rmse, "n": n}, "noise_floor_m": noise}


def test_a_change_is_worse_only_beyond_three_noise_of_the_median() -> None:
    n, noise = 400, 0.02  # the median of 400 pixels of 20 mm noise: sqrt(pi/2) * 1 mm, before and after
    sigma = math.sqrt(math.pi / 2) * math.hypot(noise / math.sqrt(n), noise / math.sqrt(n))
    inside = region_change(_region(0.010, 0.03, n, noise), _region(0.010 + 2.9 * sigma, 0.03, n, noise))
    beyond = region_change(_region(0.010, 0.03, n, noise), _region(-(0.010 + 3.1 * sigma), 0.03, n, noise))
    assert not inside["worse"]
    assert beyond["worse"] and beyond["worse_in"] == ["median"]
    assert math.isclose(beyond["median_noise_m"], sigma)
    # a median that moves toward zero is never worse, however far it moves
    assert not region_change(_region(-0.3, 0.3, n, noise), _region(0.001, 0.05, n, noise))["worse"]


def test_reasons_come_from_the_correction_report() -> None:
    before = {"square": _region(-0.24, 0.25, 1000, 0.05), "wall": _region(-0.004, 0.5, 5000, 0.06)}
    after = {"square": _region(-0.28, 0.30, 1000, 0.05), "wall": _region(0.029, 0.07, 5000, 0.04)}
    fr = {"square": {"untrusted": 1.0}, "wall": {"untrusted": 0.0}}
    out = before_after(before, after, fr, {"notes": []})
    assert out["square"]["worse"] and "saturated pixels" in out["square"]["reason"]
    # the wall's median moved away while its RMSE fell: the removed light masked a bias
    assert out["wall"]["worse_in"] == ["median"] and "masked a bias" in out["wall"]["reason"]
    twin = {"twin": {"remove": "light", "effects_left": ["wiggling"]}}
    assert "wiggling" in before_after(before, after, {}, twin)["wall"]["reason"]


def test_near_clipped_region_is_the_ring_around_clipped_pixels() -> None:
    sat = np.zeros((40, 60), bool)
    sat[20, 30] = True
    (region,) = near_clipped_regions(sat, radius_px=5)
    yy, xx = np.mgrid[:40, :60]
    ring = ((yy - 20) ** 2 + (xx - 30) ** 2 <= 25) & ~sat
    np.testing.assert_array_equal(region.mask, ring)
    assert near_clipped_regions(np.zeros((4, 4), bool)) == []


def test_frame_split_is_the_diagnosis_split(tmp_path) -> None:
    """Corrections are fitted on the frames the diagnosis trains on and scored on those it
    holds out: the means of frame_split's halves are diagnose's s_train and s_test."""
    from tests import straylight_synthetic as syn
    from tofhil.demod import phasor
    from tofhil.eval.diagnose.heldout import split_session
    from tofhil.eval.metrics.split import frame_split
    from tofhil.session import open_session

    s, _ = syn.scene_signal(square_rho=0.2, card=False)
    path = syn.write_session(tmp_path / "a.h5", s, n_frames=5, noise=0.01, offset=50.0, seed=2)
    sp = frame_split(5)
    assert sp.fit == (0, 2, 4) and sp.scored == (1, 3) and not sp.in_sample
    with open_session(path) as ses:
        data = split_session(ses, offset_channel=False)
        sig = [phasor(ses.raw_frame(i).taps.astype(np.float64), ses.theta_rad) for i in range(5)]
    np.testing.assert_allclose(data.s_train, np.mean([sig[i] for i in sp.fit], axis=0), atol=1e-9)
    np.testing.assert_allclose(data.s_test, np.mean([sig[i] for i in sp.scored], axis=0), atol=1e-9)
    one = frame_split(1)
    assert one.in_sample and one.fit == one.scored == (0,) and "in-sample" in one.text()
