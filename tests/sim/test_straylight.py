"""Stray-light operator: linear (not circular) convolution, energy moved, ghost geometry."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from scipy.signal import convolve2d

from tofhil.errors import InputFileError, TofhilError
from tofhil.sim.straylight import (GaussianLobe, Ghost, StrayLightOperator, StrayLightPSF, apply_stray_light,
                                   convolve, correlate, fft_shape, psf_kernel)


def _rng(seed: int = 0) -> np.random.Generator:
    return np.random.default_rng(seed)


def test_convolve_matches_direct_linear_convolution() -> None:
    rng = _rng(1)
    s = rng.normal(size=(2, 13, 17)) + 1j * rng.normal(size=(2, 13, 17))
    k = rng.normal(size=(7, 4))  # even width, off-centre origin
    center = (2, 1)
    out = convolve(s, k, center)
    for i in range(2):
        full = convolve2d(s[i], k, mode="full")  # independent direct sum
        np.testing.assert_allclose(out[i], full[center[0]:center[0] + 13, center[1]:center[1] + 17],
                                   atol=1e-12)


def test_convolve_real_input_matches_complex_path() -> None:
    rng = _rng(2)
    s = rng.random((11, 9))
    k = rng.random((21, 17))
    np.testing.assert_allclose(convolve(s, k), convolve(s.astype(complex), k).real, atol=1e-12)


def test_no_wrap_around_at_the_edges() -> None:
    # A kernel that moves light one pixel to the left: a point in column 0 leaves the sensor.
    # A circular (unpadded) FFT would put it in the last column instead.
    s = np.zeros((8, 10))
    s[3, 0] = 1.0
    k = np.zeros((3, 3))
    k[1, 0] = 1.0  # shift by -1 column with the centre at (1, 1)
    out = convolve(s, k)
    assert np.abs(out).max() < 1e-14
    s2 = np.zeros((8, 10))
    s2[3, 5] = 1.0
    out2 = convolve(s2, k)
    assert out2[3, 4] == pytest.approx(1.0)
    # Each FFT size is large enough: H + max(c, kh - 1 - c).
    assert fft_shape((8, 10), (15, 19), (7, 9))[0] >= 15


def test_gaussian_moves_the_stated_fraction_and_conserves_energy() -> None:
    h = w = 81
    s = np.zeros((h, w), complex)
    s[40, 40] = 2.0 * np.exp(1j * 0.7)
    weight, sigma = 0.12, 3.0
    psf = StrayLightPSF(gaussians=(GaussianLobe(weight, sigma, sigma),))
    out = apply_stray_light(s, psf)
    # Closed form: the lobe keeps G0 = (P(|x| < 1/2))^2 of its light in the source pixel.
    g0 = math.erf(0.5 / (sigma * math.sqrt(2))) ** 2
    moved = np.abs(out).sum() - np.abs(out[40, 40])
    assert moved == pytest.approx(2.0 * weight * (1 - g0), rel=1e-9)
    assert out.sum() == pytest.approx(s.sum(), rel=1e-12)  # nothing lost: tails stay on the sensor
    # The phase of scattered light is that of its source (a convolution of phasors).
    assert np.allclose(np.angle(out[np.abs(out) > 1e-12]), 0.7)
    # Second moment of the scattered light is sigma^2 (+1/12 from the pixel integration).
    yy, xx = np.mgrid[0:h, 0:w] - 40
    scat = np.abs(out).copy()
    scat[40, 40] -= 2.0 * (1 - weight)
    assert (scat * xx ** 2).sum() / scat.sum() == pytest.approx(sigma ** 2 + 1 / 12, rel=1e-6)


def test_light_scattered_beyond_the_sensor_is_lost() -> None:
    s = np.zeros((81, 21))  # tall: no light leaves at the top or bottom
    s[40, 0] = 1.0  # on the left edge: half of a symmetric lobe falls off the sensor
    psf = StrayLightPSF(gaussians=(GaussianLobe(0.2, 4.0, 4.0),))
    out = apply_stray_light(s, psf)
    g_left = 0.5 * (1 - math.erf(0.5 / (4 * math.sqrt(2))))  # fraction of the lobe left of the pixel
    assert out.sum() == pytest.approx(1.0 - 0.2 * g_left, rel=1e-6)


def test_veil_spreads_uniformly_over_the_whole_sensor() -> None:
    h, w = 12, 16
    s = np.zeros((h, w))
    s[2, 13] = 5.0
    out = apply_stray_light(s, StrayLightPSF(veil=0.3))
    expect = np.full((h, w), 0.3 * 5.0 / (h * w))
    expect[2, 13] += 5.0 * 0.7
    np.testing.assert_allclose(out, expect, atol=1e-12)


def test_ghost_mirrors_through_the_optical_centre() -> None:
    h, w = 48, 64
    s = np.zeros((h, w))
    s[5, 10] = 1.0
    psf = StrayLightPSF(ghosts=(Ghost(0.04, 0.0, (30.0, 20.0)),))
    out = apply_stray_light(s, psf)
    # 2c - p = (60 - 10, 40 - 5) = (50, 35)  (x, y)
    assert out[35, 50] == pytest.approx(0.04, rel=1e-9)
    assert out[5, 10] == pytest.approx(0.96, rel=1e-12)
    out[35, 50] = out[5, 10] = 0.0
    assert np.abs(out).max() < 1e-12
    # A ghost whose mirror point lies outside the sensor is lost.
    s2 = np.zeros((h, w))
    s2[2, 2] = 1.0  # mirror (58, 38) inside; now move the centre so it falls outside
    far = StrayLightPSF(ghosts=(Ghost(0.04, 0.0, (40.0, 30.0)),))
    assert apply_stray_light(s2, far).sum() == pytest.approx(0.96)  # (78, 58) is off the sensor


def test_ghost_default_centre_is_the_principal_point() -> None:
    from tofhil.camera import CameraModel

    cam = CameraModel(width=40, height=30, fx=50, fy=50, cx=24.0, cy=12.5)
    s = np.zeros((30, 40))
    s[4, 10] = 1.0
    out = apply_stray_light(s, StrayLightPSF(ghosts=(Ghost(0.1),)), cam)
    assert out[21, 38] == pytest.approx(0.1)  # 2c - p = (48 - 10, 25 - 4)


@pytest.mark.parametrize("method", ["fft", "separable"])
def test_operator_adjoint_is_the_transpose(method: str) -> None:
    rng = _rng(3)
    shape = (10, 14)
    psf = StrayLightPSF(gaussians=(GaussianLobe(0.05, 1.5, 3.0), GaussianLobe(0.02, 6.0, 6.0)), veil=0.01,
                        ghosts=(Ghost(0.03, 1.0, (6.3, 5.1)), Ghost(0.01, 0.5)))
    op = StrayLightOperator(psf, shape, method=method)
    x = rng.normal(size=shape) + 1j * rng.normal(size=shape)
    y = rng.normal(size=shape) + 1j * rng.normal(size=shape)
    assert np.vdot(y, op.apply(x)) == pytest.approx(np.vdot(op.adjoint(y), x), rel=1e-12)


def test_fft_and_separable_evaluations_agree() -> None:
    # Two independent evaluations of one operator: padded FFT of [2H-1, 2W-1] kernels versus
    # products with Toeplitz/Hankel pixel-Gaussian matrices.
    rng = _rng(9)
    shape = (37, 52)
    psf = StrayLightPSF(gaussians=(GaussianLobe(0.03, 2.5, 7.0), GaussianLobe(0.01, 30.0, 30.0)), veil=0.02,
                        ghosts=(Ghost(0.02, 3.0, (27.3, 16.8)),))
    s = rng.normal(size=(2, *shape)) + 1j * rng.normal(size=(2, *shape))
    a = StrayLightOperator(psf, shape, method="fft").apply(s)
    b = StrayLightOperator(psf, shape, method="separable").apply(s)
    np.testing.assert_allclose(a, b, atol=1e-12)


@pytest.mark.parametrize("method", ["fft", "separable"])
def test_operator_matches_dense_matrix_built_from_its_definition(method: str) -> None:
    # Build (delta + h) as an explicit matrix from the physical description, pixel by pixel.
    h, w = 7, 9
    sig, wg, veil, wgh = 1.2, 0.1, 0.05, 0.02
    cx, cy = 3.5, 3.0
    psf = StrayLightPSF(gaussians=(GaussianLobe(wg, sig, sig),), veil=veil,
                        ghosts=(Ghost(wgh, 0.0, (cx, cy)),))

    def pix(d: float, s: float) -> float:  # pixel-integrated unit Gaussian
        return 0.5 * (math.erf((d + 0.5) / (s * math.sqrt(2))) - math.erf((d - 0.5) / (s * math.sqrt(2))))

    m = np.zeros((h * w, h * w))
    for v in range(h):
        for u in range(w):
            src = v * w + u
            m[src, src] += 1 - (wg + veil + wgh)
            for v2 in range(h):
                for u2 in range(w):
                    m[v2 * w + u2, src] += wg * pix(u2 - u, sig) * pix(v2 - v, sig) + veil / (h * w)
            gu, gv = 2 * cx - u, 2 * cy - v  # mirrored through the centre
            if 0 <= gu < w and 0 <= gv < h and float(gu).is_integer():
                m[int(gv) * w + int(gu), src] += wgh
    x = _rng(4).normal(size=(h, w))
    got = StrayLightOperator(psf, (h, w), method=method).apply(x)
    np.testing.assert_allclose(got.ravel(), m @ x.ravel(), atol=1e-12)


def test_measured_psf_equals_the_parametric_one_it_images(tmp_path) -> None:
    # "Measure" the PSF of a point source with the parametric model, save it, and use the file.
    weight, sigma = 0.08, 2.0
    psf = StrayLightPSF(gaussians=(GaussianLobe(weight, sigma, sigma),))
    point = np.zeros((41, 41))
    point[20, 20] = 1.0
    measured = apply_stray_light(point, psf)
    np.save(tmp_path / "psf.npy", measured)
    loaded = StrayLightPSF.from_params({"psf_file": "psf.npy"}, base_dir=tmp_path)
    assert loaded.total_weight == pytest.approx(weight * (1 - math.erf(0.5 / (sigma * math.sqrt(2))) ** 2),
                                                rel=1e-9)
    s = _rng(5).random((30, 25)) * np.exp(1j * _rng(6).random((30, 25)))
    np.testing.assert_allclose(apply_stray_light(s, loaded), apply_stray_light(s, psf), atol=1e-10)


def test_off_is_identity_and_kernel_weight_is_the_fraction() -> None:
    s = _rng(7).random((9, 11))
    np.testing.assert_array_equal(apply_stray_light(s, {}), s)
    np.testing.assert_array_equal(apply_stray_light(s, {"weight": 0.0, "sigma_px": 5}), s)
    psf = StrayLightPSF.from_params({"weight": 0.1, "sigma_px": 1.0, "veil": 0.02})
    assert psf.total_weight == pytest.approx(0.12)
    # The Gaussian part of the kernel holds its weight; the veil is spread over all (2H-1)(2W-1)
    # shifts at veil / (H W) each, so that every pixel receives veil * sum(S) / (H W).
    assert psf_kernel(psf, (40, 40)).sum() == pytest.approx(0.1 + 0.02 * 79 * 79 / 1600, rel=1e-9)


def test_additive_form_when_not_conserving() -> None:
    s = np.zeros((31, 31))
    s[15, 15] = 1.0
    out = apply_stray_light(s, {"weight": 0.1, "sigma_px": 2.0, "conserve": False})
    assert out.sum() == pytest.approx(1.1, rel=1e-9)


@pytest.mark.parametrize("params, field", [
    ({"wieght": 0.1}, "effects.stray_light.wieght"),
    ({"weight": 1.5}, "effects.stray_light.weight"),
    ({"weight": 0.6, "veil": 0.6}, "effects.stray_light"),
    ({"gaussians": [[0.1, -2, 3]]}, "effects.stray_light.gaussians[0]"),
    ({"psf_file": "nope.npy"}, "effects.stray_light.psf_file"),
    ({"conserve": "yes"}, "effects.stray_light.conserve"),
])
def test_bad_parameters_name_the_field(params: dict, field: str) -> None:
    with pytest.raises(InputFileError) as err:
        StrayLightPSF.from_params(params, source="scene.yaml")
    assert err.value.field == field and err.value.file == "scene.yaml"


def test_correlate_is_adjoint_of_convolve() -> None:
    rng = _rng(8)
    k = rng.normal(size=(5, 6)) + 1j * rng.normal(size=(5, 6))
    x = rng.normal(size=(12, 10)) + 1j * rng.normal(size=(12, 10))
    y = rng.normal(size=(12, 10)) + 1j * rng.normal(size=(12, 10))
    c = (1, 4)
    assert np.vdot(y, convolve(x, k, c)) == pytest.approx(np.vdot(correlate(y, k, c), x), rel=1e-12)


def test_regularised_inverse_is_the_inverse_filter_of_the_centred_kernel() -> None:
    # against the filter written out: the kernel moved to the origin of the padded grid, its
    # transfer function H, F^-1[conj(H) F[S] / (|H|^2 + mu)] cropped to the image
    from scipy import fft as sfft

    from tofhil.sim.straylight import PaddedConvolution

    rng = _rng(4)
    s = rng.normal(size=(2, 11, 14)) + 1j * rng.normal(size=(2, 11, 14))
    k = 0.1 * rng.random((21, 27))
    k[10, 13] += 1.0
    size = (sfft.next_fast_len(11 + 21 - 1), sfft.next_fast_len(14 + 27 - 1))
    kp = np.zeros(size)
    kp[:21, :27] = k
    hf = sfft.fft2(np.roll(kp, (-10, -13), axis=(0, 1)))
    for mu in (0.0, 1e-2):
        ref = sfft.ifft2(sfft.fft2(s, s=size) * np.conj(hf) / (np.abs(hf) ** 2 + mu))[..., :11, :14]
        out = PaddedConvolution(k, (11, 14), (10, 13), fft_size=size).regularised_inverse(s, mu)
        np.testing.assert_allclose(out, ref, rtol=0, atol=1e-13 * np.abs(ref).max())
    with pytest.raises(ValueError):
        PaddedConvolution(k, (11, 14), (10, 13), fft_size=(16, 16))


def test_blur_of_one_image_equals_the_padded_convolution() -> None:
    from tofhil.sim.straylight import GaussianBlur, gaussian_kernel

    s = _rng(9).normal(size=(2, 12, 17)) + 1j * _rng(10).normal(size=(2, 12, 17))
    blur = GaussianBlur(s)
    for sx, sy, off in ((1.5, 2.5, (0.0, 0.0)), (0.0, 0.0, (3.0, -2.0)), (4.0, 4.0, (0.5, 1.5))):
        k = gaussian_kernel((12, 17), sx, sy, off)
        np.testing.assert_allclose(blur(sx, sy, off), convolve(s, k, (11, 16)), atol=1e-12)


def test_scattered_fraction_is_the_largest_column_sum_and_invert_undoes_apply() -> None:
    shape = (9, 11)
    psf = StrayLightPSF(gaussians=(GaussianLobe(0.05, 1.5, 3.0),), veil=0.02,
                        ghosts=(Ghost(0.03, 1.0, (4.2, 3.9)),))
    op = StrayLightOperator(psf, shape)
    # The operator as a matrix, column by column (independent of the adjoint).
    cols = []
    for j in range(shape[0] * shape[1]):
        e = np.zeros(shape[0] * shape[1])
        e[j] = 1.0
        cols.append(op.scatter(e.reshape(shape)).ravel())
    m = np.stack(cols, axis=1)
    assert op.scattered_fraction == pytest.approx(m.sum(axis=0).max(), rel=1e-12)
    assert op.scattered_fraction <= psf.total_weight
    s = _rng(11).random(shape) * np.exp(1j * _rng(12).random(shape))
    np.testing.assert_allclose(op.invert(op.apply(s), iterations=200, tol=0), s, atol=1e-12)


def test_psf_file_keeps_a_measured_image_beside_it(tmp_path) -> None:
    point = np.zeros((15, 15))
    point[7, 7] = 1.0
    img = apply_stray_light(point, StrayLightPSF(gaussians=(GaussianLobe(0.1, 1.5, 1.5),)))
    psf = replace(StrayLightPSF(), measured=img, measured_scale=0.5, conserve=False)
    path = psf.save(tmp_path / "lens.json")
    assert (tmp_path / "lens_measured.npy").is_file()
    back = StrayLightPSF.load(path)
    s = _rng(13).random((20, 18))
    np.testing.assert_allclose(apply_stray_light(s, back), apply_stray_light(s, psf), atol=1e-14)
    with pytest.raises(TofhilError, match="refusing to overwrite"):
        psf.save(path)
