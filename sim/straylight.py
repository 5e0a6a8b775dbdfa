"""Stray light: lens scattering as a convolution of the complex image on the sensor.

Model (Mure-Dubois and Huegli 2007): ``S_meas = (delta + h) * S`` for every modulation
frequency and harmonic (and for the unmodulated light as well: the lens scatters all of it).
``h`` moves a fraction ``W`` of each pixel's light elsewhere:

    h = sum_i w_i G_i  +  veil  +  ghost  +  measured  -  W delta     (conserve = true)

with ``W = sum_i w_i + w_veil + w_ghost + w_measured`` (the *fraction of light scattered*).
Each scattering component is normalised to unit sum over the infinite plane, so a weight is
exactly the fraction of a pixel's light the component moves; light scattered beyond the
sensor edge is lost, as in a real camera. With ``conserve = false`` the scattered light is
added on top (``S + sum_i w_i G_i * S + ...``), Mure-Dubois and Huegli's additive form.

Components:
- Gaussians: weight, ``sigma_x``, ``sigma_y`` in pixels, integrated over each pixel's area
  (erf differences), so small sigmas are exact.
- Veil: a weight spread uniformly over the whole sensor (every pixel receives
  ``w_veil * sum(S) / (H W)``).
- Ghost: a reflection between lens surfaces images the scene mirrored through the optical
  centre ``c``: light at pixel ``p`` leaks to ``2c - p``, blurred by a Gaussian.
- Measured PSF: the image of a point source (any size; its peak pixel is the direct light).

Convolutions are linear, never circular: images are zero-padded for the FFT so that no
wrap-around reaches the retained pixels. The shift-invariant part uses a kernel of shape
``[2H-1, 2W-1]`` (every shift between two sensor pixels) centred at ``(H-1, W-1)``. The
operators are public (``psf_kernel``, ``ghost_kernel``, ``convolve``, ``correlate``,
``StrayLightOperator`` with ``apply``/``scatter``/``adjoint``) so corrections can invert them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
import scipy.fft as sfft
from scipy.special import erf

from tofhil.camera import CameraModel
from tofhil.errors import InputFileError
from tofhil.schema import Schema


@dataclass(frozen=True)
class GaussianLobe:
    """A scattering lobe: ``weight`` of the light spread by a Gaussian (sigmas in pixels)."""

    weight: float
    sigma_x_px: float
    sigma_y_px: float


@dataclass(frozen=True)
class StrayLightPSF:
    """Parameters of the scatter kernel ``h`` (see the module docstring)."""

    gaussians: tuple[GaussianLobe, ...] = ()
    veil: float = 0.0
    ghost_weight: float = 0.0
    ghost_sigma_px: float = 0.0
    #: Optical centre ``(x, y)`` in pixels the ghost mirrors through; None = camera (cx, cy).
    ghost_center_px: tuple[float, float] | None = None
    #: Measured point-source image (normalised on use) and its centre pixel ``(x, y)``.
    measured: np.ndarray | None = field(default=None, compare=False)
    measured_center_px: tuple[int, int] | None = None
    measured_scale: float = 1.0
    conserve: bool = True

    @property
    def measured_fraction(self) -> float:
        """Fraction of light the measured PSF scatters away from its peak pixel (x scale)."""
        if self.measured is None:
            return 0.0
        p, (cx, cy) = _measured_normalised(self.measured, self.measured_center_px)
        return self.measured_scale * float(1.0 - p[cy, cx])

    @property
    def total_weight(self) -> float:
        """``W``: the fraction of each pixel's light that is scattered."""
        return (sum(g.weight for g in self.gaussians) + self.veil + self.ghost_weight
                + self.measured_fraction)

    @property
    def is_identity(self) -> bool:
        return self.total_weight == 0.0

    @classmethod
    def from_params(cls, params: Mapping[str, Any], *, source: str | Path = "<effects>",
                    prefix: str = "effects.stray_light", base_dir: Path | None = None) -> "StrayLightPSF":
        """From the `stray_light` effect's parameters (docs/effects.md): ``weight``,
        ``sigma_px`` (``sigma_y_px``), ``gaussians: [[w, sx, sy], ...]``, ``veil``,
        ``ghost_weight``, ``ghost_sigma_px``, ``ghost_center_px``, ``psf_file``,
        ``psf_center_px``, ``psf_scale``, ``conserve``."""
        return _psf_from_params(params, source=source, prefix=prefix, base_dir=base_dir)


