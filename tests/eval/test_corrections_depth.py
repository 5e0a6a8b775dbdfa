"""Depth filters (SR4000 study): jump edges, thresholds and smoothing, on closed forms and real data."""

from __future__ import annotations

import numpy as np
import pytest

from tofhil.camera import CameraModel
from tofhil.eval.corrections import depth_filters as df

from tests.real_data import ADI, need

CAM = CameraModel.from_fov(64, 48, 60.0)


def plane_radial(z_of_xy) -> np.ndarray:
    """Radial distance of each pixel ray to the surface z = f(x/z, y/z) (closed form per ray)."""
    r = CAM.rays
    return z_of_xy(r[..., 0] / r[..., 2], r[..., 1] / r[..., 2]) / r[..., 2]


def step_scene() -> tuple[np.ndarray, np.ndarray]:
    """Fronto-parallel planes at z = 1 m (columns < 32) and z = 2 m (columns >= 32)."""
    d = plane_radial(lambda x, y: np.ones_like(x))
    d[:, 32:] *= 2.0
    return d, np.ones(d.shape, bool)


def test_distance_criterion_flags_both_sides_of_a_step_only():
    d, v = step_scene()
    flag = df.jump_edge_distance(d, v, max_step_m=0.1)
    cols = np.flatnonzero(flag.any(axis=0))
    assert cols.tolist() == [31, 32]
    assert flag[:, 31].all() and flag[:, 32].all()
    # Within each plane neighbouring distances differ by far less than 0.1 m: no flags.
    assert not df.jump_edge_distance(d, v, max_step_m=0.1)[:, :31].any()


def test_angle_criterion_separates_steps_from_tilted_planes():
    d, v = step_scene()
    flag = df.jump_edge_angle(d, v, CAM, min_angle_deg=10.0)
    assert set(np.flatnonzero(flag.any(axis=0))) == {31, 32}
    # A plane z = 1 + tan(70 deg) X, tilted about the vertical axis: the angle alpha between
    # a pixel's ray and the plane grows from 0 (grazing) on the right to ~50 deg on the left.
    # Every segment to a neighbour lies in the plane, so it is at least alpha from the ray:
    # no pixel with alpha > 10 deg may be flagged. Near the centre row the horizontal
    # neighbour's segment is the plane's steepest line, alpha itself: grazing pixels are.
    t = np.tan(np.radians(70.0))
    dd = plane_radial(lambda x, y: 1.0 / (1.0 - t * x))
    ok = np.isfinite(dd) & (dd > 0) & (dd < 100)
    n = np.array([-t, 0.0, 1.0]) / np.hypot(t, 1.0)
    alpha = np.degrees(np.arcsin(np.abs(CAM.rays @ n)))
    f = df.jump_edge_angle(dd, ok, CAM, min_angle_deg=10.0)
    assert not f[ok & (alpha > 10.0)].any()
    centre = np.zeros(ok.shape, bool)
    centre[22:26, 1:-1] = True
    graze = ok & centre & (alpha < 8.0)
    assert graze.sum() > 5 and f[graze].all()


def test_amplitude_threshold():
    amp = np.array([[0.5, 2.0], [3.0, np.nan]])
    v = np.array([[True, True], [False, True]])
    assert df.amplitude_threshold(amp, v, 1.0).tolist() == [[False, True], [False, False]]


def test_gaussian_smoothing_keeps_a_constant_and_reduces_white_noise_by_the_closed_form():
    rng = np.random.default_rng(3)
    h, w, sigma = 200, 200, 2.0
    valid = np.ones((h, w), bool)
    valid[50:60, 50:60] = False  # a hole: its garbage must not leak
    d = np.where(valid, 1.5, 1e6)
    s = df.gaussian_smooth(d, valid, sigma)
    assert np.allclose(s[valid], 1.5)
    noise = rng.normal(0, 0.01, (h, w))
    s = df.gaussian_smooth(1.5 + noise, np.ones((h, w), bool), sigma)
    inner = (slice(20, -20), slice(20, -20))
    # Var of a unit-sum 2-D Gaussian average of white noise: sum g^2 = 1 / (4 pi sigma^2).
    expected = 0.01 / (2 * np.sqrt(np.pi) * sigma)
    assert np.std(s[inner]) == pytest.approx(expected, rel=0.08)


