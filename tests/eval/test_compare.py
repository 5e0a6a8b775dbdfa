"""Pixel-aligned comparison: robust statistics, regions, temporal means."""

from __future__ import annotations

import numpy as np
import pytest

from tofhil.camera import CameraModel
from tofhil.errors import TofhilError
from tofhil.eval import compare as cmp
from tofhil.frames import DepthFrame

CAM = CameraModel.from_fov(20, 10, 60.0)


def frame(d, amp=None, valid=None) -> DepthFrame:
    return DepthFrame(distance_m=np.asarray(d, float), kind="radial", camera=CAM,
                      amplitude=None if amp is None else np.asarray(amp, float), valid=valid)


def test_robust_stats_by_hand():
    s = cmp.robust_stats(np.array([1.0, 2.0, 3.0, 4.0, 100.0, np.nan]))
    assert s["n"] == 5 and s["median"] == 3.0 and s["mad"] == 1.0
    assert s["sigma_mad"] == pytest.approx(1.4826)
    assert s["mean"] == 22.0
    assert s["rmse"] == pytest.approx(np.sqrt((1 + 4 + 9 + 16 + 10000) / 5))
    assert s["p95_abs"] == pytest.approx(4 + 0.8 * 96)  # linear interpolation at rank 3.8
    assert cmp.robust_stats(np.array([np.nan]))["n"] == 0


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
    regions = cmp.object_regions(ids, {0: "left", 1: "right"}) + [cmp.parse_roi("10,5,20,10", CAM.shape, "box")]
    r = cmp.compare_frames(a, b, regions)["regions"]
    assert r["left"]["depth_residual_m"]["median"] == pytest.approx(0.0, abs=1e-12)
    assert r["right"]["depth_residual_m"]["median"] == pytest.approx(0.05)
    assert r["right"]["depth_residual_m"]["n"] == 9 * 10  # the invalid row is left out
    assert r["right"]["amplitude_ratio_median"] == pytest.approx(0.5)
    assert r["all"]["amplitude_ratio"]["mean"] == pytest.approx(0.75)  # half at 1, half at 0.5
    assert r["box"]["pixels"] == 50 and r["box"]["depth_residual_m"]["mad"] == pytest.approx(0.0, abs=1e-12)
    assert r["all"]["valid_fraction_a"] == pytest.approx(0.9)
    # Half the pixels are off by 5 cm: the RMSE of the whole image is 5 cm / sqrt(2).
    assert r["all"]["depth_residual_m"]["rmse"] == pytest.approx(0.05 / np.sqrt(2))


def test_z_depth_frames_are_compared_as_radial_distance():
    radial = np.full(CAM.shape, 2.0)
    a = DepthFrame(distance_m=CAM.radial_to_z(radial), kind="z", camera=CAM)
    res = cmp.residual_maps(a, frame(radial))["depth_residual_m"]
    assert np.allclose(res, 0.0, atol=1e-12)


def test_rois_and_alignment_errors():
    with pytest.raises(TofhilError, match="x0,y0,x1,y1"):
        cmp.parse_roi("1,2,3", CAM.shape)
    with pytest.raises(TofhilError, match="outside"):
        cmp.parse_roi("0,0,21,5", CAM.shape)
    other = CameraModel.from_fov(10, 10, 60.0)
    with pytest.raises(TofhilError, match="same camera"):
        cmp.compare_frames(frame(np.ones(CAM.shape)), DepthFrame(np.ones((10, 10)), "radial", other))


def test_mean_depth_frame_averages_valid_frames_only():
    d1, d2, d3 = (np.full(CAM.shape, v) for v in (1.0, 2.0, 3.0))
    v3 = np.ones(CAM.shape, bool)
    v3[0, 0] = False
    frames = [frame(d1, valid=np.ones(CAM.shape, bool)), frame(d2), frame(d3, valid=v3)]
    mean, std = cmp.mean_depth_frame(frames)
    assert mean.radial_m[1, 1] == pytest.approx(2.0) and std[1, 1] == pytest.approx(np.sqrt(2 / 3))
    assert mean.radial_m[0, 0] == pytest.approx(1.5) and std[0, 0] == pytest.approx(0.5)
    # Valid in fewer than half the frames -> invalid in the mean.
    mean2, _ = cmp.mean_depth_frame([frame(d1, valid=~np.ones(CAM.shape, bool) | (np.arange(20) < 5)),
                                     frame(d2, valid=np.zeros(CAM.shape, bool)),
                                     frame(d3, valid=np.zeros(CAM.shape, bool))])
    assert not mean2.valid.any()