# ---------------------------------------------------------------------------------------------
# Kernels
# ---------------------------------------------------------------------------------------------
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


def ghost_kernel(psf: StrayLightPSF, shape: tuple[int, int], center_px: tuple[float, float]) -> np.ndarray:
    """Kernel of the ghost on the flipped image: ``ghost(S) = convolve(flip(S), ghost_kernel)``.

    Light at pixel ``p`` goes to ``2c - p``. With ``S'`` the image flipped in both axes
    (``S'[p'] = S[(W-1, H-1) - p']``), ``2c - p = p' + d`` with ``d = 2c - (W-1, H-1)``, so
    the ghost is ``S'`` convolved with the blur Gaussian shifted by ``d``.
    """
    h, w = shape
    d = (2.0 * center_px[0] - (w - 1), 2.0 * center_px[1] - (h - 1))
    return psf.ghost_weight * gaussian_kernel(shape, psf.ghost_sigma_px, psf.ghost_sigma_px, d)


# ---------------------------------------------------------------------------------------------
# Padded FFT convolution (linear, no wrap-around)
# ---------------------------------------------------------------------------------------------
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
    fixed shape, with the kernel's FFT computed once. ``adjoint`` is the correlation."""

    kernel: np.ndarray
    image_shape: tuple[int, int]
    center: tuple[int, int] | None = None
    workers: int | None = None

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


def _pixel_matrix(n: int, sigma: float, *, mirror_about: float | None = None) -> np.ndarray:
    """``[n, n]`` matrix of the pixel-integrated 1-D Gaussian: ``M[q, p] = g(q - p)`` (Toeplitz),
    or with ``mirror_about = c`` the ghost's ``M[q, p] = g(q - (2c - p))`` (Hankel)."""
    q = np.arange(n, dtype=np.float64)[:, None]
    p = np.arange(n, dtype=np.float64)[None, :]
    shift = q - p if mirror_about is None else q + p - 2.0 * mirror_about
    return _pixel_gauss_1d(shift, 0.0, sigma)


def _separable(s: np.ndarray, my: np.ndarray, mx: np.ndarray) -> np.ndarray:
    """``My @ S @ Mx^T`` on images ``[..., H, W]`` (real matrices; complex images done as two
    real products, which BLAS runs at real speed)."""
    if np.iscomplexobj(s):
        out = np.empty(s.shape, dtype=np.complex128)
        out.real = my @ s.real @ mx.T
        out.imag = my @ s.imag @ mx.T
        return out
    return my @ s @ mx.T


