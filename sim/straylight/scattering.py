"""The stray-light operator: ``S -> (delta + h) * S`` on images of one size, its adjoint and
its inverse (fixed-point deconvolution), built on the kernels and the padded convolution.
"""

from __future__ import annotations

import math
from typing import Any, Mapping

import numpy as np

from tofhil import C_M_PER_S
from tofhil.camera import CameraModel
from tofhil.errors import TofhilError
from tofhil.sim.straylight.convolution import PaddedConvolution, _separable, flip_image
from tofhil.sim.straylight.kernels import (_pixel_matrix, field_rho2, gaussian_kernel, ghost_kernel, psf_kernel,
                                           radial_hats, shift_grid)
from tofhil.sim.straylight.psf import Ghost, StrayLightPSF


class StrayLightOperator:
    """``S -> (delta + h) * S`` for images of one size; kernels built once.

    ``apply`` is the forward model, ``scatter`` the stray light alone (``apply(S) = keep * S +
    scatter(S)``), ``adjoint`` the transpose (for least-squares corrections), ``invert`` the
    correction (fixed-point deconvolution). A ghost without a centre mirrors through
    ``center_px`` (the camera's principal point; default the image centre).

    ``method``: ``"separable"`` evaluates Gaussian lobes and ghosts as products with
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
        c = center_px or ((w - 1) / 2.0, (h - 1) / 2.0)
        self.center_px = (float(c[0]), float(c[1]))
        self.keep: float | np.ndarray = psf.keep
        # A radial profile is not separable: it always goes through the FFT.
        self.method = ("fft" if method == "auto" or psf.radial is not None
                       or any(g.field_weight or g.field_weight4 for g in psf.gaussians) else method)
        self._field: PaddedConvolution | None = None
        self._field4: PaddedConvolution | None = None
        rad = psf.radial
        field_lobes = [g for g in psf.gaussians if g.field_weight]
        if field_lobes or (rad is not None and rad.field_values and np.any(rad.field_values)):
            # Shift-variant part: kernel applied to rho^2 S (a source's lobe grows with rho^2).
            self._rho2 = field_rho2(self.shape, self.center_px)
            kf = np.zeros((2 * h - 1, 2 * w - 1))
            moved = 0.0
            for g in field_lobes:
                kf += g.field_weight * gaussian_kernel(self.shape, g.sigma_x_px, g.sigma_y_px)
                moved += g.field_weight
            if rad is not None and rad.field_values:
                kf += np.tensordot(np.asarray(rad.field_values), radial_hats(rad.radii_px, *shift_grid(self.shape),
                                                                             rad.aspect), axes=1)
                moved += rad.field_weight
            self._field = PaddedConvolution(kf, self.shape, (h - 1, w - 1), workers)
            if psf.direct is None and psf.conserve:
                self.keep = psf.keep - self._rho2 * moved  # the field lobe moves light too
        lobes4 = [g for g in psf.gaussians if g.field_weight4]
        if lobes4:
            # Second order in the field: the kernel applied to rho^4 S.
            self._rho2 = field_rho2(self.shape, self.center_px)
            k4 = sum(g.field_weight4 * gaussian_kernel(self.shape, g.sigma_x_px, g.sigma_y_px) for g in lobes4)
            self._field4 = PaddedConvolution(k4, self.shape, (h - 1, w - 1), workers)
            if psf.direct is None and psf.conserve:
                self.keep = self.keep - self._rho2 ** 2 * sum(g.field_weight4 for g in lobes4)
        self._conv: PaddedConvolution | None = None
        self._ghosts: list[PaddedConvolution] = []
        self._lobes: list[tuple[float, np.ndarray, np.ndarray]] = []
        self._ghost_mats: list[tuple[float, np.ndarray, np.ndarray]] = []
        ghosts = [(g, self.ghost_center(g)) for g in psf.ghosts if g.weight and g.is_mirror]
        # Ghosts with another magnification or a delay: separable matrices in either method
        # (a magnified image is not a convolution), each with its extra optical path.
        self._gen_ghosts: list[tuple[float, np.ndarray, np.ndarray, float]] = [
            (g.weight, _pixel_matrix(h, g.sigma_px, mirror_about=gc[1], magnification=g.magnification),
             _pixel_matrix(w, g.sigma_px, mirror_about=gc[0], magnification=g.magnification), g.extra_path_m)
            for g, gc in ((g, self.ghost_center(g)) for g in psf.ghosts if g.weight and not g.is_mirror)]
        if self.method == "separable":
            for g in psf.gaussians:
                if g.weight:
                    self._lobes.append((g.weight, _pixel_matrix(h, g.sigma_y_px), _pixel_matrix(w, g.sigma_x_px)))
            for g, gc in ghosts:
                self._ghost_mats.append((g.weight, _pixel_matrix(h, g.sigma_px, mirror_about=gc[1]),
                                         _pixel_matrix(w, g.sigma_px, mirror_about=gc[0])))
            if psf.measured is not None and psf.measured_scale != 0:
                # Only the measured part goes through the FFT here.
                k = psf_kernel(StrayLightPSF(measured=psf.measured, measured_center_px=psf.measured_center_px,
                                             measured_scale=psf.measured_scale), self.shape)
                self._conv = PaddedConvolution(k, self.shape, (h - 1, w - 1), workers)
        else:
            k = psf_kernel(psf, self.shape)
            self._conv = PaddedConvolution(k, self.shape, (h - 1, w - 1), workers) if np.any(k) else None
            # Ghosts sharing a centre share one kernel (and one FFT per application).
            by_centre: dict[tuple[float, float], np.ndarray] = {}
            for g, gc in ghosts:
                by_centre[gc] = by_centre.get(gc, 0.0) + ghost_kernel(g, self.shape, gc)
            self._ghosts = [PaddedConvolution(gk, self.shape, (h - 1, w - 1), workers) for gk in by_centre.values()]

    def ghost_center(self, ghost: Ghost) -> tuple[float, float]:
        """The point a ghost mirrors through: its own centre, else the principal point."""
        c = ghost.center_px or self.center_px
        return float(c[0]), float(c[1])

    def _general_ghosts(self, s: np.ndarray, out: np.ndarray, freq_hz: Any, adjoint: bool) -> np.ndarray:
        """Adds the magnified/delayed ghosts; ``freq_hz`` (broadcast against ``s``, e.g.
        ``[F, NH, 1, 1]``: each channel's modulation frequency x harmonic) delays a ghost's
        phasor by ``exp(i 2 pi f extra_path / c)``; None = unmodulated light (no delay)."""
        for wgt, my, mx, path in self._gen_ghosts:
            img = _separable(s, my.T, mx.T) if adjoint else _separable(s, my, mx)
            if path and freq_hz is not None:
                ph = np.exp(2j * np.pi * np.asarray(freq_hz, dtype=np.float64) * path / C_M_PER_S)
                img = img * (np.conj(ph) if adjoint else ph)
                if not np.iscomplexobj(out):
                    out = out.astype(np.complex128)
            out = out + wgt * img
        return out

    def scatter(self, s: np.ndarray, freq_hz: Any = None) -> np.ndarray:
        """The stray light only: ``h * S`` (without the direct part); ``freq_hz`` see
        :meth:`_general_ghosts` (only ghosts with an extra path need it)."""
        s = np.asarray(s)
        out = np.zeros(s.shape, dtype=np.result_type(s.dtype, np.float64))
        out = self._general_ghosts(s, out, freq_hz, adjoint=False)
        if self.method == "separable":
            for wgt, my, mx in self._lobes + self._ghost_mats:
                out += wgt * _separable(s, my, mx)
            if self.psf.veil:
                h, w = self.shape
                out += (self.psf.veil / (h * w)) * s.sum(axis=(-2, -1), keepdims=True)
        elif self._ghosts:
            flipped = flip_image(s)
            for gc in self._ghosts:
                out += gc(flipped)
        if self._conv is not None:
            out += self._conv(s)
        if self._field is not None:
            out += self._field(self._rho2 * s)
        if self._field4 is not None:
            out += self._field4(self._rho2 ** 2 * s)
        return out

    def scatter_adjoint(self, s: np.ndarray, freq_hz: Any = None) -> np.ndarray:
        """Transpose of :meth:`scatter` (conjugate transpose for complex kernels)."""
        s = np.asarray(s)
        out = np.zeros(s.shape, dtype=np.result_type(s.dtype, np.float64))
        out = self._general_ghosts(s, out, freq_hz, adjoint=True)
        if self.method == "separable":
            for wgt, my, mx in self._lobes + self._ghost_mats:
                out += wgt * _separable(s, my.T, mx.T)
            if self.psf.veil:
                h, w = self.shape
                out += (self.psf.veil / (h * w)) * s.sum(axis=(-2, -1), keepdims=True)
        else:
            for gc in self._ghosts:
                out += flip_image(gc.adjoint(s))
        if self._conv is not None:
            out += self._conv.adjoint(s)
        if self._field is not None:
            out += self._rho2 * self._field.adjoint(s)
        if self._field4 is not None:
            out += self._rho2 ** 2 * self._field4.adjoint(s)
        return out

    def apply(self, s: np.ndarray, freq_hz: Any = None) -> np.ndarray:
        """``S_meas = keep * S + scatter(S)``."""
        return self.keep * np.asarray(s) + self.scatter(s, freq_hz)

    __call__ = apply

    def adjoint(self, s: np.ndarray, freq_hz: Any = None) -> np.ndarray:
        """Transpose of :meth:`apply` (conjugate transpose for complex kernels)."""
        s = np.asarray(s)
        return self.keep * s.astype(np.result_type(s.dtype, np.float64)) + self.scatter_adjoint(s, freq_hz)

    @property
    def scattered_fraction(self) -> float:
        """Largest fraction of one pixel's light that lands on other pixels of this sensor:
        the operator 1-norm of ``h`` on the sensor (its largest column sum; every part of
        ``h`` is non-negative). Light scattered beyond the edge does not count, so it is at
        most :attr:`StrayLightPSF.total_weight`."""
        if not hasattr(self, "_scattered"):
            self._scattered = float(self.scatter_adjoint(np.ones(self.shape)).max())
        return self._scattered

    def invert(self, s_meas: np.ndarray, *, iterations: int = 30, tol: float = 1e-7,
               freq_hz: Any = None) -> np.ndarray:
        """Remove the stray light: solve ``keep * S + h * S = S_meas`` by the fixed point
        ``S_{k+1} = (S_meas - h * S_k) / keep`` (a Neumann series; Kavli et al. 2008).

        The error shrinks by ``scattered_fraction / keep`` per iteration, so a few tens of
        iterations reach float precision for realistic optics (< 0.3). Stops early when the
        update is below ``tol`` of the signal. Refuses optics it cannot invert this way.
        """
        keep_min = float(np.min(self.keep))
        ratio = self.scattered_fraction / keep_min if keep_min > 0 else math.inf
        if ratio >= 1.0:
            raise TofhilError(f"the PSF scatters {self.scattered_fraction:.3f} of the signal against a direct "
                              f"part of {keep_min:.3f}; the fixed-point inversion needs a ratio < 1",
                              field="psf", expected="scattered fraction / direct < 1")
        s_meas = np.asarray(s_meas)
        scale = float(np.abs(s_meas).max()) or 1.0
        s = s_meas.astype(np.result_type(s_meas.dtype, np.float64), copy=True)
        for _ in range(iterations):
            nxt = (s_meas - self.scatter(s, freq_hz)) / self.keep
            done = float(np.abs(nxt - s).max()) <= tol * scale
            s = nxt
            if done:
                break
        return s


def apply_stray_light(s: np.ndarray, psf_params: StrayLightPSF | Mapping[str, Any],
                      camera: CameraModel | None = None) -> np.ndarray:
    """``S_meas = (delta + h) * S`` on images ``[..., H, W]``; ghosts without a centre mirror
    through the camera's principal point (or the image centre without a camera)."""
    psf = psf_params if isinstance(psf_params, StrayLightPSF) else StrayLightPSF.from_params(psf_params)
    if psf.is_identity:
        return np.array(s, copy=True)
    s = np.asarray(s)
    center = (camera.cx, camera.cy) if camera is not None else None
    return StrayLightOperator(psf, s.shape[-2:], center).apply(s)
