"""The fast path of Gaussian lobes and a veil (the form diagnosis fits).

:class:`GaussianBlur` transforms one image stack once and blurs it by any widths;
:func:`apply_lobes` applies a PSF of lobes and a veil with that transform, keeping the last
transform and the last result by image content (:mod:`tofhil.content_cache`): a fit that
changes only the PSF, or only what acts after the stray light, transforms its light once.
"""

from __future__ import annotations

import numpy as np
import scipy.fft as sfft

from tofhil.content_cache import LRUCache, content_digest
from tofhil.sim.straylight.convolution import fft_shape
from tofhil.sim.straylight.kernels import _pixel_gauss_1d
from tofhil.sim.straylight.psf import StrayLightPSF


class GaussianBlur:
    """Pixel-integrated Gaussians of any widths and shifts applied to ONE image stack
    ``[..., H, W]`` (what a calibration does for every basis lobe): the image's FFT is taken
    once and each kernel's FFT is the outer product of two 1-D FFTs. ``blur(sx, sy,
    offset)`` equals ``convolve(s, gaussian_kernel(shape, sx, sy, offset), (H-1, W-1))``."""

    def __init__(self, s: np.ndarray, workers: int | None = None, *, single: bool = False) -> None:
        """``single``: transforms in single precision (half the time and memory; relative
        error ~1e-7 of the image's largest value, for a stray-light term of a few per cent of
        the light far below any measurement noise)."""
        s = np.asarray(s)
        self.h, self.w = s.shape[-2:]
        self.workers = workers
        self.ctype = np.complex64 if single else np.complex128
        self.fshape = fft_shape((self.h, self.w), (2 * self.h - 1, 2 * self.w - 1), (self.h - 1, self.w - 1))
        self.stack = s.shape[:-2]
        flat = s.reshape((-1, self.h, self.w))
        # An image that is zero everywhere (the ambient light of a scene without any) blurs to
        # zero: neither transformed nor blurred.
        self._lit = np.flatnonzero([np.any(x) for x in flat])
        if len(self._lit) == len(flat):
            lit = flat.astype(self.ctype, copy=False) if single else flat
        else:  # (one copy of the lit images, in the transform's precision)
            lit = np.empty((len(self._lit), self.h, self.w), dtype=self.ctype if single else flat.dtype)
            for j, i in enumerate(self._lit):
                lit[j] = flat[i]
        self._sf = sfft.fft2(lit, s=self.fshape, axes=(-2, -1), workers=workers)

    def __call__(self, sigma_x_px: float, sigma_y_px: float,
                 offset_px: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
        fy = sfft.fft(_pixel_gauss_1d(np.arange(-(self.h - 1), self.h, dtype=np.float64), offset_px[1],
                                      sigma_y_px), n=self.fshape[0]).astype(self.ctype, copy=False)
        fx = sfft.fft(_pixel_gauss_1d(np.arange(-(self.w - 1), self.w, dtype=np.float64), offset_px[0],
                                      sigma_x_px), n=self.fshape[1]).astype(self.ctype, copy=False)
        # Inverse along x, crop to the sensor's columns, then along y: half the work. One image
        # of the stack at a time: the padded temporaries are one image's, not the stack's
        # (each 1-D transform is the same).
        out = np.zeros((int(np.prod(self.stack)), self.h, self.w), dtype=self.ctype)
        for sf, i in zip(self._sf, self._lit):
            t = sfft.ifft(sf * fx, axis=-1, workers=self.workers)[:, self.w - 1:2 * self.w - 1]
            out[i] = sfft.ifft(t * fy[:, None], axis=-2, workers=self.workers)[self.h - 1:2 * self.h - 1, :]
        return out.reshape(self.stack + (self.h, self.w))


def lobes_only(psf: StrayLightPSF) -> bool:
    """True for a PSF of shift-invariant Gaussian lobes and a veil only (the form diagnosis
    fits): :func:`apply_lobes` applies it with the image's transform kept."""
    return (psf.radial is None and (psf.measured is None or psf.measured_scale == 0)
            and not any(g.weight for g in psf.ghosts)
            and not any(g.field_weight or g.field_weight4 for g in psf.gaussians))


#: The transforms of the last few images :func:`apply_lobes` scattered, by content: a fit
#: that changes only the PSF (every stray-light Jacobian column) transforms its image once.
_BLURS_KEPT = 1
_BLURS = LRUCache(_BLURS_KEPT)


#: The last results of :func:`apply_lobes`, by image content and PSF: a fit of an effect that
#: acts after the stray light, with the stray light held, scatters the same light every time.
_SCATTERED_KEPT = 1
_SCATTERED = LRUCache(_SCATTERED_KEPT)


def _blur_of(s: np.ndarray, key: str | None = None) -> GaussianBlur:
    key = content_digest(s) if key is None else key
    blur = _BLURS.get(key)
    if blur is None:
        _BLURS.make_room()  # (before the new one: never two frames' worth at once)
        blur = GaussianBlur(s, single=True)
        _BLURS.put(key, blur)
    return blur


def apply_lobes(psf: StrayLightPSF, s: np.ndarray) -> np.ndarray:
    """``keep * S + h * S`` on images ``[..., H, W]`` for a PSF of Gaussian lobes and a veil
    (:func:`lobes_only`): each lobe a separable blur of the image's transform (computed once
    per image content, :class:`GaussianBlur`, in single precision), the veil ``veil * sum(S) /
    (H W)`` on every pixel (its kernel is constant over every shift between two pixels). The
    operator of :class:`StrayLightOperator` to ~1e-7 of the scattered light."""
    if not lobes_only(psf):
        raise ValueError("apply_lobes takes Gaussian lobes and a veil only")
    s = np.asarray(s)
    h, w = s.shape[-2:]
    lobes = [g for g in psf.gaussians if g.weight]
    image = content_digest(s)
    key = (image, psf.keep, psf.veil, tuple((g.weight, g.sigma_x_px, g.sigma_y_px) for g in lobes))
    done = _SCATTERED.get(key)
    if done is not None:
        return done.copy()
    _SCATTERED.make_room()  # (a miss: the kept result is another light's or PSF's)
    out = np.multiply(s, psf.keep, dtype=np.result_type(s.dtype, np.float64))  # (no copy of s first)
    if lobes:
        blur = _blur_of(s, image)
        for g in lobes:
            b = blur(g.sigma_x_px, g.sigma_y_px)
            out += g.weight * (b if np.iscomplexobj(out) else b.real)
    if psf.veil:
        out += (psf.veil / (h * w)) * s.sum(axis=(-2, -1), keepdims=True)
    _SCATTERED.put(key, out.copy())
    return out
