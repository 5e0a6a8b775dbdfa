"""The fast stray-light path (Gaussian lobes and a veil, the form diagnosis fits): the same
operator as the padded-FFT StrayLightOperator and as a direct double sum, and the image's
transform reused only for the same image content."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import erf

from tofhil.sim import straylight as SL
from tofhil.sim.straylight import StrayLightOperator, StrayLightPSF, apply_lobes, lobes_only


def _direct(s: np.ndarray, weight: float, sx: float, sy: float, veil: float, keep: float) -> np.ndarray:
    """keep*S + sum_q S[q] (weight * G(p - q) + veil / (H W)), G the pixel-integrated Gaussian."""
    h, w = s.shape

    def g1(d, sig):
        a = sig * np.sqrt(2.0)
        return 0.5 * (erf((d + 0.5) / a) - erf((d - 0.5) / a))

    y, x = np.mgrid[0:h, 0:w]
    out = keep * s.astype(complex)
    for qy in range(h):
        for qx in range(w):
            out += s[qy, qx] * (weight * g1(y - qy, sy) * g1(x - qx, sx) + veil / (h * w))
    return out


def test_lobes_equal_direct_sum_and_operator():
    rng = np.random.default_rng(1)
    s = rng.random((9, 13)) + 1j * rng.random((9, 13))
    psf = StrayLightPSF.from_params({"weight": 0.06, "sigma_px": 2.5, "sigma_y_px": 1.5, "veil": 0.01})
    assert lobes_only(psf)
    fast = apply_lobes(psf, s)
    ref = _direct(s, 0.06, 2.5, 1.5, 0.01, psf.keep)
    # single-precision transforms: ~1e-7 of the scattered light
    assert np.abs(fast - ref).max() < 1e-6 * np.abs(ref - psf.keep * s).max()
    op = StrayLightOperator(psf, s.shape).apply(s)
    assert np.abs(fast - op).max() < 1e-6 * np.abs(op - psf.keep * s).max()
    # a real image stays real
    r = s.real
    assert apply_lobes(psf, r).dtype == np.float64
    assert np.allclose(apply_lobes(psf, r), StrayLightOperator(psf, r.shape).apply(r), rtol=0, atol=1e-7)


def test_transform_reused_only_for_same_content():
    rng = np.random.default_rng(2)
    s = rng.random((2, 20, 24))
    SL._BLURS.clear()
    SL._SCATTERED.clear()
    a = StrayLightPSF.from_params({"weight": 0.04, "sigma_px": 3.0})
    b = StrayLightPSF.from_params({"weight": 0.05, "sigma_px": 5.0, "veil": 0.002})
    apply_lobes(a, s)
    apply_lobes(b, s.copy())  # same content, another array: one transform
    assert len(SL._BLURS) == 1
    first = next(iter(SL._BLURS))
    s2 = s.copy()
    s2[0, 3, 4] += 1.0
    out = apply_lobes(b, s2)  # changed content: its own transform, its own result
    assert len(SL._BLURS) == 1 and next(iter(SL._BLURS)) != first
    assert np.allclose(out, StrayLightOperator(b, s2.shape[-2:]).apply(s2), atol=1e-7)


def test_other_forms_are_not_lobes_only():
    assert not lobes_only(StrayLightPSF.from_params({"weight": 0.04, "ghost_weight": 0.01}))
    with pytest.raises(ValueError):
        apply_lobes(StrayLightPSF.from_params({"weight": 0.04, "ghost_weight": 0.01}), np.ones((4, 4)))


def test_same_light_and_psf_give_the_kept_result():
    rng = np.random.default_rng(3)
    s = rng.random((3, 16, 20)) + 1j * rng.random((3, 16, 20))
    psf = StrayLightPSF.from_params({"weight": 0.04, "sigma_px": 3.0, "veil": 0.01})
    a = apply_lobes(psf, s)
    a[0, 0, 0] = 99.0  # a caller changing its result does not change the kept one
    b = apply_lobes(psf, s.copy())
    assert b[0, 0, 0] != 99.0
    assert np.allclose(b, StrayLightOperator(psf, s.shape[-2:]).apply(s), atol=1e-7)
    other = apply_lobes(StrayLightPSF.from_params({"weight": 0.04, "sigma_px": 3.5, "veil": 0.01}), s)
    assert not np.allclose(other, b)


def test_blur_of_a_stack_with_a_dark_image_is_each_image_blurred_alone():
    # the dark image (no ambient light) is skipped: its blur is exactly zero, and the other
    # images' blurs are those of each image on its own, against the direct sum too
    rng = np.random.default_rng(3)
    s = rng.random((3, 30, 40)) + 1j * rng.random((3, 30, 40))
    s[1] = 0.0
    both = SL.GaussianBlur(s)(3.0, 2.0)
    assert both.shape == s.shape and not np.any(both[1])
    for i in (0, 2):
        np.testing.assert_array_equal(both[i], SL.GaussianBlur(s[i])(3.0, 2.0))
        np.testing.assert_allclose(both[i], _direct(s[i], 1.0, 3.0, 2.0, 0.0, 0.0), atol=1e-9 * np.abs(s[i]).sum())
