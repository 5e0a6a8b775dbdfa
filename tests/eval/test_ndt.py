"""NDT grid, likelihoods and scores against hand-computed closed forms."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tofhil.errors import TofhilError
from tofhil.eval.metrics.ndt import (NDTGrid, cell_likelihood, d2d_score, gauss_params, multi_resolution,
                             ndt_score, pcl_point_scores, trilinear_likelihood, trilinear_weights)

from tests.real_data import adi_office_points

R = 0.5   # cell size used by the hand-made grids


def star(centre, ax: float, ay: float, az: float) -> np.ndarray:
    """6 points centre +- a_i e_i: mean = centre, unbiased cov = diag(2 a_i^2 / 5)."""
    c = np.asarray(centre, dtype=float)
    e = np.eye(3) * np.array([ax, ay, az])[:, None]
    return np.concatenate([c + e, c - e])


def centre(ijk) -> np.ndarray:
    return (np.asarray(ijk, dtype=float) + 0.5) * R


# ---------------------------------------------------------------- grid construction
def test_grid_mean_cov_and_min_points():
    pts = np.concatenate([star(centre((0, 0, 0)), 0.1, 0.1, 0.1),
                          star(centre((2, 0, 0)), 0.1, 0.05, 0.1)[:5]])  # 5 points: dropped
    g = NDTGrid.from_points(pts, R, min_points=6)
    assert g.cells == 1
    np.testing.assert_allclose(g.means[0], centre((0, 0, 0)), atol=1e-15)
    np.testing.assert_allclose(g.covs[0], np.eye(3) * 2 * 0.1 ** 2 / 5, atol=1e-15)
    np.testing.assert_allclose(g.icovs[0] @ g.covs[0], np.eye(3), atol=1e-12)
    assert NDTGrid.from_points(pts, R, min_points=5).cells == 2


def test_eigenvalue_floor_closed_form():
    # Eigenvalues 2a^2/5 = 0.004, 2b^2/5 = 1e-5 and 0 (a flat, thin cell): both small
    # ones rise to 1 % of the largest, the largest is untouched.
    pts = star(centre((1, 1, 1)), 0.1, 0.005, 0.0)
    g = NDTGrid.from_points(pts, R, eig_floor=0.01)
    lmax = 2 * 0.1 ** 2 / 5
    np.testing.assert_allclose(np.diag(g.covs[0]), [lmax, 0.01 * lmax, 0.01 * lmax], rtol=1e-12, atol=1e-18)
    # No floor: an eigenvalue above the floor is kept exactly.
    pts2 = star(centre((1, 1, 1)), 0.1, 0.05, 0.03)
    g2 = NDTGrid.from_points(pts2, R, eig_floor=0.01)
    np.testing.assert_allclose(np.diag(g2.covs[0]), 2 * np.array([0.1, 0.05, 0.03]) ** 2 / 5, rtol=1e-12)


def test_grid_cells_anchor_at_origin_and_negative_coordinates():
    pts = star(centre((-3, 2, -1)), 0.1, 0.1, 0.1)
    g = NDTGrid.from_points(pts, R)
    np.testing.assert_array_equal(g.ijk[0], [-3, 2, -1])
    assert g.lookup(np.array([[-3, 2, -1], [3, 2, -1], [-3, 2, 1]])).tolist() == [0, -1, -1]


def test_sparse_lookup_for_far_apart_cells():
    # Two cells 17 km apart exceed the dense table: the sorted-key path must agree.
    far = np.concatenate([star(centre((0, 0, 0)), 0.1, 0.1, 0.1),
                          star(centre((20000, 20000, 20000)), 0.1, 0.1, 0.1)])
    g = NDTGrid.from_points(far, R)
    assert g._table is None and g.cells == 2
    p = np.array([centre((0, 0, 0)), centre((20000, 20000, 20000)), centre((5, 0, 0))])
    np.testing.assert_allclose(cell_likelihood(g, p), [1.0, 1.0, 0.0])


# ---------------------------------------------------------------- likelihoods
def test_cell_likelihood_closed_form():
    g = NDTGrid.from_points(star(centre((0, 0, 0)), 0.1, 0.1, 0.1), R)
    s2 = 2 * 0.1 ** 2 / 5
    d = np.array([0.03, -0.02, 0.05])
    p = centre((0, 0, 0)) + d
    assert cell_likelihood(g, p[None])[0] == pytest.approx(math.exp(-d @ d / (2 * s2)), rel=1e-12)
    # A point in an empty neighbouring cell gets 0 from the containing-cell rule.
    assert cell_likelihood(g, centre((1, 0, 0))[None])[0] == 0.0


def test_mean_likelihood_of_own_gaussian_is_2_to_minus_1_5():
    # Points drawn from the cell's own Gaussian: q^T C^-1 q ~ chi2(3), and
    # E[exp(-chi2_3 / 2)] = (1 + 1)^(-3/2) = 0.35355 (moment generating function).
    rng = np.random.default_rng(11)
    mean, sig = np.array([5.0, 5.0, 5.0]), np.array([0.3, 0.2, 0.1])
    ref = mean + rng.normal(size=(200000, 3)) * sig
    cloud = mean + rng.normal(size=(50000, 3)) * sig
    s = ndt_score(ref, cloud, cell_size=10.0)
    assert s.cells == 1
    assert s.mean_likelihood == pytest.approx(2 ** -1.5, abs=0.004)


def test_trilinear_weights_hand_cases():
    ijk, w = trilinear_weights(np.array([centre((2, 3, 4))]), R)
    assert w[0].max() == pytest.approx(1.0) and w[0].sum() == pytest.approx(1.0)
    np.testing.assert_array_equal(ijk[0, np.argmax(w[0])], [2, 3, 4])

    mid = 0.5 * (centre((2, 3, 4)) + centre((3, 3, 4)))       # halfway along x
    ijk, w = trilinear_weights(mid[None], R)
    got = {tuple(c): x for c, x in zip(ijk[0].tolist(), w[0]) if x > 1e-12}
    assert got == pytest.approx({(2, 3, 4): 0.5, (3, 3, 4): 0.5})

    p = centre((0, 0, 0)) + np.array([0.25, 0.25, 0.0]) * R   # quarter step in x and y
    ijk, w = trilinear_weights(p[None], R)
    got = {tuple(c): x for c, x in zip(ijk[0].tolist(), w[0]) if x > 1e-12}
    assert got == pytest.approx({(0, 0, 0): 0.5625, (1, 0, 0): 0.1875, (0, 1, 0): 0.1875, (1, 1, 0): 0.0625})

    corner = np.array([[R, R, R]])                             # shared corner of 8 cells
    ijk, w = trilinear_weights(corner, R)
    np.testing.assert_allclose(w[0], np.full(8, 0.125))
    assert sorted(map(tuple, ijk[0].tolist())) == [(i, j, k) for i in (0, 1) for j in (0, 1) for k in (0, 1)]


def test_trilinear_likelihood_hand_computed():
    # Two neighbouring cells along x with different isotropic spreads.
    a0, a1 = 0.1, 0.15
    pts = np.concatenate([star(centre((0, 0, 0)), a0, a0, a0), star(centre((1, 0, 0)), a1, a1, a1)])
    g = NDTGrid.from_points(pts, R)
    s0, s1 = 2 * a0 ** 2 / 5, 2 * a1 ** 2 / 5
    # At 0.4 of the way from centre 0 to centre 1: weights 0.6 / 0.4, distances 0.4R / 0.6R.
    p = centre((0, 0, 0)) + np.array([0.4 * R, 0, 0])
    want = 0.6 * math.exp(-(0.4 * R) ** 2 / (2 * s0)) + 0.4 * math.exp(-(0.6 * R) ** 2 / (2 * s1))
    assert trilinear_likelihood(g, p[None])[0] == pytest.approx(want, rel=1e-12)
    # The containing-cell rule uses cell 0 alone.
    assert cell_likelihood(g, p[None])[0] == pytest.approx(math.exp(-(0.4 * R) ** 2 / (2 * s0)), rel=1e-12)
    # At a cell centre the trilinear value is that cell's own likelihood (1 at its mean).
    assert trilinear_likelihood(g, centre((1, 0, 0))[None])[0] == pytest.approx(1.0)
    # Off-axis: 0.25 R up in y, so the y-neighbours (empty) take 25 % of the weight.
    q = p + np.array([0, 0.25 * R, 0])
    dy2 = (0.25 * R) ** 2
    want_q = 0.75 * (0.6 * math.exp(-((0.4 * R) ** 2 + dy2) / (2 * s0))
                     + 0.4 * math.exp(-((0.6 * R) ** 2 + dy2) / (2 * s1)))
    assert trilinear_likelihood(g, q[None])[0] == pytest.approx(want_q, rel=1e-12)


def test_trilinear_is_continuous_across_cell_boundaries():
    rng = np.random.default_rng(3)
    pts = rng.normal(size=(20000, 3)) * [0.6, 0.6, 0.2]
    g = NDTGrid.from_points(pts, R)
    x = np.linspace(-0.99, 0.99, 4001)
    line = np.c_[x, np.full_like(x, 0.13), np.full_like(x, 0.07)]
    tri = trilinear_likelihood(g, line)
    cell = cell_likelihood(g, line)
    # Step size 5e-4 m: the interpolated curve has no jumps, the per-cell one does.
    assert np.abs(np.diff(tri)).max() < 0.01
    assert np.abs(np.diff(cell)).max() > 0.05


# ---------------------------------------------------------------- PCL score, NVTL
def test_gauss_params_fit_the_mixture_at_0_and_1_sigma():
    # Magnusson eq. 6.8: -log(c1 exp(-x^2/2) + c2) is matched by d1 exp(-d2 x^2/2) + d3
    # at x = 0 and x = 1, with c1 = 10 (1 - r), c2 = r / R^3, d3 = -log c2.
    for cell, ratio in [(1.0, 0.55), (0.1, 0.55), (0.3, 0.2)]:
        d1, d2 = gauss_params(cell, ratio)
        c1, c2 = 10 * (1 - ratio), ratio / cell ** 3
        for x in (0.0, 1.0):
            assert d1 * math.exp(-d2 * x * x / 2) - math.log(c2) == pytest.approx(
                -math.log(c1 * math.exp(-x * x / 2) + c2), rel=1e-12)
        assert d1 < 0


def test_pcl_score_single_cell_hand_computed():
    g = NDTGrid.from_points(star(centre((0, 0, 0)), 0.1, 0.1, 0.1), R)
    d1, d2 = gauss_params(R, 0.55)
    s2 = 2 * 0.1 ** 2 / 5
    d = np.array([0.02, 0.01, -0.03])
    pts = np.array([centre((0, 0, 0)), centre((0, 0, 0)) + d, centre((0, 0, 0)) + [R * 1.01, 0, 0]])
    total, best, has = pcl_point_scores(g, pts, 0.55)
    want1 = -d1 * math.exp(-d2 * (d @ d / s2) / 2)
    np.testing.assert_allclose(total, [-d1, want1, 0.0], rtol=1e-12)
    np.testing.assert_allclose(best, total, rtol=1e-12)
    assert has.tolist() == [True, True, False]   # third point: mean farther than R
    s = ndt_score(g, pts)
    assert s.score_per_point == pytest.approx((-d1 + want1) / 3, rel=1e-12)
    assert s.nvtl == pytest.approx((-d1 + want1) / 2, rel=1e-12)   # mean over points with a neighbour


def test_pcl_score_sums_and_nvtl_takes_max_over_neighbours():
    pts = np.concatenate([star(centre((0, 0, 0)), 0.1, 0.1, 0.1), star(centre((1, 0, 0)), 0.1, 0.1, 0.1)])
    g = NDTGrid.from_points(pts, R)
    d1, d2 = gauss_params(R, 0.55)
    s2 = 2 * 0.1 ** 2 / 5
    p = centre((0, 0, 0)) + [0.1, 0, 0]      # 0.1 from mean 0, 0.4 from mean 1 (< R)
    t0 = -d1 * math.exp(-d2 * 0.1 ** 2 / s2 / 2)
    t1 = -d1 * math.exp(-d2 * 0.4 ** 2 / s2 / 2)
    total, best, _ = pcl_point_scores(g, p[None], 0.55)
    assert total[0] == pytest.approx(t0 + t1, rel=1e-12)
    assert best[0] == pytest.approx(max(t0, t1), rel=1e-12)


def test_scores_fall_with_misalignment():
    rng = np.random.default_rng(7)
    ref = rng.normal(size=(30000, 3)) * [1.0, 1.0, 0.05]
    cloud = rng.normal(size=(5000, 3)) * [1.0, 1.0, 0.05]
    g = NDTGrid.from_points(ref, 0.25)
    prev = None
    for dz in (0.0, 0.05, 0.1, 0.2):
        s = ndt_score(g, cloud + [0, 0, dz], thresholds=(0.3,))
        cur = (s.score_per_point, s.nvtl, s.mean_likelihood, s.mean_likelihood_trilinear, s.fraction_above[0.3])
        if prev is not None:
            assert all(c < p for c, p in zip(cur, prev))
        prev = cur


def test_ndt_score_accepts_points_and_grid_alike():
    rng = np.random.default_rng(1)
    ref = rng.normal(size=(5000, 3))
    cloud = ref[:1000] + rng.normal(scale=0.02, size=(1000, 3))
    a = ndt_score(ref, cloud, cell_size=0.5).to_dict()
    b = ndt_score(NDTGrid.from_points(ref, 0.5), cloud).to_dict()
    assert a == b
    with pytest.raises(TofhilError, match="cell_size"):
        ndt_score(ref, cloud)
    with pytest.raises(TofhilError, match="cell_size"):
        ndt_score(NDTGrid.from_points(ref, 0.5), cloud, cell_size=0.25)
    with pytest.raises(TofhilError, match="N x 3"):
        ndt_score(ref, cloud[:, :2], cell_size=0.5)


def test_multi_resolution_equals_single_calls():
    rng = np.random.default_rng(2)
    ref = rng.normal(size=(8000, 3))
    cloud = ref[:2000] + 0.05
    m = multi_resolution(ref, cloud, cell_sizes=(0.25, 0.5, 1.0))
    assert list(m) == [0.25, 0.5, 1.0]
    for r, s in m.items():
        assert s.to_dict() == ndt_score(ref, cloud, cell_size=r).to_dict()
    assert [s.cell_size for s in m.values()] == [0.25, 0.5, 1.0]


# ---------------------------------------------------------------- D2D
def test_d2d_closed_form_two_cells():
    sa, sb, shift = 0.1, 0.15, np.array([0.03, -0.02, 0.01])
    ga = NDTGrid.from_points(star(centre((0, 0, 0)), sa, sa, sa), R)
    gb = NDTGrid.from_points(star(centre((0, 0, 0)) + shift, sb, sb, sb), R)
    d1, d2 = gauss_params(R, 0.55)
    m = shift @ shift / (2 * sa ** 2 / 5 + 2 * sb ** 2 / 5)
    s = d2d_score(ga, gb)
    assert s.pairs == 1 and s.cells_b == 1
    assert s.score == pytest.approx(-d1 * math.exp(-d2 * m / 2), rel=1e-12)
    assert s.mean_similarity == pytest.approx(math.exp(-m / 2), rel=1e-12)


def test_d2d_identical_grids_and_shift():
    rng = np.random.default_rng(5)
    ref = rng.normal(size=(20000, 3)) * [1, 1, 0.1]
    g = NDTGrid.from_points(ref, 0.5)
    same = d2d_score(g, g)
    assert same.mean_similarity == pytest.approx(1.0)
    moved = d2d_score(g, NDTGrid.from_points(ref + [0, 0, 0.1], 0.5))
    assert moved.score < same.score and moved.mean_similarity < 0.99


# ---------------------------------------------------------------- real data
def test_real_tof_frame_self_consistency():
    pts = adi_office_points(step=4)
    assert pts.shape[0] > 10000
    ref, cloud = pts[0::2], pts[1::2]          # two interleaved halves of the same frame
    s = ndt_score(ref, cloud, cell_size=0.1)
    moved = ndt_score(ref, cloud + [0, 0, 0.05], cell_size=0.1)
    assert s.cells > 100
    # A sample of the cell's own Gaussian has E[exp(-chi2_3 / 2)] = 2**-1.5 = 0.35; real
    # surfaces (flat, heavy-tailed noise, edges) sit near or below that, far above 0.
    assert 0.15 < s.mean_likelihood < 0.5
    assert s.fraction_above[0.1] > 0.3
    assert moved.score_per_point < 0.6 * s.score_per_point
    assert moved.nvtl < s.nvtl and moved.mean_likelihood_trilinear < s.mean_likelihood_trilinear


def test_fused_pass_equals_separate_functions():
    rng = np.random.default_rng(12)
    ref = rng.normal(size=(20000, 3)) * [1.0, 0.8, 0.3]
    cloud = rng.normal(size=(5000, 3)) * [1.1, 0.9, 0.35]
    g = NDTGrid.from_points(ref, 0.4)
    s = ndt_score(g, cloud, outlier_ratio=0.4)
    np.testing.assert_allclose(s.likelihood, cell_likelihood(g, cloud), rtol=0, atol=1e-12)
    np.testing.assert_allclose(s.likelihood_trilinear, trilinear_likelihood(g, cloud), rtol=0, atol=1e-12)
    total, best, has = pcl_point_scores(g, cloud, 0.4)
    np.testing.assert_allclose(s.point_score, total, rtol=0, atol=1e-12)
    np.testing.assert_allclose(s.nearest_score, best, rtol=0, atol=1e-12)
    assert s.likelihood_trilinear.max() > 0.5 and s.likelihood.max() > 0.5


def test_per_point_arrays_follow_input_rows():
    rng = np.random.default_rng(13)
    ref = rng.normal(size=(5000, 3))
    cloud = ref[:100].copy()
    cloud[[3, 50]] = np.nan
    s = ndt_score(ref, cloud, cell_size=0.5)
    clean = ndt_score(ref, cloud[np.isfinite(cloud).all(1)], cell_size=0.5)
    assert s.likelihood.shape == (100,) and s.n_points == 98
    assert np.isnan(s.likelihood_trilinear[[3, 50]]).all()
    np.testing.assert_array_equal(np.delete(s.likelihood_trilinear, [3, 50]), clean.likelihood_trilinear)
    assert s.to_dict() == clean.to_dict()


def _brute_grid(pts: np.ndarray, r: float, min_points: int = 6, floor: float = 0.01) -> dict:
    """Cells from scratch with Python loops (test reference only)."""
    cells: dict[tuple[int, int, int], list] = {}
    for p in pts:
        cells.setdefault(tuple(int(v) for v in np.floor(p / r)), []).append(p)
    out = {}
    for k, members in cells.items():
        x = np.array(members)
        if len(x) < min_points:
            continue
        cov = np.cov(x.T)                     # unbiased, like PCL
        lam, vec = np.linalg.eigh(cov)
        lam = np.maximum(lam, floor * lam[2])
        out[k] = (x.mean(0), np.linalg.inv(vec @ np.diag(lam) @ vec.T))
    return out


def test_trilinear_and_d2d_against_brute_force_loops():
    rng = np.random.default_rng(21)
    r = 0.5
    ref = rng.normal(size=(3000, 3)) * [0.8, 0.8, 0.4]
    cloud = rng.normal(size=(150, 3)) * [0.8, 0.8, 0.4]
    brute = _brute_grid(ref, r)
    g = NDTGrid.from_points(ref, r)
    assert g.cells == len(brute)
    want = []
    for p in cloud:
        u = p / r - 0.5                       # cell centres at integer u
        lo = np.floor(u).astype(int)
        total = 0.0
        for di in (0, 1):
            for dj in (0, 1):
                for dk in (0, 1):
                    k = (lo[0] + di, lo[1] + dj, lo[2] + dk)
                    w = 1.0
                    for a, d in enumerate((di, dj, dk)):
                        f = u[a] - lo[a]
                        w *= f if d else 1.0 - f
                    if k in brute:
                        mean, icov = brute[k]
                        q = p - mean
                        total += w * math.exp(-0.5 * q @ icov @ q)
        want.append(total)
    np.testing.assert_allclose(trilinear_likelihood(g, cloud), want, rtol=1e-9, atol=1e-12)

    # D2D: every (a, b) pair with means within R, from scratch.
    other = rng.normal(size=(3000, 3)) * [0.8, 0.8, 0.4] + [0.05, 0, 0]
    gb = NDTGrid.from_points(other, r)
    d1, d2 = gauss_params(r, 0.55)
    total, pairs = 0.0, 0
    for mb, cb in zip(gb.means, gb.covs):
        for ma, ca in zip(g.means, g.covs):
            mu = mb - ma
            if mu @ mu <= r * r:
                total += -d1 * math.exp(-0.5 * d2 * mu @ np.linalg.solve(ca + cb, mu))
                pairs += 1
    s = d2d_score(g, gb)
    assert s.pairs == pairs
    assert s.score == pytest.approx(total, rel=1e-10)


def test_trilinear_weights_reproduce_linear_functions():
    # Trilinear interpolation is exact for affine functions: sum_k w_k centre_k = p,
    # with non-negative weights summing to 1, anywhere (negative coordinates included).
    rng = np.random.default_rng(17)
    p = rng.uniform(-3, 3, size=(2000, 3))
    ijk, w = trilinear_weights(p, R)
    assert (w >= 0).all()
    np.testing.assert_allclose(w.sum(1), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.einsum("nk,nkd->nd", w, (ijk + 0.5) * R), p, atol=1e-12)


@pytest.mark.parametrize("cell", [0.05, 0.2])
def test_compiled_point_loop_equals_vectorised_terms(cell: float) -> None:
    """The compiled per-point loop and the vectorised 27-offset pass give the same per-point
    terms, for points inside the reference, beside it and far outside the dense table."""
    from tofhil.eval.metrics.ndt import _all_point_terms, _point_terms

    rng = np.random.default_rng(5)
    ref = rng.normal(scale=[0.5, 0.3, 0.05], size=(20000, 3)) + [0.2, -0.1, 1.0]
    pts = np.concatenate([ref[:3000] + rng.normal(scale=0.01, size=(3000, 3)),
                          rng.uniform(-2, 2, (2000, 3)), [[50.0, 50.0, 50.0], [-40.0, 0.0, 1.0]]])
    grid = NDTGrid.from_points(ref, cell)
    assert grid._table is not None
    fast = _point_terms(grid, pts, 0.55)
    slow = _all_point_terms(grid, pts, 0.55)
    for a, b in zip(fast[:4], slow[:4]):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-13)
    np.testing.assert_array_equal(fast[4], slow[4])
    assert fast[4].sum() > 2000 and not fast[4][-2:].any()