def test_median_removes_isolated_outliers_exactly_on_a_plane():
    rng = np.random.default_rng(4)
    d = np.full((40, 40), 2.0)
    idx = rng.choice(d.size, 30, replace=False)
    d.flat[idx] = 0.5  # flying pixels, isolated
    v = np.ones(d.shape, bool)
    s = df.median_smooth(d, v, 3)
    # Any 3x3 window holds at most a few outliers out of 9: the median is the plane.
    isolated = True
    for i in idx:
        r, c = divmod(int(i), 40)
        win = d[max(r - 1, 0):r + 2, max(c - 1, 0):c + 2]
        isolated &= (win == 0.5).sum() <= win.size // 2
    assert isolated
    assert np.allclose(s, 2.0)
    with pytest.raises(ValueError):
        df.median_smooth(d, v, 4)


def test_bilateral_keeps_the_step_and_smooths_the_flat_parts():
    rng = np.random.default_rng(5)
    d, v = step_scene()
    noisy = d + rng.normal(0, 0.005, d.shape)
    s = df.bilateral_smooth(noisy, v, sigma_px=1.5, sigma_m=0.02)
    # Edge columns stay on their own side (a Gaussian would average 1 m and 2 m there).
    assert np.abs(s[:, 31] - d[:, 31]).max() < 0.02 and np.abs(s[:, 32] - d[:, 32]).max() < 0.02
    g = df.gaussian_smooth(noisy, v, 1.5)
    assert np.abs(g[:, 31] - d[:, 31]).max() > 0.1
    flat = (slice(5, -5), slice(5, 25))
    assert np.std(s[flat] - d[flat]) < 0.5 * np.std(noisy[flat] - d[flat])


def _real(name: str) -> np.ndarray:
    return np.fromfile(need(ADI / name), "<u2").reshape(512, 512).astype(np.float64)


def test_real_adi_plane_jump_edges_sit_on_the_cable_and_smoothing_reduces_roughness():
    from scipy.ndimage import binary_dilation

    d = _real("near_plane_depth.bin") / 1000.0  # mm -> m (README)
    ir = _real("near_plane_ir.bin")
    v = d > 0
    top = np.zeros(d.shape, bool)
    top[:380] = True  # above the cable bundle at the bottom: a plane crossed by one cable
    cable = (ir < 0.5 * np.median(ir[top])) & top
    flag = df.jump_edge_distance(d, v, max_step_m=0.01) & top
    near_cable = binary_dilation(cable, iterations=3)
    assert 0.001 < flag.mean() < 0.05
    assert (flag & near_cable).sum() / flag.sum() > 0.8  # the cable covers < 10 % of the area
    assert cable[top].mean() < 0.1

    d, v = d[40:180, 20:220], v[40:180, 20:220]  # a clear part of the plane and a margin

    def roughness(img: np.ndarray) -> float:
        p = img[20:120, 20:180]  # image rows 60..159, columns 40..199: no cable
        h, w = p.shape
        y, x = np.mgrid[0:h, 0:w]
        a = np.stack([np.ones(p.size), x.ravel(), y.ravel(), x.ravel() ** 2, y.ravel() ** 2, (x * y).ravel()], 1)
        c, *_ = np.linalg.lstsq(a, p.ravel(), rcond=None)
        return float(np.std(p.ravel() - a @ c))

    r0 = roughness(d)
    assert roughness(df.gaussian_smooth(d, v, 1.5)) < 0.9 * r0
    assert roughness(df.median_smooth(d, v, 5)) < r0
    assert roughness(df.bilateral_smooth(d, v, 1.5, 0.01)) < r0