class StrayLightOperator:
    """``S -> (delta + h) * S`` for images of one size; kernels built once.

    ``apply`` is the forward model, ``scatter`` the stray light alone (``apply(S) = keep * S +
    scatter(S)``, ``keep = 1 - W`` when conserving), ``adjoint`` the transpose (for
    least-squares corrections).

    ``method``: ``"separable"`` evaluates Gaussian lobes and the ghost as products with
    ``[H, H]`` and ``[W, W]`` pixel-Gaussian matrices (exact linear convolution, no padding
    needed) and the veil as a sum; ``"fft"`` (and ``"auto"``) uses the zero-padded FFT with the
    ``[2H-1, 2W-1]`` kernels. A measured PSF always goes through the FFT. Both give the same
    operator; the separable form is faster with a single-threaded BLAS, but multi-threaded
    BLAS on a busy machine makes it unpredictable, so the FFT is the default.
    """

    def __init__(self, psf: StrayLightPSF, shape: tuple[int, int],
                 center_px: tuple[float, float] | None = None, workers: int | None = None,
                 method: str = "auto") -> None:
        if method not in ("auto", "fft", "separable"):
            raise ValueError(f"method must be auto, fft or separable, got {method!r}")
        self.psf = psf
        self.shape = (int(shape[0]), int(shape[1]))
        h, w = self.shape
        c = psf.ghost_center_px or center_px or ((w - 1) / 2.0, (h - 1) / 2.0)
        self.center_px = (float(c[0]), float(c[1]))
        self.keep = 1.0 - psf.total_weight if psf.conserve else 1.0
        self.method = "fft" if method == "auto" else method
        self._conv = self._ghost = None
        self._lobes: list[tuple[float, np.ndarray, np.ndarray]] = []
        self._ghost_mats: tuple[np.ndarray, np.ndarray] | None = None
        if self.method == "separable":
            for g in psf.gaussians:
                if g.weight:
                    self._lobes.append((g.weight, _pixel_matrix(h, g.sigma_y_px), _pixel_matrix(w, g.sigma_x_px)))
            if psf.ghost_weight:
                self._ghost_mats = (_pixel_matrix(h, psf.ghost_sigma_px, mirror_about=self.center_px[1]),
                                    _pixel_matrix(w, psf.ghost_sigma_px, mirror_about=self.center_px[0]))
            if psf.measured is not None and psf.measured_scale != 0:
                # Only the measured part goes through the FFT here.
                k = psf_kernel(StrayLightPSF(measured=psf.measured, measured_center_px=psf.measured_center_px,
                                             measured_scale=psf.measured_scale), self.shape)
                self._conv = PaddedConvolution(k, self.shape, (h - 1, w - 1), workers)
        else:
            k = psf_kernel(psf, self.shape)
            self._conv = PaddedConvolution(k, self.shape, (h - 1, w - 1), workers) if np.any(k) else None
            self._ghost = (PaddedConvolution(ghost_kernel(psf, self.shape, self.center_px), self.shape,
                                             (h - 1, w - 1), workers) if psf.ghost_weight else None)

    def scatter(self, s: np.ndarray) -> np.ndarray:
        """The stray light only: ``h_scatter * S`` (without the ``-W delta`` term)."""
        s = np.asarray(s)
        out = np.zeros(s.shape, dtype=np.result_type(s.dtype, np.float64))
        if self.method == "separable":
            for wgt, my, mx in self._lobes:
                out += wgt * _separable(s, my, mx)
            if self._ghost_mats is not None:
                out += self.psf.ghost_weight * _separable(s, *self._ghost_mats)
            if self.psf.veil:
                h, w = self.shape
                out += (self.psf.veil / (h * w)) * s.sum(axis=(-2, -1), keepdims=True)
        elif self._ghost is not None:
            out += self._ghost(flip_image(s))
        if self._conv is not None:
            out += self._conv(s)
        return out

    def apply(self, s: np.ndarray) -> np.ndarray:
        """``S_meas = keep * S + scatter(S)``."""
        return self.keep * np.asarray(s) + self.scatter(s)

    __call__ = apply

    def adjoint(self, s: np.ndarray) -> np.ndarray:
        """Transpose of :meth:`apply` (conjugate transpose for complex kernels)."""
        s = np.asarray(s)
        out = self.keep * s.astype(np.result_type(s.dtype, np.float64))
        if self.method == "separable":
            for wgt, my, mx in self._lobes:
                out = out + wgt * _separable(s, my.T, mx.T)
            if self._ghost_mats is not None:
                out = out + self.psf.ghost_weight * _separable(s, self._ghost_mats[0].T, self._ghost_mats[1].T)
            if self.psf.veil:
                h, w = self.shape
                out = out + (self.psf.veil / (h * w)) * s.sum(axis=(-2, -1), keepdims=True)
        elif self._ghost is not None:
            out = out + flip_image(self._ghost.adjoint(s))
        if self._conv is not None:
            out = out + self._conv.adjoint(s)
        return out


