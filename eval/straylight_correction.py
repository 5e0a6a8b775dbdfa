"""Stray-light correction of complex ToF images: ``S_meas = (delta + h) * S``.

Stray light (lens flare, scattering between lens and sensor) spreads a fraction of every
pixel's complex signal ``S = A exp(i phi)`` over the sensor. Because it adds phasors, a
bright near object (a white card close to the lens) pulls the phase of dim far pixels
toward its own: a dark patch on a wall appears closer than it is. All corrections here
work on the complex image of one modulation frequency at a time (``[..., H, W]``), since
the scattering is optical and the same for every frequency.

Three families are implemented:

* **Thesis method 1** (Holmlund, uniform veil): ``S_corr = S - w * sum_p S_p`` -- the
  stray light is a fixed fraction ``w`` of the sum of all pixels' complex values, the same
  at every pixel. :func:`subtract_uniform`.
* **Thesis method 2** (inverse filtering): ``h = w * G(sigma_h, sigma_v)`` with ``G`` a
  unit-sum Gaussian; ``S_corr = F^-1[ conj(H) F[S] / (|H|^2 + mu) ]`` with
  ``H = F[delta + h]`` on a zero-padded grid (Wiener-like regularisation ``mu``).
  :func:`inverse_filter_gaussian`.
* **Calibrated PSF** (Mure-Dubois and Hügli 2007; Kavli et al. 2008): ``h`` is fitted
  once from a calibration capture whose stray-light-free signal is known (from the twin,
  or a bright target on a dark background), as a non-negative combination of a fixed
  dictionary of shapes -- isotropic Gaussians on a log-spaced grid of widths, a uniform
  veil, and a ghost mirrored through the principal point -- so the fit is linear (NNLS)
  and needs no tuning. It is then removed from any other scene by the fixed-point
  iteration ``S_{k+1} = S_meas - h * S_k`` (a Neumann series, converging because the
  scattered fraction ``||h||_1 < 1``). :func:`calibrate_psf`, :func:`deconvolve`.

Convolutions are linear (not circular): images are zero-padded to at least
``H + kh - 1`` by ``W + kw - 1`` before the FFT, so light never wraps around the sensor
edges.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy import fft as sfft
from scipy.optimize import lsq_linear, minimize, nnls
from scipy.special import erf

from tofhil.errors import InputFileError
from tofhil.eval.tagged_npz import load_tagged_npz

#: The ``format`` tag of a saved stray-light PSF file.
PSF_FORMAT = "tofhil.straylight_psf.v1"

#: Narrowest lobe fitted (pixels); see :func:`default_sigmas`.
MIN_SIGMA_PX = 1.0
LOG_SIGMA_RANGE = (float(np.log(0.8)), float(np.log(3000.0)))

# ---------------------------------------------------------------------------- convolution


def _fast_shape(h: int, w: int, kh: int, kw: int) -> tuple[int, int]:
    return sfft.next_fast_len(h + kh - 1), sfft.next_fast_len(w + kw - 1)


def kernel_offsets(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Row and column offsets ``dy[2H-1, 1]``, ``dx[1, 2W-1]`` of a full-size kernel.

    A kernel of shape ``(2H-1, 2W-1)`` centred at ``(H-1, W-1)`` covers every displacement
    between two pixels of an ``H x W`` sensor.
    """
    dy = np.arange(-(height - 1), height, dtype=np.float64)[:, None]
    dx = np.arange(-(width - 1), width, dtype=np.float64)[None, :]
    return dy, dx


def gaussian_kernel(height: int, width: int, sigma_h: float, sigma_v: float | None = None) -> np.ndarray:
    """Separable Gaussian on the full ``(2H-1, 2W-1)`` offset grid, integrated over pixels.

    ``sigma_h`` is the horizontal (column) width in pixels, ``sigma_v`` the vertical one.
    Unit integral over the infinite plane: a weight on it is the fraction of a pixel's
    light it moves, and what falls beyond the grid (beyond the sensor) is lost.
    """
    gy, gx = _gauss_1d(height, sigma_v if sigma_v is not None else sigma_h), _gauss_1d(width, sigma_h)
    return gy[:, None] * gx[None, :]


