"""The free-form parts of the one PSF type: a radial profile (heavy tails), shift-variant
(field-dependent) lobes; checked against sums and convolutions computed here."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import fftconvolve

from tofhil.errors import InputFileError
from tofhil.sim.straylight import GaussianLobe, RadialProfile, StrayLightOperator, StrayLightPSF

H, W = 30, 40


def _profile() -> RadialProfile:
    r = tuple(float(x) for x in 2.0 ** np.arange(0, 7))  # 1 .. 64 px
    return RadialProfile(r, tuple(1e-3 * np.asarray(r) ** -3.0))  # an r^-3 tail


def _kernel_here(p: RadialProfile, half: int) -> np.ndarray:
    """k(r): linear interpolation in log r, written independently (np.interp)."""
    y, x = np.mgrid[-half:half + 1, -half:half + 1].astype(float)
    r = np.hypot(x, y)
    lr = np.log(np.maximum(r, 1e-12))
    k = np.interp(lr, np.log(p.radii_px), p.values, left=p.values[0], right=0.0)
    k[r > p.radii_px[-1]] = 0.0
    k[half, half] = 0.0
    return k


def test_radial_weight_is_the_kernel_sum_over_the_plane():
    p = _profile()
    assert p.weight == pytest.approx(_kernel_here(p, 70).sum(), rel=1e-9)


def test_radial_profile_scatters_as_a_convolution_and_conserves_energy():
    p = _profile()
    psf = StrayLightPSF(radial=p)
    rng = np.random.default_rng(1)
    s = rng.random((H, W)) + 1j * rng.random((H, W))
    got = StrayLightOperator(psf, (H, W)).apply(s)
    k = _kernel_here(p, 70)
    conv = fftconvolve(s, k, mode="full")[70:70 + H, 70:70 + W]
    np.testing.assert_allclose(got, (1 - p.weight) * s + conv, rtol=1e-9, atol=1e-12)
    # A point far from the edges: the light the radial lobe keeps on the sensor + the direct part.
    pt = np.zeros((H, W))
    pt[15, 20] = 1.0
    out = StrayLightOperator(psf, (H, W)).apply(pt)
    inside = k[70 - 15:70 - 15 + H, 70 - 20:70 - 20 + W].sum()
    assert out.sum() == pytest.approx(1 - p.weight + inside, rel=1e-9)


def test_field_lobe_grows_towards_the_corner_and_conserves_energy():
    # On axis the lobe moves nothing; at rho^2 it moves 0.2 rho^2 of the light (sigma 1 px,
    # so a point 6 px from the edges loses nothing past them).
    psf = StrayLightPSF(gaussians=(GaussianLobe(0.0, 1.0, 1.0, 0.2),))
    op = StrayLightOperator(psf, (H, W), ((W - 1) / 2, (H - 1) / 2))
    half_diag2 = ((W - 1) / 2) ** 2 + ((H - 1) / 2) ** 2
    moved = []
    for y, x in ((15, 20), (6, 6), (23, 33)):
        pt = np.zeros((H, W))
        pt[y, x] = 1.0
        out = op.apply(pt)
        r2 = ((x - (W - 1) / 2) ** 2 + (y - (H - 1) / 2) ** 2) / half_diag2
        assert out.sum() == pytest.approx(1.0, abs=1e-8)
        assert out.sum() - out[y, x] == pytest.approx(0.2 * r2 * (1 - _centre_mass(1.0)), rel=1e-6, abs=1e-12)
        moved.append(out.sum() - out[y, x])
    assert moved[0] < 0.01 * moved[1]  # (15, 20) is half a pixel from the principal point


def _centre_mass(sigma: float) -> float:
    """Fraction of a unit 2-D Gaussian falling on its own (centre) pixel."""
    from scipy.special import erf

    return float(erf(0.5 / (sigma * np.sqrt(2)))) ** 2


def test_free_form_parameters_round_trip_and_refuse_bad_values(tmp_path):
    psf = StrayLightPSF(gaussians=(GaussianLobe(0.02, 3.0, 2.0, -0.01),), radial=_profile(), veil=0.01)
    back = StrayLightPSF.from_params(psf.to_params())
    assert back == psf
    path = psf.save(tmp_path / "p.json")
    assert StrayLightPSF.load(path) == psf
    for bad in ({"radii_px": [2, 1], "values": [0, 0]}, {"radii_px": [1, 2], "values": [-1, 0]},
                {"radii_px": [1], "values": [1, 2]}, {"radii": [1], "values": [1]}):
        with pytest.raises(InputFileError, match="radial"):
            StrayLightPSF.from_params({"radial": bad})
