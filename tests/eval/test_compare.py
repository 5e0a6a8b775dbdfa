"""The evaluation core (eval/metrics/core.py): robust statistics, regions, residual maps, temporal means."""

from __future__ import annotations

import numpy as np
import pytest

from tofhil.camera import CameraModel
from tofhil.errors import TofhilError
from tofhil.eval.metrics import core as M
from tofhil.frames import DepthFrame

CAM = CameraModel.from_fov(20, 10, 60.0)


def frame(d, amp=None, valid=None) -> DepthFrame:
    return DepthFrame(distance_m=np.asarray(d, float), kind="radial", camera=CAM,
                      amplitude=None if amp is None else np.asarray(amp, float), valid=valid)


def test_robust_stats_by_hand():
    s = M.stats(np.array([1.0, 2.0, 3.0, 4.0, 100.0, np.nan]))
    assert s.n == 5 and s.median == 3.0 and s.mad == 1.0
    assert s.sigma_mad == pytest.approx(1.4826)
    assert s.mean == 22.0
    assert s.rmse == pytest.approx(np.sqrt((1 + 4 + 9 + 16 + 10000) / 5))
    assert s.p95_abs == pytest.approx(4 + 0.8 * 96)  # linear interpolation at rank 3.8
    assert M.stats(np.array([np.nan])).n == 0
    assert M.stats(np.array([np.nan])).to_json()["rmse"] is None  # JSON has no NaN


def test_compare_frames_per_region():
    b = frame(np.full(CAM.shape, 2.0), amp=np.full(CAM.shape, 10.0))
    da = np.full(CAM.shape, 2.0)
    da[:, 10:] += 0.05  # right half 5 cm too far
    amp = np.full(CAM.shape, 10.0)
    amp[:, 10:] = 5.0
    valid = np.ones(CAM.shape, bool)
    valid[0, :] = False  # one row invalid in A
    a = frame(da, amp, valid)
    ids = np.zeros(CAM.shape, int)
    ids[:, 10:] = 1
    regions = M.object_regions(ids, {0: "left", 1: "right"}) + [M.parse_roi("10,5,20,10", CAM.shape, "box")]
    r = M.evaluate(a, b, regions).to_json()["regions"]
    assert r["left"]["depth_residual_m"]["median"] == pytest.approx(0.0, abs=1e-12)
    assert r["right"]["depth_residual_m"]["median"] == pytest.approx(0.05)
    assert r["right"]["depth_residual_m"]["n"] == 9 * 10  # the invalid row is left out
    assert r["right"]["amplitude_ratio_median"] == pytest.approx(0.5)
    assert r["right"]["amplitude_difference"]["median"] == pytest.approx(-5.0)
    assert r["all"]["amplitude_ratio"]["mean"] == pytest.approx(0.75)  # half at 1, half at 0.5
    assert r["box"]["pixels"] == 50 and r["box"]["depth_residual_m"]["mad"] == pytest.approx(0.0, abs=1e-12)
    assert r["all"]["valid_fraction_a"] == pytest.approx(0.9)
    # Half the pixels are off by 5 cm: the RMSE of the whole image is 5 cm / sqrt(2).
    assert r["all"]["depth_rmse_m"] == pytest.approx(0.05 / np.sqrt(2))


def test_z_depth_frames_are_compared_as_radial_distance():
    radial = np.full(CAM.shape, 2.0)
    a = DepthFrame(distance_m=CAM.radial_to_z(radial), kind="z", camera=CAM)
    res = M.residual_maps(a, frame(radial)).depth_residual_m
    assert np.allclose(res, 0.0, atol=1e-12)


def test_rois_and_alignment_errors():
    with pytest.raises(TofhilError, match="X0,Y0,X1,Y1"):
        M.parse_roi("1,2,3", CAM.shape)
    with pytest.raises(TofhilError, match="outside"):
        M.parse_roi("0,0,21,5", CAM.shape)
    other = CameraModel.from_fov(10, 10, 60.0)
    with pytest.raises(TofhilError, match="same camera"):
        M.evaluate(frame(np.ones(CAM.shape)), DepthFrame(np.ones((10, 10)), "radial", other))


def test_mean_depth_frame_averages_valid_frames_only():
    d1, d2, d3 = (np.full(CAM.shape, v) for v in (1.0, 2.0, 3.0))
    v3 = np.ones(CAM.shape, bool)
    v3[0, 0] = False
    frames = [frame(d1, valid=np.ones(CAM.shape, bool)), frame(d2), frame(d3, valid=v3)]
    mean, std = M.mean_depth_frame(frames)
    assert mean.radial_m[1, 1] == pytest.approx(2.0) and std[1, 1] == pytest.approx(np.sqrt(2 / 3))
    assert mean.radial_m[0, 0] == pytest.approx(1.5) and std[0, 0] == pytest.approx(0.5)
    # Valid in fewer than half the frames -> invalid in the mean.
    mean2, _ = M.mean_depth_frame([frame(d1, valid=~np.ones(CAM.shape, bool) | (np.arange(20) < 5)),
                                     frame(d2, valid=np.zeros(CAM.shape, bool)),
                                     frame(d3, valid=np.zeros(CAM.shape, bool))])
    assert not mean2.valid.any()


