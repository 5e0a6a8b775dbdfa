"""ICP and cloud distances against closed forms and known transforms."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tofhil.errors import TofhilError
from tofhil.eval.metrics.matching import (apply_transform, chamfer, cloud_metrics, fscore, hausdorff, icp,
                                  precision_recall)

from tests.real_data import adi_office_points


def grid_plane(n: int = 40, z: float = 0.0, step: float = 0.01) -> np.ndarray:
    u, v = np.meshgrid(np.arange(n) * step, np.arange(n) * step)
    return np.c_[u.ravel(), v.ravel(), np.full(u.size, z)]


def rigid(yaw_deg: float, pitch_deg: float, t) -> np.ndarray:
    a, b = np.radians(yaw_deg), np.radians(pitch_deg)
    rz = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
    ry = np.array([[math.cos(b), 0, math.sin(b)], [0, 1, 0], [-math.sin(b), 0, math.cos(b)]])
    m = np.eye(4)
    m[:3, :3] = rz @ ry
    m[:3, 3] = t
    return m


def corner_scene(rng: np.random.Generator, n: int) -> np.ndarray:
    """Floor, two walls and a box: every rigid motion is observable."""
    k = rng.integers(0, 4, n)
    u, v = rng.uniform(0, 1, n), rng.uniform(0, 1, n)
    pts = np.where((k == 0)[:, None], np.c_[u, v, 0 * u],
                   np.where((k == 1)[:, None], np.c_[0 * u, u, v],
                            np.where((k == 2)[:, None], np.c_[u, 0 * u, v],
                                     np.c_[0.5 + 0.2 * u, 0.5 + 0.2 * v, np.full(n, 0.3)])))
    return pts


def test_parallel_planes_closed_form():
    a, b = grid_plane(z=0.0), grid_plane(z=0.003)
    # Same xy sampling, 3 mm apart: every nearest neighbour is the point straight across.
    assert chamfer(a, b) == pytest.approx(0.003, abs=1e-12)
    h, p95 = hausdorff(a, b)
    assert h == pytest.approx(0.003) and p95 == pytest.approx(0.003)
    assert fscore(a, b, 0.004) == 1.0 and fscore(a, b, 0.002) == 0.0


def test_hausdorff_max_vs_p95_with_one_outlier():
    a, b = grid_plane(), grid_plane()
    a_out = np.vstack([a, [0.2, 0.2, 0.5]])           # 0.5 m above the plane's interior
    h, p95 = hausdorff(a_out, b)
    assert h == pytest.approx(0.5)
    assert p95 == pytest.approx(0.0)                  # 1 of 1601 points does not move p95
    # Chamfer: one term of 0.5 in the a->B mean, zero elsewhere.
    assert chamfer(a_out, b) == pytest.approx(0.5 * 0.5 / a_out.shape[0])


def test_fscore_precision_recall_hand_computed():
    b = grid_plane(n=40)                              # 1600 reference points
    a = b[:1200]                                      # measured covers 3/4 of the reference
    p, r = precision_recall(a, b, 0.001)
    assert p == 1.0
    # Reference rows 30..39 are 1 cm from the measured rows (> 1 mm): recall = 1200/1600.
    assert r == pytest.approx(0.75)
    assert fscore(a, b, 0.001) == pytest.approx(2 * 0.75 / 1.75)
    with pytest.raises(TofhilError, match="threshold"):
        fscore(a, b, 0.0)


def test_icp_recovers_known_transform_with_noise_and_outliers():
    rng = np.random.default_rng(4)
    target = corner_scene(rng, 20000)
    truth = rigid(2.0, -1.0, [0.02, -0.015, 0.01])
    source = apply_transform(corner_scene(rng, 15000), np.linalg.inv(truth))
    source += rng.normal(scale=0.002, size=source.shape)
    source = np.vstack([source, rng.uniform(-0.5, 1.5, size=(1500, 3))])   # 10 % outliers
    res = icp(source, target, max_distance=0.08, kernel="tukey")
    err = np.linalg.inv(truth) @ res.transformation
    assert np.linalg.norm(err[:3, 3]) < 1.5e-3
    assert math.degrees(math.acos(min(1.0, (np.trace(err[:3, :3]) - 1) / 2))) < 0.1
    assert 0.85 < res.fitness < 0.97                   # the outliers mostly find no partner
    assert res.inlier_rmse < 0.02


def test_icp_exact_copy_and_init():
    rng = np.random.default_rng(8)
    target = corner_scene(rng, 5000)
    truth = rigid(-3.0, 2.0, [0.05, 0.02, -0.03])
    source = apply_transform(target, np.linalg.inv(truth))
    res = icp(source, target, 0.2, kernel="huber", init=truth)   # start at the answer: stay
    np.testing.assert_allclose(res.transformation, truth, atol=1e-6)
    assert res.fitness == 1.0 and res.inlier_rmse < 1e-6
    with pytest.raises(TofhilError, match="kernel"):
        icp(source, target, 0.2, kernel="bogus")
    with pytest.raises(TofhilError, match="4x4"):
        icp(source, target, 0.2, init=np.eye(3))
    with pytest.raises(TofhilError, match="no finite points"):
        icp(np.full((3, 3), np.nan), target, 0.2)


def test_cloud_metrics_bundle_and_alignment():
    rng = np.random.default_rng(9)
    ref = corner_scene(rng, 8000)
    truth = rigid(1.0, 0.5, [0.01, 0.0, 0.005])
    meas = apply_transform(ref, np.linalg.inv(truth))
    before = cloud_metrics(meas, ref, threshold=0.002)
    after = cloud_metrics(meas, ref, threshold=0.002, align=True, max_distance=0.05)
    assert set(before) >= {"chamfer", "hausdorff", "hausdorff_p95", "precision", "recall", "fscore"}
    assert before["chamfer"] == pytest.approx(chamfer(meas, ref))
    assert before["fscore"] == pytest.approx(fscore(meas, ref, 0.002))
    assert after["chamfer"] < 1e-6 and after["fscore"] == 1.0
    np.testing.assert_allclose(after["icp"]["transformation"], truth, atol=1e-5)


def test_icp_on_real_tof_frame():
    pts = adi_office_points(step=6)
    target, source0 = pts[0::2], pts[1::2]       # interleaved halves: no shared points
    truth = rigid(1.5, -1.0, [0.03, -0.02, 0.02])
    res = icp(apply_transform(source0, np.linalg.inv(truth)), target, max_distance=0.1)
    err = np.linalg.inv(truth) @ res.transformation
    assert np.linalg.norm(err[:3, 3]) < 3e-3
    assert math.degrees(math.acos(min(1.0, (np.trace(err[:3, :3]) - 1) / 2))) < 0.2
    assert res.fitness > 0.95


def test_tukey_kernel_rejects_ghost_surface_that_biases_l2():
    # 6000 "multipath ghost" points 3 cm above the floor: least squares is pulled up by
    # ~2 cm, the Tukey kernel (scale 1 cm) gives them zero weight.
    rng = np.random.default_rng(4)
    target = corner_scene(rng, 20000)
    truth = rigid(1.0, 0.5, [0.01, -0.01, 0.005])
    ghost = np.c_[rng.uniform(0, 1, 6000), rng.uniform(0, 1, 6000), np.full(6000, 0.03)]
    src = apply_transform(np.vstack([corner_scene(rng, 15000), ghost]), np.linalg.inv(truth))

    def err(kernel: str) -> float:
        r = icp(src, target, 0.08, kernel=kernel, kernel_k=0.01)
        return float(np.linalg.norm((np.linalg.inv(truth) @ r.transformation)[:3, 3]))

    assert err("tukey") < 1e-3
    assert err("l2") > 5e-3
