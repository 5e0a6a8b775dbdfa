"""Padded FFT convolution: linear, never circular, and its adjoint (the one home of it).

Images are zero-padded for the FFT so that no wrap-around reaches the retained pixels
(:func:`fft_shape`); :class:`PaddedConvolution` keeps a kernel's transform for images of one
size. :func:`_separable` is the other way to apply a separable kernel: products with
``[H, H]`` and ``[W, W]`` matrices.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.fft as sfft


def fft_shape(image_shape: tuple[int, int], kernel_shape: tuple[int, int],
              kernel_center: tuple[int, int] | None = None) -> tuple[int, int]:
    """Smallest fast FFT size for which the retained ``[H, W]`` window of the circular
    convolution equals the linear one (the wrapped part lands only on discarded samples).

    For a kernel of length ``kh`` with centre ``ch`` the output sample ``q`` is the full
    linear convolution's ``q + ch``; aliasing stays out of ``[ch, ch + H - 1]`` when
    ``N >= H + max(ch, kh - 1 - ch)``.
    """
    out = []
    for n, kn, c in zip(image_shape, kernel_shape, kernel_center or (kernel_shape[0] // 2, kernel_shape[1] // 2)):
        out.append(sfft.next_fast_len(int(n + max(c, kn - 1 - c)), real=False))
    return out[0], out[1]


@dataclass
class PaddedConvolution:
    """``S -> S * kernel`` (linear, 'same' size, kernel centre at ``center``) for images of a
    fixed shape, with the kernel's FFT computed once. ``adjoint`` is the correlation,
    ``regularised_inverse`` the (Wiener-like) inverse filter on the same padded grid.

    ``fft_size``: a padded grid larger than the least one without wrap-around (for both
    directions), e.g. for an inverse filter, whose own impulse response has long tails."""

    kernel: np.ndarray
    image_shape: tuple[int, int]
    center: tuple[int, int] | None = None
    workers: int | None = None
    fft_size: tuple[int, int] | None = None

    def __post_init__(self) -> None:
        self.kernel = np.asarray(self.kernel)
        if self.kernel.ndim != 2:
            raise ValueError(f"kernel must be 2-D, got shape {self.kernel.shape}")
        if self.center is None:
            self.center = (self.kernel.shape[0] // 2, self.kernel.shape[1] // 2)
        self.fshape = fft_shape(self.image_shape, self.kernel.shape, self.center)
        # Adjoint kernel: the flipped kernel with the mirrored centre; it needs its own size.
        kh, kw = self.kernel.shape
        self._adj_center = (kh - 1 - self.center[0], kw - 1 - self.center[1])
        self.fshape_adj = fft_shape(self.image_shape, self.kernel.shape, self._adj_center)
        if self.fft_size is not None:
            size = (int(self.fft_size[0]), int(self.fft_size[1]))
            if any(n < max(a, b) for n, a, b in zip(size, self.fshape, self.fshape_adj)):
                raise ValueError(f"fft_size {size} is smaller than the padding the kernel needs "
                                 f"({self.fshape}, adjoint {self.fshape_adj})")
            self.fshape = self.fshape_adj = size

    @cached_property
    def _kfft(self) -> np.ndarray:
        return sfft.fft2(self.kernel, s=self.fshape)

    @cached_property
    def _kfft_adj(self) -> np.ndarray:
        return sfft.fft2(np.conj(self.kernel[::-1, ::-1]), s=self.fshape_adj)

    def _run(self, s: np.ndarray, kfft: np.ndarray, fshape: tuple[int, int], center: tuple[int, int]) -> np.ndarray:
        s = np.asarray(s)
        if s.shape[-2:] != tuple(self.image_shape):
            raise ValueError(f"image is {s.shape[-2:]}, operator built for {tuple(self.image_shape)}")
        real = not np.iscomplexobj(s) and not np.iscomplexobj(self.kernel)
        h, w = self.image_shape
        cy, cx = center
        if real:
            sf = sfft.rfft2(s, s=fshape, workers=self.workers)
            kf = kfft[..., : fshape[1] // 2 + 1]
            full = sfft.irfft2(sf * kf, s=fshape, workers=self.workers)
        else:
            sf = sfft.fft2(s, s=fshape, workers=self.workers)
            full = sfft.ifft2(sf * kfft, workers=self.workers)
        return full[..., cy:cy + h, cx:cx + w]

    def __call__(self, s: np.ndarray) -> np.ndarray:
        return self._run(s, self._kfft, self.fshape, self.center)  # type: ignore[arg-type]

    def regularised_inverse(self, s: np.ndarray, mu: float = 0.0) -> np.ndarray:
        """``F^-1[conj(K) F[S] / (|K|^2 + mu)]`` on the padded grid, cropped to the image
        (complex): the inverse of the convolution for ``mu = 0`` where ``K`` does not vanish, a
        Wiener-like regularised inverse for ``mu > 0``. ``conj(K)`` is the adjoint's transfer
        function (the flipped conjugate kernel), so the window kept is the adjoint's."""
        s = np.asarray(s)
        if s.shape[-2:] != tuple(self.image_shape):
            raise ValueError(f"image is {s.shape[-2:]}, operator built for {tuple(self.image_shape)}")
        h, w = self.image_shape
        cy, cx = self._adj_center
        kf = self._kfft_adj
        sf = sfft.fft2(s, s=self.fshape_adj, axes=(-2, -1), workers=self.workers)
        full = sfft.ifft2(sf * kf / (np.abs(kf) ** 2 + mu), axes=(-2, -1), workers=self.workers)
        return full[..., cy:cy + h, cx:cx + w]

    def adjoint(self, s: np.ndarray) -> np.ndarray:
        return self._run(s, self._kfft_adj, self.fshape_adj, self._adj_center)


def convolve(s: np.ndarray, kernel: np.ndarray, center: tuple[int, int] | None = None) -> np.ndarray:
    """Linear 2-D convolution of images ``[..., H, W]`` (real or complex) with ``kernel``,
    same-size output: ``out[q] = sum_j kernel[j] s[q - (j - center)]``. ``center`` is the
    kernel's origin index (default: its middle). Zero-padded FFT, no wrap-around."""
    s = np.asarray(s)
    return PaddedConvolution(kernel, s.shape[-2:], center)(s)


def correlate(s: np.ndarray, kernel: np.ndarray, center: tuple[int, int] | None = None) -> np.ndarray:
    """The adjoint of :func:`convolve` (correlation with the conjugate kernel)."""
    s = np.asarray(s)
    return PaddedConvolution(kernel, s.shape[-2:], center).adjoint(s)


def flip_image(s: np.ndarray) -> np.ndarray:
    """Mirror ``[..., H, W]`` in both axes (pixel ``p`` -> ``(W-1, H-1) - p``)."""
    return np.asarray(s)[..., ::-1, ::-1]


def _separable(s: np.ndarray, my: np.ndarray, mx: np.ndarray) -> np.ndarray:
    """``My @ S @ Mx^T`` on images ``[..., H, W]`` (real matrices; complex images done as two
    real products, which BLAS runs at real speed)."""
    # Contiguous operands: numpy's matmul on a strided view (the real part of a complex array)
    # bypasses BLAS and is far slower (docs/effects.md, figures behind implementation choices).
    if np.iscomplexobj(s):
        out = np.empty(s.shape, dtype=np.complex128)
        out.real = my @ np.ascontiguousarray(s.real) @ mx.T
        out.imag = my @ np.ascontiguousarray(s.imag) @ mx.T
        return out
    return my @ np.ascontiguousarray(s) @ mx.T