def apply_stray_light(s: np.ndarray, psf_params: StrayLightPSF | Mapping[str, Any],
                      camera: CameraModel | None = None) -> np.ndarray:
    """``S_meas = (delta + h) * S`` on images ``[..., H, W]``; the ghost mirrors through the
    camera's principal point (or the image centre without a camera)."""
    psf = psf_params if isinstance(psf_params, StrayLightPSF) else StrayLightPSF.from_params(psf_params)
    if psf.is_identity:
        return np.array(s, copy=True)
    s = np.asarray(s)
    center = (camera.cx, camera.cy) if camera is not None else None
    return StrayLightOperator(psf, s.shape[-2:], center).apply(s)


# ---------------------------------------------------------------------------------------------
# Parameters (the `stray_light` effect's mapping)
# ---------------------------------------------------------------------------------------------
PSF_KEYS = ("weight", "sigma_px", "sigma_y_px", "gaussians", "veil", "ghost_weight", "ghost_sigma_px",
            "ghost_center_px", "psf_file", "psf_center_px", "psf_scale", "conserve")


def _num(params: Mapping[str, Any], key: str, default: float, *, source: str | Path, prefix: str,
         lo: float = 0.0, hi: float = math.inf, expected: str = "a number >= 0") -> float:
    return Schema(source).number(params.get(key, default), f"{prefix}.{key}", lo=lo,
                                 hi=None if hi == math.inf else hi, expected=expected)


def _pair(v: Any, *, source: str | Path, field_: str) -> tuple[float, float]:
    try:
        a, b = (float(x) for x in v)
    except (TypeError, ValueError):
        raise InputFileError(f"got {v!r}", file=source, field=field_, expected="[x, y] in pixels") from None
    return a, b


def load_psf_image(path: str | Path, *, source: str | Path = "<effects>", field_: str = "psf_file") -> np.ndarray:
    """A measured PSF image: ``.npy`` or an image file OpenCV reads (16-bit PNG, TIFF, ...)."""
    p = Path(path)
    if not p.is_file():
        raise InputFileError(f"no such file {str(p)!r}", file=source, field=field_,
                             expected="a PSF image (.npy, .png, .tif)")
    if p.suffix.lower() == ".npy":
        img = np.load(p)
    else:
        import cv2

        img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED | cv2.IMREAD_ANYDEPTH)
        if img is None:
            raise InputFileError("cannot be read as an image", file=p, field=field_,
                                 expected="a PSF image (.npy, .png, .tif)")
        if img.ndim == 3:
            img = img.mean(axis=2)
    img = np.asarray(img, dtype=np.float64)
    if img.ndim == 2 and np.all(np.isfinite(img)) and img.size and img.min() >= -1e-9 * np.abs(img).max():
        img = np.clip(img, 0.0, None)  # round-off below zero (e.g. an FFT-made PSF) is zero light
    if img.ndim != 2 or not np.all(np.isfinite(img)) or img.min() < 0 or img.sum() <= 0:
        raise InputFileError("is not a 2-D non-negative image with positive sum", file=p, field=field_,
                             expected="a PSF image (.npy, .png, .tif)")
    return img


