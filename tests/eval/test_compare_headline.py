"""The compare page's headline figures (issue 34): a side's pixels without a signal of their own
are left out by that side's own noise, robust figures lead, the trimming is stated."""

from __future__ import annotations

import numpy as np
import pytest

from tofhil.camera import CameraModel
from tofhil.eval.metrics import core as M
from tofhil.frames import DepthFrame

CAM = CameraModel.from_fov(40, 30, 60.0)
SHORTEST = 7.495  # 20 MHz
LIMIT = M.NO_SIGNAL_FRACTION * SHORTEST


def _frame(radial: np.ndarray, amplitude: np.ndarray) -> DepthFrame:
    return DepthFrame(distance_m=radial.astype(np.float32), kind="radial", camera=CAM,
                      amplitude=amplitude.astype(np.float32), valid=np.ones(CAM.shape, bool))


def test_a_strip_of_random_depths_is_incoherent_an_edge_is_not() -> None:
    rng = np.random.default_rng(1)
    d = np.full(CAM.shape, 1.0) + rng.normal(0, 0.005, CAM.shape)
    d[:, 5:15] = 0.4                      # a card: two edges
    d[:, 25:32] = rng.uniform(0.3, 7.0, (30, 7))  # a shadow with depths at random
    flags = M.incoherent_depth(d, np.ones(CAM.shape, bool), LIMIT)
    assert flags[:, 26:31].mean() > 0.9
    assert not flags[:, :24].any()


def test_the_twins_shadow_is_left_out_by_its_own_noise_and_counted() -> None:
    """A's pixel is clean, B's (the twin's) has no light of its own: not in the figures; a
    combined noise small enough to pass is no longer what decides."""
    rng = np.random.default_rng(2)
    truth = np.full(CAM.shape, 1.0)
    amp = np.full(CAM.shape, 300.0)
    b_depth, b_amp = truth.copy(), amp.copy()
    b_depth[:, 30:36] = rng.uniform(0.3, 7.0, (30, 6))
    b_amp[:, 30:36] = 2.0                 # lit only by what the twin does not model
    a = _frame(truth + rng.normal(0, 0.005, CAM.shape), amp)
    b = _frame(b_depth, b_amp)
    small = np.full(CAM.shape, 0.005)     # the frames' scatter: a few mm everywhere
    maps = M.residual_maps(a, b, freq_hz=[20e6], noise_m=np.hypot(small, small), own_noise_m=(small, small))
    assert maps.no_signal[:, 30:36].mean() > 0.95
    assert not maps.no_signal[:, :28].any()
    ev = M.evaluate(a, b, freq_hz=[20e6], noise_m=np.hypot(small, small), own_noise_m=(small, small),
                    cloud_regions=False)
    r = ev.regions["all"]
    assert r.no_signal_pixels >= 4 * 30 and r.depth_rmse_m < 0.05
    before = M.evaluate(a, b, freq_hz=[20e6], noise_m=np.hypot(small, small), cloud_regions=False).regions["all"]
    assert before.depth_rmse_m > 1.0      # what the combined noise let through


def test_a_bright_edge_among_clipped_pixels_is_kept() -> None:
    """Coherence decides only for dim pixels: a card corner whose neighbours are clipped mixes
    card and wall in its window and still has a signal."""
    d = np.full(CAM.shape, 1.0)
    d[10:20, 10:20] = 0.3
    d[25, :] = 0.5                        # a bright line one pixel wide
    valid = np.ones(CAM.shape, bool)
    valid[10:20, 10:20] = False
    valid[10, 10] = True                  # one unclipped corner pixel
    a = DepthFrame(distance_m=d.astype(np.float32), kind="radial", camera=CAM,
                   amplitude=np.full(CAM.shape, 300.0, np.float32), valid=valid)
    maps = M.residual_maps(a, a, freq_hz=[20e6], own_noise_m=(None, None))
    assert not maps.no_signal[10, 10] and not maps.no_signal[25].any()


def test_trimmed_rmse_drops_the_stated_fraction() -> None:
    x = np.r_[np.full(95, 0.01), np.full(5, 2.0)]
    assert M.trimmed_rmse(x, 0.05) == pytest.approx(0.01)
    assert M.stats(x).rmse_trimmed == M.trimmed_rmse(x) and M.stats(x).rmse > 0.4
    assert np.isnan(M.trimmed_rmse(np.array([])))