def test_roi_is_half_open_like_numpy_slices():
    r = M.parse_roi("4,2,16,8", CAM.shape)
    assert r.mask.sum() == (16 - 4) * (8 - 2)
    assert r.mask[2, 4] and r.mask[7, 15] and not r.mask[8, 15] and not r.mask[7, 16]
    # the full image is X1 = width, Y1 = height
    assert M.parse_roi("0,0,20,10", CAM.shape).mask.all()


def test_masks_from_npy_and_png(tmp_path):
    import matplotlib.image as mpimg

    m = np.zeros(CAM.shape, bool)
    m[2:5, 3:9] = True
    np.save(tmp_path / "m.npy", m)
    mpimg.imsave(tmp_path / "m.png", m.astype(float), cmap="gray")
    assert np.array_equal(M.load_mask(tmp_path / "m.npy", CAM.shape).mask, m)
    assert np.array_equal(M.load_mask(tmp_path / "m.png", CAM.shape).mask, m)
    np.save(tmp_path / "wrong.npy", np.ones((3, 3)))
    with pytest.raises(TofhilError, match="wrong.npy.*shape"):
        M.load_mask(tmp_path / "wrong.npy", CAM.shape)
    np.save(tmp_path / "empty.npy", np.zeros(CAM.shape))
    with pytest.raises(TofhilError, match="selects no pixel"):
        M.load_mask(tmp_path / "empty.npy", CAM.shape)
    with pytest.raises(TofhilError, match="no such file"):
        M.load_mask(tmp_path / "missing.png", CAM.shape)


def test_single_frequency_residual_wraps_at_the_unambiguous_range():
    f = 20e6
    period = M.wrap_period([f])
    assert period == pytest.approx(299_792_458.0 / (2 * f))  # c / 2f: the phase wraps every half wavelength of path
    assert M.wrap_period([20e6, 24e6]) is None
    # A: just past the wrap (reads near 0), B: just before it; the true difference is 2 cm.
    a = frame(np.full(CAM.shape, 0.01))
    b = frame(np.full(CAM.shape, period - 0.01))
    assert np.allclose(M.residual_maps(a, b, wrap_m=period).depth_residual_m, 0.02)
    assert np.allclose(M.residual_maps(a, b).depth_residual_m, 0.02 - period)


def test_clipped_and_nonfinite_taps_are_invalid_and_reported():
    rng = np.random.default_rng(3)
    taps = rng.uniform(-500, 500, (1, 4) + CAM.shape)
    taps[0, 1, :4, :5] = 2047.0   # a 4 x 5 block clipped at the ADC's top
    taps[0, 2, 9, 0] = np.nan     # one pixel with a NaN tap
    h = M.TapHealth.from_taps([taps])
    assert h.saturated.sum() == 20 and h.saturated[:4, :5].all()
    assert h.nonfinite.sum() == 1 and h.nonfinite[9, 0]
    # a single pixel at the top is a bright pixel, not a clipped ADC
    one = taps.copy()
    one[0, 1, :4, :5] = 0.0
    one[0, 1, 0, 0] = 3000.0
    assert not M.TapHealth.from_taps([one]).saturated.any()

    b = frame(np.full(CAM.shape, 2.0))
    da = np.full(CAM.shape, 2.0)
    da[:4, :5] = 2.5  # the saturated block reads wrong
    card = np.zeros(CAM.shape, bool)
    card[:4, :6] = True  # the block and one good column
    ev = M.evaluate(frame(da), b, [M.Region("card", card, "object")], health_a=h)
    r = ev.regions["card"]
    assert r.saturated_fraction_a == pytest.approx(20 / 24)
    assert r.depth_residual_m.n == 4 and r.depth_rmse_m == pytest.approx(0.0)  # the clipped pixels are out
    assert r.saturation_dominated
    assert "83.3 % of its pixels saturated in A" in r.validity_note()
    assert ev.regions["all"].nonfinite_fraction_a == pytest.approx(1 / 200)
    j = ev.to_json()["regions"]["card"]
    assert j["saturated_fraction_a"] == pytest.approx(20 / 24) and j["saturation_dominated"] is True


def test_no_pixel_valid_in_both_is_refused():
    b = frame(np.full(CAM.shape, 2.0))
    a = frame(np.full(CAM.shape, np.nan))
    with pytest.raises(TofhilError, match="a.h5.*no pixel is valid in both.*A has no valid pixel"):
        M.evaluate(a, b, source="a.h5")
    with pytest.raises(TofhilError, match="threshold"):
        M.evaluate(b, b, threshold=-1)


def test_residual_colour_scale_ignores_outliers():
    from tofhil.eval.reports import html as H

    rng = np.random.default_rng(0)
    res = rng.normal(0.0, 0.003, (60, 80))
    res[0, 0] = 2.0  # one jump-edge pixel 2 m off
    lo, hi = H.symmetric_range([res])
    assert lo == -hi
    assert 0.005 < hi < 0.008  # +-(2-98 %) of a 3 mm Gaussian is about 6 mm, not 2 m


def test_cross_section_choice():
    from tofhil.eval.reports import html as H

    assert H.CrossSection.choose((10, 20)) == H.CrossSection("row", 5)
    s = H.CrossSection.choose((10, 20), column=19)
    assert s.take(np.arange(200.0).reshape(10, 20)).tolist() == list(np.arange(19.0, 200.0, 20))
    with pytest.raises(TofhilError, match="--column"):
        H.CrossSection.choose((10, 20), column=20)
    with pytest.raises(TofhilError, match="not both"):
        H.CrossSection.choose((10, 20), row=1, column=1)
