"""tofhil's NDT scores against PCL 1.13's own NormalDistributionsTransform.

The reference numbers in tests/data/pcl/ were printed by tools/pcl_reference/ndt_reference.cpp
linked against Debian's libpcl 1.13.0 (see tests/data/pcl/README.md): an independent
implementation (PCL's voxel grid, FLANN radius search, Eigen eigen-solver), not our output.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tofhil.eval.metrics.clouds import load_cloud
from tofhil.eval.metrics.ndt import NDTGrid, gauss_params, ndt_score, pcl_score

DATA = Path(__file__).resolve().parents[1] / "data" / "pcl"
SETTINGS = [("r050", 0.5, 0.55, 6), ("r025", 0.25, 0.55, 6), ("r030", 0.3, 0.3, 10)]
TOL = 1e-9   # absolute, on scores and likelihoods in [0, ~1]; measured ~1e-12


def _pcl_cloud(name: str) -> np.ndarray:
    # PCL holds PointXYZ in float32: use exactly those values.
    return load_cloud(DATA / name).astype(np.float32).astype(np.float64)


def _summary(tag: str) -> dict[str, str]:
    lines = (DATA / f"pcl_{tag}_summary.txt").read_text().splitlines()
    return dict(line.split(" ", 1) for line in lines)


@pytest.fixture(scope="module")
def clouds() -> tuple[np.ndarray, np.ndarray]:
    return _pcl_cloud("ref.pcd"), _pcl_cloud("cloud.pcd")


@pytest.mark.parametrize("tag,res,ratio,min_pts", SETTINGS)
def test_scores_match_pcl(clouds, tag, res, ratio, min_pts):
    ref, cloud = clouds
    summ = _summary(tag)
    assert summ["pcl_version"].startswith("1.")
    cell = float(np.float32(res))            # PCL's resolution is a float
    grid = NDTGrid.from_points(ref, cell, min_points=min_pts)
    s = ndt_score(grid, cloud, outlier_ratio=ratio)
    assert grid.cells == int(summ["cells"])
    assert s.n_points == int(summ["n_points"])
    assert s.d1 == pytest.approx(float(summ["d1"]), abs=1e-12)
    assert s.d2 == pytest.approx(float(summ["d2"]), abs=1e-12)
    assert s.score_per_point == pytest.approx(float(summ["score_per_point"]), abs=TOL)
    assert s.nvtl == pytest.approx(float(summ["nvtl"]), abs=TOL)
    assert s.mean_likelihood == pytest.approx(float(summ["mean_likelihood"]), abs=TOL)

    per_point = np.loadtxt(DATA / f"pcl_{tag}_points.txt")
    np.testing.assert_allclose(s.point_score, per_point[:, 0], rtol=0, atol=TOL)
    np.testing.assert_allclose(s.nearest_score, per_point[:, 1], rtol=0, atol=TOL)
    np.testing.assert_allclose(s.likelihood, per_point[:, 3], rtol=0, atol=TOL)
    # Points with no voxel mean within the radius score 0 in both.
    assert np.all(s.point_score[per_point[:, 2] == 0] == 0)
    # The scores are not trivial: most points see a voxel, outliers mostly do not.
    assert 0.5 < per_point[:, 2].mean() < 1.0


@pytest.mark.parametrize("tag,res,ratio,min_pts", SETTINGS)
def test_grid_matches_pcl_voxels(clouds, tag, res, ratio, min_pts):
    ref, _ = clouds
    grid = NDTGrid.from_points(ref, float(np.float32(res)), min_points=min_pts)
    cells = np.loadtxt(DATA / f"pcl_{tag}_cells.txt")
    a = cells[np.lexsort(cells[:, 1:4].T)]
    order = np.lexsort(grid.means.T)
    np.testing.assert_array_equal(a[:, 0].astype(int), grid.counts[order])
    np.testing.assert_allclose(a[:, 1:4], grid.means[order], rtol=0, atol=1e-12)
    np.testing.assert_allclose(a[:, 4:].reshape(-1, 3, 3), grid.covs[order], rtol=0, atol=1e-12)
    # The eigenvalue floor is active on the planar voxels of this scene.
    ev = np.linalg.eigvalsh(grid.covs)
    assert np.any(np.isclose(ev[:, 0], 0.01 * ev[:, 2], rtol=1e-9))


def test_gauss_params_pcl_default():
    # PCL's defaults (resolution 1, outlier ratio 0.55) -- and the r050 file's constants.
    d1, d2 = gauss_params(0.5, 0.55)
    s = _summary("r050")
    assert d1 == pytest.approx(float(s["d1"]), abs=1e-14)
    assert d2 == pytest.approx(float(s["d2"]), abs=1e-14)


@pytest.mark.parametrize("tag,res,ratio,min_pts", SETTINGS)
def test_score_equals_pcl_transformation_likelihood_after_align(clouds, tag, res, ratio, min_pts):
    # PCL registered the cloud itself (align(), several Newton steps) and reported
    # getTransformationLikelihood() for the cloud it transformed, saved as float32 binary.
    ref, _ = clouds
    summ = _summary(tag)
    assert int(summ["aligned_iterations"]) >= 2
    aligned = load_cloud(DATA / f"pcl_{tag}_aligned.pcd")
    grid = NDTGrid.from_points(ref, float(np.float32(res)), min_points=min_pts)
    s = ndt_score(grid, aligned, outlier_ratio=ratio)
    assert s.score_per_point == pytest.approx(float(summ["aligned_likelihood"]), abs=TOL)
    # Registration raised PCL's score above the identity pose's.
    assert float(summ["aligned_likelihood"]) > float(summ["score_per_point"])


@pytest.mark.parametrize("tag,res,ratio,min_pts", SETTINGS)
def test_numpy_score_only_path_matches_pcl(clouds, tag, res, ratio, min_pts):
    """``pcl_score`` (numpy, no compiled kernel: ``tofhil ndt --score-only``) gives PCL's
    number, with the dense lookup table and with the sorted-key lookup alike."""
    import dataclasses

    ref, cloud = clouds
    summ = _summary(tag)
    grid = NDTGrid.from_points(ref, float(np.float32(res)), min_points=min_pts)
    assert grid._table is not None
    assert pcl_score(grid, cloud, outlier_ratio=ratio) == pytest.approx(float(summ["score_per_point"]), abs=TOL)
    sparse = dataclasses.replace(grid, _table=None, _lo_span=None)
    assert pcl_score(sparse, cloud, outlier_ratio=ratio) == pytest.approx(float(summ["score_per_point"]), abs=TOL)
    aligned = load_cloud(DATA / f"pcl_{tag}_aligned.pcd")
    assert pcl_score(grid, aligned, outlier_ratio=ratio) == pytest.approx(float(summ["aligned_likelihood"]), abs=TOL)
