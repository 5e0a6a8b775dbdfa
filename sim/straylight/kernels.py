"""Stray-light kernels: pixel-integrated Gaussians, the shift-invariant kernel of a PSF, the
ghost's kernel, the free radial lobe's hat functions, and the 1-D pixel-Gaussian matrices of
the separable method.

Shift-invariant kernels live on the ``[2H-1, 2W-1]`` shift grid (every shift between two
sensor pixels), centred at ``(H-1, W-1)``.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
from scipy.special import erf

if TYPE_CHECKING:
    from tofhil.sim.straylight.psf import Ghost, StrayLightPSF


def _pixel_gauss_1d(x: np.ndarray, mu: float, sigma: float) -> np.ndarray:
    """Integral of a unit Gaussian N(mu, sigma) over the pixels [x - 1/2, x + 1/2]."""
    s = max(float(sigma), 1e-9) * math.sqrt(2.0)
    return 0.5 * (erf((x + 0.5 - mu) / s) - erf((x - 0.5 - mu) / s))


def gaussian_kernel(shape: tuple[int, int], sigma_x_px: float, sigma_y_px: float,
                    offset_px: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """Pixel-integrated unit Gaussian on the ``[2H-1, 2W-1]`` shift grid, centred at
    ``(H-1, W-1) + offset``. Sums to 1 minus the tails beyond the grid (light leaving the
    sensor)."""
    h, w = shape
    ys = np.arange(-(h - 1), h, dtype=np.float64)
    xs = np.arange(-(w - 1), w, dtype=np.float64)
    gy = _pixel_gauss_1d(ys, offset_px[1], sigma_y_px)
    gx = _pixel_gauss_1d(xs, offset_px[0], sigma_x_px)
    return np.outer(gy, gx)


def _measured_normalised(img: np.ndarray, center: tuple[int, int] | None) -> tuple[np.ndarray, tuple[int, int]]:
    p = np.asarray(img, dtype=np.float64)
    total = p.sum()
    if center is None:
        cy, cx = np.unravel_index(int(np.argmax(p)), p.shape)
        center = (int(cx), int(cy))
    return p / total, center


def psf_kernel(psf: StrayLightPSF, shape: tuple[int, int]) -> np.ndarray:
    """The shift-invariant scattering kernel on the ``[2H-1, 2W-1]`` grid, centred at
    ``(H-1, W-1)``: Gaussians + veil + the measured PSF's scattered part, each times its
    weight. Excludes the ghost (not shift-invariant) and the ``delta`` / ``-W delta`` term."""
    h, w = shape
    k = np.zeros((2 * h - 1, 2 * w - 1))
    for g in psf.gaussians:
        if g.weight != 0:
            k += g.weight * gaussian_kernel(shape, g.sigma_x_px, g.sigma_y_px)
    if psf.veil:
        k += psf.veil / (h * w)  # every shift: each pixel gets veil * sum(S) / (H W)
    if psf.radial is not None:
        k += np.tensordot(np.asarray(psf.radial.values), radial_hats(psf.radial.radii_px, *shift_grid(shape),
                                                                     psf.radial.aspect), axes=1)
    if psf.measured is not None and psf.measured_scale != 0:
        p, (mcx, mcy) = _measured_normalised(psf.measured, psf.measured_center_px)
        p = p.copy()
        p[mcy, mcx] = 0.0  # the peak is the direct light, not scatter
        # Paste the measured image onto the shift grid, cropping what lies beyond it.
        ph, pw = p.shape
        y0, x0 = (h - 1) - mcy, (w - 1) - mcx
        ys, xs = max(0, y0), max(0, x0)
        ye, xe = min(2 * h - 1, y0 + ph), min(2 * w - 1, x0 + pw)
        if ye > ys and xe > xs:
            k[ys:ye, xs:xe] += psf.measured_scale * p[ys - y0:ye - y0, xs - x0:xe - x0]
    return k


def ghost_kernel(ghost: Ghost, shape: tuple[int, int], center_px: tuple[float, float]) -> np.ndarray:
    """Kernel of a ghost on the flipped image: ``ghost(S) = convolve(flip(S), ghost_kernel)``.

    Light at pixel ``p`` goes to ``2c - p``. With ``S'`` the image flipped in both axes
    (``S'[p'] = S[(W-1, H-1) - p']``), ``2c - p = p' + d`` with ``d = 2c - (W-1, H-1)``, so
    the ghost is ``S'`` convolved with the blur Gaussian shifted by ``d`` (sub-pixel: the
    pixel-integrated Gaussian, a box for ``sigma_px = 0``).
    """
    return ghost.weight * gaussian_kernel(shape, ghost.sigma_px, ghost.sigma_px, ghost_shift(shape, center_px))


def ghost_shift(shape: tuple[int, int], center_px: tuple[float, float]) -> tuple[float, float]:
    """``d = 2c - (W-1, H-1)``: the shift of the flipped image that mirrors through ``c``."""
    h, w = shape
    return 2.0 * center_px[0] - (w - 1), 2.0 * center_px[1] - (h - 1)


def radial_hats(radii_px: tuple[float, ...] | np.ndarray, dx: np.ndarray, dy: np.ndarray,
                aspect: float = 1.0) -> np.ndarray:
    """``[n, ...]``: the piecewise-linear-in-``log r`` hat functions of the knots at the shifts
    ``(dx, dy)`` (so ``k = sum_j values_j hat_j``); 0 at ``r = 0`` (the direct pixel), the
    first hat constant inside the first knot, nothing beyond the last."""
    radii = np.asarray(radii_px, dtype=np.float64)
    r = np.hypot(dx, np.asarray(dy) / aspect)
    lr = np.log(np.maximum(r, 1e-12))
    lk = np.log(radii)
    out = np.zeros((radii.size,) + np.shape(r))
    for j in range(radii.size):
        hat = np.zeros(np.shape(r))
        if j > 0:
            up = (lr >= lk[j - 1]) & (lr <= lk[j])
            hat[up] = (lr[up] - lk[j - 1]) / (lk[j] - lk[j - 1])
        else:
            hat[(r > 0) & (lr <= lk[0])] = 1.0
        if j + 1 < radii.size:
            down = (lr > lk[j]) & (lr < lk[j + 1])
            hat[down] = (lk[j + 1] - lr[down]) / (lk[j + 1] - lk[j])
        out[j] = hat
    return out


def radial_hat_sums(radii_px: tuple[float, ...] | np.ndarray, aspect: float = 1.0) -> np.ndarray:
    """Sum of each hat over the infinite pixel plane (the light one unit of ``values_j``
    moves): evaluated on a grid reaching past the last knot."""
    key = (tuple(float(r) for r in radii_px), float(aspect))
    if key not in _HAT_SUMS:
        half = int(math.ceil(max(key[0]) * max(1.0, aspect))) + 1
        y, x = np.mgrid[-half:half + 1, -half:half + 1].astype(np.float64)
        _HAT_SUMS[key] = radial_hats(key[0], x, y, aspect).sum(axis=(1, 2))
    return _HAT_SUMS[key]


_HAT_SUMS: dict[tuple[tuple[float, ...], float], np.ndarray] = {}


def shift_grid(shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """``(dx, dy)`` of the ``[2H-1, 2W-1]`` shift grid (centre ``(H-1, W-1)``)."""
    h, w = shape
    dy, dx = np.mgrid[-(h - 1):h, -(w - 1):w].astype(np.float64)
    return dx, dy


def field_rho2(shape: tuple[int, int], center_px: tuple[float, float]) -> np.ndarray:
    """``rho^2``: squared distance from the principal point over the squared half diagonal."""
    h, w = shape
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    return ((x - center_px[0]) ** 2 + (y - center_px[1]) ** 2) / (((w - 1) / 2) ** 2 + ((h - 1) / 2) ** 2)


def _pixel_matrix(n: int, sigma: float, *, mirror_about: float | None = None,
                  magnification: float = -1.0) -> np.ndarray:
    """``[n, n]`` matrix of the pixel-integrated 1-D Gaussian: ``M[q, p] = g(q - p)`` (Toeplitz),
    or with ``mirror_about = c`` the ghost's ``M[q, p] = g(q - (c + m (p - c)))`` (``m = -1``:
    Hankel, the mirror)."""
    q = np.arange(n, dtype=np.float64)[:, None]
    p = np.arange(n, dtype=np.float64)[None, :]
    if mirror_about is None:
        shift = q - p
    else:
        shift = q - (mirror_about + magnification * (p - mirror_about))
        # A source pixel lands on |m| pixels: its footprint widens the blur (a box's variance).
        sigma = math.sqrt(sigma * sigma + max(magnification * magnification - 1.0, 0.0) / 12.0)
    return _pixel_gauss_1d(shift, 0.0, sigma)