def _psf_from_params(params: Mapping[str, Any], *, source: str | Path, prefix: str,
                     base_dir: Path | None) -> StrayLightPSF:
    if not isinstance(params, Mapping):
        raise InputFileError(f"got {params!r}", file=source, field=prefix, expected="a mapping of parameters")
    unknown = sorted(set(params) - set(PSF_KEYS))
    if unknown:
        raise InputFileError(f"unknown parameter {unknown[0]!r}", file=source, field=f"{prefix}.{unknown[0]}",
                             expected="one of " + ", ".join(PSF_KEYS))
    kw: dict[str, Any] = {}
    lobes: list[GaussianLobe] = []
    weight = _num(params, "weight", 0.0, source=source, prefix=prefix, hi=1.0, expected="a fraction in [0, 1]")
    if weight:
        sx = _num(params, "sigma_px", 20.0, source=source, prefix=prefix, expected="a sigma in pixels >= 0")
        sy = _num(params, "sigma_y_px", sx, source=source, prefix=prefix, expected="a sigma in pixels >= 0")
        lobes.append(GaussianLobe(weight, sx, sy))
    for i, g in enumerate(params.get("gaussians") or []):
        try:
            vals = [float(x) for x in g]
            if len(vals) == 2:
                vals.append(vals[1])
            w, sx, sy = vals
            ok = 0 <= w <= 1 and sx >= 0 and sy >= 0
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise InputFileError(f"got {g!r}", file=source, field=f"{prefix}.gaussians[{i}]",
                                 expected="[weight in [0, 1], sigma_x_px >= 0, sigma_y_px >= 0]")
        lobes.append(GaussianLobe(w, sx, sy))
    kw["gaussians"] = tuple(lobes)
    kw["veil"] = _num(params, "veil", 0.0, source=source, prefix=prefix, hi=1.0, expected="a fraction in [0, 1]")
    kw["ghost_weight"] = _num(params, "ghost_weight", 0.0, source=source, prefix=prefix, hi=1.0,
                              expected="a fraction in [0, 1]")
    kw["ghost_sigma_px"] = _num(params, "ghost_sigma_px", 0.0, source=source, prefix=prefix,
                                expected="a sigma in pixels >= 0")
    if params.get("ghost_center_px") is not None:
        kw["ghost_center_px"] = _pair(params["ghost_center_px"], source=source, field_=f"{prefix}.ghost_center_px")
    if params.get("psf_file"):
        f = Path(str(params["psf_file"]))
        if not f.is_absolute() and base_dir is not None:
            f = base_dir / f
        kw["measured"] = load_psf_image(f, source=source, field_=f"{prefix}.psf_file")
        kw["measured_scale"] = _num(params, "psf_scale", 1.0, source=source, prefix=prefix,
                                    expected="a scale >= 0")
        if params.get("psf_center_px") is not None:
            cx, cy = _pair(params["psf_center_px"], source=source, field_=f"{prefix}.psf_center_px")
            ph, pw = kw["measured"].shape
            if not (float(cx).is_integer() and float(cy).is_integer() and 0 <= cx < pw and 0 <= cy < ph):
                raise InputFileError(f"got {params['psf_center_px']!r}", file=source,
                                     field=f"{prefix}.psf_center_px",
                                     expected=f"integer pixel [x, y] inside the {pw}x{ph} PSF image")
            kw["measured_center_px"] = (int(cx), int(cy))
    conserve = params.get("conserve", True)
    if not isinstance(conserve, bool):
        raise InputFileError(f"got {conserve!r}", file=source, field=f"{prefix}.conserve", expected="true or false")
    kw["conserve"] = conserve
    psf = StrayLightPSF(**kw)
    if psf.conserve and psf.total_weight > 1.0 + 1e-12:
        raise InputFileError(f"the weights add up to {psf.total_weight:g}", file=source, field=prefix,
                             expected="a total scattered fraction <= 1")
    return psf


def psf_to_params(psf: StrayLightPSF) -> dict[str, Any]:
    """Inverse of :meth:`StrayLightPSF.from_params` for the parametric parts (not a measured image)."""
    d: dict[str, Any] = {}
    if psf.gaussians:
        d["gaussians"] = [[g.weight, g.sigma_x_px, g.sigma_y_px] for g in psf.gaussians]
    if psf.veil:
        d["veil"] = psf.veil
    if psf.ghost_weight:
        d["ghost_weight"] = psf.ghost_weight
        d["ghost_sigma_px"] = psf.ghost_sigma_px
        if psf.ghost_center_px is not None:
            d["ghost_center_px"] = list(psf.ghost_center_px)
    d["conserve"] = psf.conserve
    return d


def psf_from_sequence(lobes: Sequence[tuple[float, float, float]], **kw: Any) -> StrayLightPSF:
    """Convenience: ``psf_from_sequence([(w, sx, sy), ...], veil=..., ...)``."""
    return StrayLightPSF(gaussians=tuple(GaussianLobe(*map(float, g)) for g in lobes), **kw)