def _gauss_1d(n: int, sigma: float) -> np.ndarray:
    """Pixel-integrated unit Gaussian at offsets ``-(n-1) .. n-1`` (erf differences)."""
    if not sigma > 0:
        raise ValueError(f"Gaussian widths must be positive, got {sigma}")
    d = np.arange(-(n - 1), n, dtype=np.float64)
    s = np.sqrt(2) * sigma
    return 0.5 * (erf((d + 0.5) / s) - erf((d - 0.5) / s))


class _GaussianBlur:
    """``G(sx, sy) * S`` for one fixed image stack, fast: the image's FFT is computed once
    and a separable kernel's FFT is the outer product of two 1-D FFTs."""

    def __init__(self, s: np.ndarray) -> None:
        self.h, self.w = s.shape[-2:]
        self.fshape = _fast_shape(self.h, self.w, 2 * self.h - 1, 2 * self.w - 1)
        self._sf = sfft.fft2(s, s=self.fshape, axes=(-2, -1))

    def __call__(self, sx: float, sy: float) -> np.ndarray:
        fy = sfft.fft(_gauss_1d(self.h, sy), n=self.fshape[0])
        fx = sfft.fft(_gauss_1d(self.w, sx), n=self.fshape[1])
        # Inverse along x, crop to the sensor's columns, then along y: half the work.
        t = sfft.ifft(self._sf * fx, axis=-1)[..., self.w - 1:2 * self.w - 1]
        return sfft.ifft(t * fy[:, None], axis=-2)[..., self.h - 1:2 * self.h - 1, :]


def uniform_kernel(height: int, width: int) -> np.ndarray:
    """Constant kernel with unit value: ``uniform * S`` is ``sum_p S_p`` at every pixel."""
    return np.ones((2 * height - 1, 2 * width - 1))


class Convolver:
    """Linear convolution of ``[..., H, W]`` images with one fixed kernel (padded FFT).

    The kernel's FFT is computed once, so repeated application (fixed-point iterations)
    costs one forward and one inverse FFT per image.
    """

    def __init__(self, kernel: np.ndarray, image_shape: tuple[int, int]) -> None:
        k = np.asarray(kernel)
        if k.ndim != 2 or k.shape[0] % 2 == 0 or k.shape[1] % 2 == 0:
            raise ValueError(f"kernel must be 2-D with odd sizes (centred), got {k.shape}")
        self.image_shape = tuple(image_shape)
        self.kernel_shape = k.shape
        h, w = self.image_shape
        self.fshape = _fast_shape(h, w, *k.shape)
        self._kf = sfft.fft2(k, s=self.fshape)
        self._r0, self._c0 = k.shape[0] // 2, k.shape[1] // 2

    def __call__(self, s: np.ndarray) -> np.ndarray:
        h, w = self.image_shape
        sf = sfft.fft2(s, s=self.fshape, axes=(-2, -1))
        out = sfft.ifft2(sf * self._kf, axes=(-2, -1))
        out = out[..., self._r0:self._r0 + h, self._c0:self._c0 + w]
        return out if np.iscomplexobj(s) else out.real


