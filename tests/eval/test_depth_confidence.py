"""The device's confidence as a noise source of a one-frame depth session (eval/diagnose/depth_heldout.py):
used, at the noise ratio it was made with, when it predicts the local scatter; refused when it
does not. Synthetic phasors with known per-pixel noise, no rendering."""

from __future__ import annotations

import numpy as np
import pytest

from tofhil.eval.diagnose.depth_heldout import confidence_noise, depth_phasor

H, W = 60, 80


def _frame(sigma_m: np.ndarray, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:H, 0:W]
    depth = 1.0 + 0.002 * u + 0.001 * v + rng.normal(0.0, 1.0, (H, W)) * sigma_m
    return depth_phasor(depth, np.full((H, W), 100.0), np.array([20e6]))


def test_confidence_that_predicts_the_scatter_is_used_at_its_ratio():
    conf = np.where(np.arange(W)[None, :] < W // 2, 10.0, 200.0) * np.ones((H, 1))
    sigma = np.where(conf < 100, 0.002, 0.006)  # the device decides which way its confidence runs
    res = confidence_noise(_frame(sigma, 1), np.ones((H, W), bool), conf)
    assert res is not None
    scale, note = res
    # variance ratio between the halves: (6 / 2)^2 = 9, within the robust estimate's error
    ratio = np.median(scale[:, W // 2 + 2:]) / np.median(scale[:, :W // 2 - 2])
    assert ratio == pytest.approx(9.0, rel=0.3)
    assert "confidence calibrated" in note


@pytest.mark.parametrize("seed", [2, 3])
def test_confidence_unrelated_to_the_scatter_is_not_used(seed):
    rng = np.random.default_rng(seed + 10)
    conf = rng.uniform(0, 255, (H, W))
    assert confidence_noise(_frame(np.full((H, W), 0.003), seed), np.ones((H, W), bool), conf) is None


def test_constant_confidence_says_nothing():
    assert confidence_noise(_frame(np.full((H, W), 0.003), 4), np.ones((H, W), bool), np.full((H, W), 7.0)) is None


def test_real_adi_office_confidence_is_calibrated_and_stated(tmp_path):
    """The ADI office frame carries the device's confidence byte: the one-frame split states
    whether it was used; if used, the pixels it calls noisier do scatter more (the high-pass
    of the binned phasor, computed here on its own)."""
    from types import SimpleNamespace

    from tests.real_data import CAPTURES, need
    from tofhil.drivers.importers.dispatch import import_file
    from tofhil.eval.diagnose.depth_heldout import split_depth_session
    from tofhil.session import open_session

    office = CAPTURES["office"]
    path = import_file(need(office.file), tmp_path / "office.h5").out
    scene = SimpleNamespace(sensor=SimpleNamespace(freq_hz=(office.freq_hz,), theta_rad=(0.0, 1.5708, 3.1416, 4.7124),
                                                   integration_time_s=1e-3))
    with open_session(path) as s:
        assert "depth/confidence" in s.datasets
        data = split_depth_session(s, scene)
    assert "confidence" in data.noise
    if "calibrated against the local scatter and used" not in data.noise:
        assert "does not predict it" in data.noise
        return
    s0 = data.s_test[0]
    u = data.usable
    inner = u & np.roll(u, 1, 0) & np.roll(u, -1, 0) & np.roll(u, 1, 1) & np.roll(u, -1, 1)
    inner[0], inner[-1], inner[:, 0], inner[:, -1] = False, False, False, False
    nb = 0.25 * (np.roll(s0, 1, 0) + np.roll(s0, -1, 0) + np.roll(s0, 1, 1) + np.roll(s0, -1, 1))
    hp = ((s0 - nb) * np.conj(s0 / np.abs(s0))).imag
    var = data.var_test[0]
    lo = inner & (var <= np.median(var[inner]))
    hi = inner & (var > np.median(var[inner]))

    def mad(x):
        return 1.4826 * np.median(np.abs(x - np.median(x)))

    assert mad(hp[hi]) > mad(hp[lo])