def fft_convolve(s: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """``kernel * s`` (linear, same size as ``s``; kernel centred at its middle sample)."""
    return Convolver(kernel, s.shape[-2:])(s)


def mirror_through(s: np.ndarray, cx: float, cy: float) -> np.ndarray:
    """Point reflection of ``[..., H, W]`` through the principal point ``(cx, cy)``.

    A lens ghost (a double reflection between lens surfaces) images a bright object at
    the opposite side of the optical axis. The pixel at ``(u, v)`` receives the signal of
    ``(2cx - u, 2cy - v)`` (nearest pixel; zero where that falls off the sensor).
    """
    h, w = s.shape[-2:]
    v = np.rint(2 * cy - np.arange(h)).astype(int)
    u = np.rint(2 * cx - np.arange(w)).astype(int)
    vin, uin = (v >= 0) & (v < h), (u >= 0) & (u < w)
    out = np.zeros_like(s)
    src = s[..., np.clip(v, 0, h - 1)[:, None], np.clip(u, 0, w - 1)[None, :]]
    out[...] = src * (vin[:, None] & uin[None, :])
    return out


# ---------------------------------------------------------------------------- thesis methods


def subtract_uniform(s: np.ndarray, w: float) -> np.ndarray:
    """Thesis method 1: ``S_corr = S - w * sum_p S_p`` (sum over the ``H x W`` image).

    ``s`` is ``[..., H, W]`` complex; the sum is taken per leading index (per frequency).
    """
    s = np.asarray(s)
    return s - w * s.sum(axis=(-2, -1), keepdims=True)


def inverse_filter_gaussian(s: np.ndarray, sigma_h: float, sigma_v: float, w: float, mu: float) -> np.ndarray:
    """Thesis method 2: Wiener-like inverse filter of ``delta + w * G(sigma_h, sigma_v)``.

    ``S_corr = F^-1[ conj(H) F[S] / (|H|^2 + mu) ]`` with ``H`` the transfer function of
    ``delta + w G`` on the zero-padded grid; ``mu = 0`` is the plain inverse (``|H| >= 1 - w``
    never vanishes for ``w < 1``, so it is always defined). The result is cropped back.
    """
    s = np.asarray(s)
    h, wd = s.shape[-2:]
    k = w * gaussian_kernel(h, wd, sigma_h, sigma_v)
    k[h - 1, wd - 1] += 1.0
    fshape = _fast_shape(h, wd, *k.shape)
    # Centre the kernel at the origin of the padded grid so the filter has no shift.
    kp = np.zeros(fshape)
    kp[:k.shape[0], :k.shape[1]] = k
    kp = np.roll(kp, (-(h - 1), -(wd - 1)), axis=(0, 1))
    hf = sfft.fft2(kp)
    sf = sfft.fft2(s, s=fshape, axes=(-2, -1))
    out = sfft.ifft2(sf * np.conj(hf) / (np.abs(hf) ** 2 + mu), axes=(-2, -1))
    return out[..., :h, :wd]


# ---------------------------------------------------------------------------- calibrated PSF


@dataclass
class StrayLightPSF:
    """A stray-light model ``S_meas = direct * S + h * S``.

    ``h * S = kernel (*) S + ghost_weight * mirror(ghost_blur (*) S)``; the kernel lives on
    the full ``(2H-1, 2W-1)`` offset grid of the sensor it was calibrated on. ``direct`` is
    the fraction of a pixel's light that stays on it: 1 for purely additive stray light,
    ``1 - scattered`` when the scattering conserves energy (both occur in the literature,
    so the calibration fits it).
    """

    kernel: np.ndarray
    cx: float
    cy: float
    ghost_weight: float = 0.0
    ghost_kernel: np.ndarray | None = None
    direct: float = 1.0
    #: What the calibration found: basis names and weights, fit residual, source.
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def sensor_shape(self) -> tuple[int, int]:
        return ((self.kernel.shape[0] + 1) // 2, (self.kernel.shape[1] + 1) // 2)

    @property
    def scattered_fraction(self) -> float:
        """Largest fraction of one pixel's light that lands on the sensor's pixels.

        The operator 1-norm of ``h`` restricted to the sensor (its largest column sum):
        light scattered beyond the sensor edge does not count, so a veil of weight ``v``
        counts ``v``, not the sum of its full offset grid.
        """
        reach = Convolver(np.abs(self.kernel)[::-1, ::-1], self.sensor_shape)(np.ones(self.sensor_shape))
        return float(reach.max() + abs(self.ghost_weight))

    def operator(self, image_shape: tuple[int, int]) -> "PSFOperator":
        if tuple(image_shape) != self.sensor_shape:
            raise InputFileError(f"PSF was calibrated for a {self.sensor_shape[0]}x{self.sensor_shape[1]} "
                                 f"sensor, the images are {image_shape[0]}x{image_shape[1]}",
                                 field="psf", expected="a PSF calibrated on the same camera")
        return PSFOperator(self, image_shape)

    def apply(self, s: np.ndarray) -> np.ndarray:
        """``h * S`` (the stray light alone) for ``[..., H, W]`` images."""
        return self.operator(s.shape[-2:])(s)

    # ---------------------------------------------------------------- files
    def save(self, path: str | Path) -> None:
        import json

        np.savez_compressed(path, kernel=self.kernel, cx=self.cx, cy=self.cy, ghost_weight=self.ghost_weight,
                            direct=self.direct,
                            ghost_kernel=np.zeros((1, 1)) if self.ghost_kernel is None else self.ghost_kernel,
                            has_ghost_kernel=self.ghost_kernel is not None,
                            info=json.dumps(self.info), format=PSF_FORMAT)

    @classmethod
    def load(cls, path: str | Path) -> "StrayLightPSF":
        import json

        p = Path(path)
        data = load_tagged_npz(p, PSF_FORMAT, "tofhil stray-light PSF", "a PSF file written by --save-psf (.npz)")
        for key in ("kernel", "cx", "cy", "ghost_weight"):
            if key not in data:
                raise InputFileError("missing", file=p, field=key, expected="see docs/evaluation.md")
        k = np.asarray(data["kernel"], dtype=np.float64)
        if k.ndim != 2 or k.shape[0] % 2 == 0 or k.shape[1] % 2 == 0:
            raise InputFileError(f"has shape {k.shape}", file=p, field="kernel", expected="(2H-1, 2W-1)")
        gk = np.asarray(data["ghost_kernel"], dtype=np.float64) if bool(data.get("has_ghost_kernel", False)) else None
        return cls(kernel=k, cx=float(data["cx"]), cy=float(data["cy"]), ghost_weight=float(data["ghost_weight"]),
                   ghost_kernel=gk, direct=float(data.get("direct", 1.0)),
                   info=json.loads(str(data.get("info", "{}"))))


class PSFOperator:
    """``S -> h * S`` for one image size, with all FFTs of the kernels precomputed."""

    def __init__(self, psf: StrayLightPSF, image_shape: tuple[int, int]) -> None:
        self.psf = psf
        self._conv = Convolver(psf.kernel, image_shape)
        self._ghost_conv = (Convolver(psf.ghost_kernel, image_shape)
                            if psf.ghost_kernel is not None and psf.ghost_weight != 0 else None)

    def __call__(self, s: np.ndarray) -> np.ndarray:
        out = self._conv(s)
        if self.psf.ghost_weight != 0:
            g = self._ghost_conv(s) if self._ghost_conv is not None else s
            out = out + self.psf.ghost_weight * mirror_through(g, self.psf.cx, self.psf.cy)
        return out


def deconvolve(s_meas: np.ndarray, psf: StrayLightPSF, *, iterations: int = 30, tol: float = 1e-7) -> np.ndarray:
    """Remove stray light: solve ``direct * S + h * S = S_meas`` by the fixed point
    ``S_{k+1} = (S_meas - h * S_k) / direct``.

    The error shrinks by ``||h||_1 / direct`` per iteration (Kavli et al. 2008), so a few
    tens of iterations reach float precision for realistic scattered fractions (< 0.3).
    Stops early when the update is below ``tol`` of the signal.
    """
    ratio = psf.scattered_fraction / psf.direct if psf.direct > 0 else np.inf
    if ratio >= 1.0:
        raise InputFileError(f"PSF scatters {psf.scattered_fraction:.3f} of the signal against a direct "
                             f"part of {psf.direct:.3f}; the fixed-point inversion needs a ratio < 1",
                             field="psf", expected="||h||_1 / direct < 1")
    s_meas = np.asarray(s_meas)
    op = psf.operator(s_meas.shape[-2:])
    scale = float(np.abs(s_meas).max()) or 1.0
    s = s_meas.copy()
    for _ in range(iterations):
        nxt = (s_meas - op(s)) / psf.direct
        done = float(np.abs(nxt - s).max()) <= tol * scale
        s = nxt
        if done:
            break
    return s


def default_sigmas(height: int, width: int) -> np.ndarray:
    """Log-spaced Gaussian widths (ratio sqrt 2) from 1 px to the sensor diagonal / 2.

    Narrower lobes keep almost all light in the pixel: they are indistinguishable from the
    ``direct`` factor, and with a noisy reference a narrow lobe minus the loss term is a
    high-pass filter that fits the noise instead of the optics.
    """
    top = 0.5 * float(np.hypot(height, width))
    n = int(np.floor(np.log(top / MIN_SIGMA_PX) / np.log(np.sqrt(2)))) + 1
    return MIN_SIGMA_PX * np.sqrt(2) ** np.arange(n)


def calibrate_psf(s_meas: np.ndarray, s_true: np.ndarray, cx: float, cy: float, *,
                  sigmas: np.ndarray | None = None, veil: bool = True, ghost: bool = True,
                  fit_direct: bool = True, weight: np.ndarray | None = None,
                  refine: bool = True) -> StrayLightPSF:
    """Fit ``direct`` and ``h`` so that ``direct * S_true + h * S_true`` matches ``S_meas``.

    Non-negative least squares over all pixels (real and imaginary parts). ``s_meas`` and
    ``s_true`` are ``[..., H, W]`` complex (frequencies / frames stacked in front);
    ``s_true`` is the stray-light-free signal of the calibration scene -- the twin's
    render without stray light, or the target pixels of a bright target on a dark
    background (:func:`calibrate_psf_target`). The dictionary: one pixel-integrated
    Gaussian of unit integral per width in
    ``sigmas`` (default :func:`default_sigmas`), a uniform veil, the ghost mirrored
    through ``(cx, cy)`` (sharp and blurred by each width), and, with ``fit_direct``, the
    loss ``-S_true`` (light scattered away from its pixel). Each weight is a fraction of
    light. ``weight`` (``[H, W]``) weights pixels in the fit. With ``refine`` the active
    Gaussians' widths are then optimised continuously and separately in x and y
    (variable projection), so lobes between the dictionary's widths are matched too.
    """
    s_meas = np.asarray(s_meas, dtype=np.complex128)
    s_true = np.asarray(s_true, dtype=np.complex128)
    if s_meas.shape != s_true.shape:
        raise ValueError(f"measured {s_meas.shape} and true {s_true.shape} signals differ in shape")
    h, w = s_true.shape[-2:]
    sig = default_sigmas(h, w) if sigmas is None else np.asarray(sigmas, dtype=np.float64)
    wt = np.ones((h, w)) if weight is None else np.sqrt(np.asarray(weight, dtype=np.float64))
    wt = np.broadcast_to(wt, s_true.shape).ravel()

    def column(b: np.ndarray) -> np.ndarray:
        bw = np.broadcast_to(b, s_true.shape).ravel() * wt
        return np.concatenate([bw.real, bw.imag])

    # Terms: (kind, label, kernel or None, column). kinds: gauss, veil, ghost, loss.
    terms: list[tuple[str, str, np.ndarray | None, np.ndarray]] = []
    blur = _GaussianBlur(s_true)
    blurred = {sg: blur(sg, sg) for sg in sig}
    for sg in sig:
        terms.append(("gauss", f"gauss_{sg:.3g}", gaussian_kernel(h, w, sg), column(blurred[sg])))
    if veil:
        # Unit fraction spread evenly: every pixel gets sum(S) / (H W).
        terms.append(("veil", "veil", uniform_kernel(h, w) / (h * w),
                      column(s_true.sum(axis=(-2, -1), keepdims=True) / (h * w))))
    if ghost:
        terms.append(("ghost", "ghost_0", None, column(mirror_through(s_true, cx, cy))))
        for sg in sig:
            terms.append(("ghost", f"ghost_{sg:.3g}", gaussian_kernel(h, w, sg),
                          column(mirror_through(blurred[sg], cx, cy))))
    if fit_direct:
        terms.append(("loss", "loss", None, column(-s_true)))
    rhs = column(s_meas - s_true)
    a_all = np.stack([t[3] for t in terms], axis=1)
    # Every weight is a fraction of light in [0, 1]; the loss at most 0.9 (a lens that
    # keeps less than a tenth of the light on its pixel is not a camera). The bounds keep
    # an ill-posed fit (a noisy reference: average frames, render the twin noise-free)
    # from trading a huge loss against huge lobes.
    upper = np.array([0.9 if t[0] == "loss" else 1.0 for t in terms])
    coef, rnorm = _nnls_gram(a_all.T @ a_all, a_all.T @ rhs, float(rhs @ rhs), upper)
    n_gauss = len(sig)
    if refine and np.any(coef[:n_gauss] > 0):
        # Variable projection: each run of neighbouring active widths becomes one Gaussian
        # with free (sigma_x, sigma_y); the weights are re-solved linearly for every trial.
        groups = _active_groups(coef[:n_gauss])
        fixed = [t for t, c in zip(terms[n_gauss:], coef[n_gauss:]) if c > 0]
        upper_f = np.array([0.9 if t[0] == "loss" else 1.0 for t in fixed])
        fixed_a = np.stack([t[3] for t in fixed], axis=1) if fixed else np.zeros((rhs.size, 0))
        # Gram blocks of the fixed columns are computed once; per trial only the new ones.
        g_ff, c_f, bb = fixed_a.T @ fixed_a, fixed_a.T @ rhs, float(rhs @ rhs)
        init = np.array([np.exp(np.average(np.log(sig[g]), weights=coef[g])) for g in groups])

        def solve(x: np.ndarray) -> tuple[np.ndarray, float, list[tuple[str, str, np.ndarray, np.ndarray]]]:
            gs = [("gauss", f"gauss_{sx:.3g}x{sy:.3g}", None, column(blur(sx, sy)))
                  for sx, sy in np.exp(np.clip(x, LOG_SIGMA_RANGE[0], LOG_SIGMA_RANGE[1])).reshape(-1, 2)]
            a_g = np.stack([g[3] for g in gs], axis=1)
            gram = np.block([[a_g.T @ a_g, a_g.T @ fixed_a], [fixed_a.T @ a_g, g_ff]])
            c, r = _nnls_gram(gram, np.concatenate([a_g.T @ rhs, c_f]), bb,
                              np.concatenate([np.ones(len(gs)), upper_f]))
            return c, r, gs

        x0 = np.log(np.repeat(init, 2))
        res = minimize(lambda x: solve(x)[1], x0, method="Nelder-Mead",
                       options={"xatol": 1e-3, "fatol": 1e-7 * rnorm, "maxfev": 80 * x0.size + 40})
        c_ref, r_ref, gs = solve(res.x)
        if r_ref < rnorm:
            sxy = np.exp(np.clip(res.x, LOG_SIGMA_RANGE[0], LOG_SIGMA_RANGE[1])).reshape(-1, 2)
            gs = [(kind, name, gaussian_kernel(h, w, sx, sy), col) for (kind, name, _, col), (sx, sy) in zip(gs, sxy)]
            terms, coef, rnorm = gs + fixed, c_ref, r_ref
    kernel = np.zeros((2 * h - 1, 2 * w - 1))
    g_kernel = np.zeros((2 * h - 1, 2 * w - 1))
    g_weight = loss = 0.0
    for (kind, _, k, _), c in zip(terms, coef):
        if c <= 0:
            continue
        if kind in ("gauss", "veil"):
            kernel += c * k
        elif kind == "ghost":
            g_weight += c
            if k is None:
                g_kernel[h - 1, w - 1] += c
            else:
                g_kernel += c * k
        else:
            loss += c
    info = {"basis": [t[1] for t in terms], "weights": [float(c) for c in coef],
            "relative_residual": float(rnorm / (np.linalg.norm(rhs) or 1.0)),
            "direct": 1.0 - loss}
    psf = StrayLightPSF(kernel=kernel, cx=float(cx), cy=float(cy), ghost_weight=g_weight,
                        ghost_kernel=g_kernel / g_weight if g_weight > 0 else None,
                        direct=1.0 - loss, info=info)
    info["scattered_fraction"] = psf.scattered_fraction
    return psf


def _nnls_gram(gram: np.ndarray, atb: np.ndarray, btb: float,
               upper: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """Bounded least squares ``min ||A x - b||, 0 <= x <= upper`` from the normal equations.

    With ``A^T A = R^T R`` (Cholesky of the column-scaled Gram matrix) the problem equals
    ``min ||R x - R^-T A^T b||`` up to a constant, a k x k NNLS instead of one with a row
    per pixel. Returns the coefficients and ``||A x - b||``.
    """
    d = np.sqrt(np.clip(np.diag(gram), 0, None))
    d[d == 0] = 1.0
    g = gram / np.outer(d, d)
    c = atb / d
    k = g.shape[0]
    r = np.linalg.cholesky(g + 1e-12 * np.eye(k))
    y = np.linalg.solve(r, c)  # r lower-triangular: R^T = r, so R^-T c = r^-1 c
    coef, _ = nnls(r.T, y, maxiter=50 * k)
    coef = coef / d
    if upper is not None and np.any(coef > upper):
        res = lsq_linear(r.T, y, bounds=(np.zeros(k), np.asarray(upper) * d), method="bvls")
        coef = res.x / d
    res2 = btb - 2 * coef @ atb + coef @ gram @ coef
    return coef, float(np.sqrt(max(res2, 0.0)))


def _active_groups(coef: np.ndarray) -> list[np.ndarray]:
    """Runs of consecutive positive coefficients -> index arrays."""
    groups: list[list[int]] = []
    for i, c in enumerate(coef):
        if c > 0:
            if groups and groups[-1][-1] == i - 1:
                groups[-1].append(i)
            else:
                groups.append([i])
    return [np.array(g) for g in groups]


def target_mask(s_meas: np.ndarray, threshold: float = 0.2) -> np.ndarray:
    """Pixels whose amplitude (max over leading axes) exceeds ``threshold`` of the brightest."""
    amp = np.abs(np.asarray(s_meas)).reshape((-1,) + np.shape(s_meas)[-2:]).max(axis=0)
    return amp >= threshold * amp.max()


def target_only_signal(s_meas: np.ndarray, threshold: float = 0.2) -> np.ndarray:
    """Stray-light-free estimate of a bright target on a dark (or far) background.

    Keeps the target's pixels (:func:`target_mask`), zero elsewhere: the background's own
    signal is assumed negligible. The target's pixels still hold the stray light the
    target throws on itself; :func:`calibrate_psf_target` removes it iteratively.
    """
    return np.where(target_mask(s_meas, threshold), s_meas, 0)


def calibrate_psf_target(s_meas: np.ndarray, cx: float, cy: float, *, threshold: float = 0.2,
                         rounds: int = 4, **kwargs: Any) -> StrayLightPSF:
    """Calibrate from a bright target on a dark background alone (no twin needed).

    The fit uses the background pixels only (their true signal is zero). Round 0 takes
    the measured target pixels as the true source, which still holds the stray light the
    target throws on itself; each further round uses the target pixels of the measurement
    deconvolved with the previous PSF instead. Scattering that never leaves the target
    cannot be seen this way (nor does it matter for other pixels).
    """
    s_meas = np.asarray(s_meas, dtype=np.complex128)
    mask = target_mask(s_meas, threshold)
    # The target's own pixels say nothing about h (their true value is unknown): fit
    # only the background, where the true signal is known to be zero.
    kwargs.setdefault("weight", (~mask).astype(np.float64))
    s_true = np.where(mask, s_meas, 0)
    psf = calibrate_psf(s_meas, s_true, cx, cy, **kwargs)
    for _ in range(rounds - 1):
        s_true = np.where(mask, deconvolve(s_meas, psf), 0)
        psf = calibrate_psf(s_meas, s_true, cx, cy, **kwargs)
    psf.info["calibration"] = {"mode": "target", "threshold": threshold, "rounds": rounds,
                               "target_pixels": int(mask.sum())}
    return psf
