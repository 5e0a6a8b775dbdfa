"""Stray-light corrections of complex ToF images, built on the optics of ``sim/straylight/``.

Stray light spreads a fraction of every pixel's complex signal ``S = A exp(i phi)`` over the
sensor: ``S_meas = (delta + h) * S`` (the one PSF type, :class:`StrayLightPSF`). Because it
adds phasors, a bright near object pulls the phase of dim far pixels toward its own. Every
correction here works on ``S[..., H, W]`` of one frame (all frequencies at once: the
scattering is optical and the same for every frequency).

* **Thesis method 1** (Holmlund, uniform veil): ``S_corr = S - w * sum_p S_p``.
  :func:`subtract_uniform`.
* **Thesis method 2** (inverse filtering): ``h = w * G(sigma_h, sigma_v)``;
  ``S_corr = F^-1[ conj(H) F[S] / (|H|^2 + mu) ]`` with ``H = F[delta + h]`` on a zero-padded
  grid. :func:`inverse_filter_gaussian`.
* **Calibrated, diagnosed or simulated PSF** (Mure-Dubois and Hügli 2007; Kavli et al.
  2008): removed by the fixed-point iteration of :meth:`StrayLightOperator.invert`.
  :func:`deconvolve`; the PSF comes from :func:`load_psf` (a PSF file, or a diagnosis.json
  whose causes include stray light) or from ``psf_calibration``.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from scipy import fft as sfft

from tofhil.errors import InputFileError, TofhilError
from tofhil.sim.straylight import PaddedConvolution, StrayLightOperator, StrayLightPSF, gaussian_kernel


def subtract_uniform(s: np.ndarray, w: float) -> np.ndarray:
    """Thesis method 1: ``S_corr = S - w * sum_p S_p`` (sum over the ``H x W`` image).

    ``s`` is ``[..., H, W]`` complex; the sum is taken per leading index (per frequency).
    """
    s = np.asarray(s)
    return s - w * s.sum(axis=(-2, -1), keepdims=True)


def inverse_filter_gaussian(s: np.ndarray, sigma_h: float, sigma_v: float, w: float, mu: float) -> np.ndarray:
    """Thesis method 2: Wiener-like inverse filter of ``delta + w * G(sigma_h, sigma_v)``.

    ``H`` is the transfer function of ``delta + w G`` (the pixel-integrated Gaussian of
    ``sim/straylight/``) on the zero-padded grid; ``mu = 0`` is the plain inverse
    (``|H| >= 1 - w`` never vanishes for ``w < 1``). The result is cropped back.
    """
    s = np.asarray(s)
    h, wd = s.shape[-2:]
    k = w * gaussian_kernel((h, wd), sigma_h, sigma_v)
    k[h - 1, wd - 1] += 1.0
    # Twice the linear-convolution size: the filter's inverse has long tails of its own.
    fshape = (sfft.next_fast_len(h + k.shape[0] - 1), sfft.next_fast_len(wd + k.shape[1] - 1))
    # The simulator's padded convolution of this kernel (centre (H-1, W-1): no shift), inverted.
    return PaddedConvolution(k, (h, wd), (h - 1, wd - 1), fft_size=fshape).regularised_inverse(s, mu)


def scatter_uniform(s: np.ndarray, w: float) -> np.ndarray:
    """The stray light thesis method 1 assumes: ``w * sum_p S_p`` on every pixel."""
    s = np.asarray(s)
    return np.broadcast_to(w * s.sum(axis=(-2, -1), keepdims=True), s.shape)


def scatter_gaussian(s: np.ndarray, sigma_h: float, sigma_v: float, w: float) -> np.ndarray:
    """The stray light thesis method 2 assumes: ``w G(sigma_h, sigma_v) * S`` (zero-padded)."""
    s = np.asarray(s)
    h, wd = s.shape[-2:]
    k = w * gaussian_kernel((h, wd), sigma_h, sigma_v)
    return PaddedConvolution(k, (h, wd), (h - 1, wd - 1))(s)


def scatter_psf(s: np.ndarray, psf: StrayLightPSF, center_px: tuple[float, float] | None = None) -> np.ndarray:
    """The stray light of ``psf``: ``h * S`` without the direct part."""
    s = np.asarray(s)
    return StrayLightOperator(psf, s.shape[-2:], center_px).scatter(s)


def deconvolve(s_meas: np.ndarray, psf: StrayLightPSF, *, center_px: tuple[float, float] | None = None,
               iterations: int = 30, tol: float = 1e-7) -> np.ndarray:
    """Remove the stray light of ``psf`` from ``S_meas[..., H, W]`` (fixed point, see
    :meth:`StrayLightOperator.invert`); ghosts without a centre mirror through
    ``center_px`` (the camera's principal point; default the image centre)."""
    s_meas = np.asarray(s_meas)
    return StrayLightOperator(psf, s_meas.shape[-2:], center_px).invert(s_meas, iterations=iterations, tol=tol)


def load_psf(value: str | Path | StrayLightPSF) -> StrayLightPSF:
    """A PSF from a PSF file (``--save-psf``, ``stray_light_psf.json`` of diagnose) or from a
    diagnosis.json whose causes include stray light (its fitted effect parameters)."""
    if isinstance(value, StrayLightPSF):
        return value
    if value is None or str(value) == "":
        raise TofhilError("method 'psf' needs a PSF", field="psf",
                          expected="psf=FILE (a PSF file or diagnosis.json), or --calibrate CAL.h5")
    p = Path(value)
    if p.is_file() and p.suffix.lower() == ".json":
        try:
            doc = json.loads(p.read_text(encoding="utf-8"))
        except (UnicodeDecodeError, ValueError):
            doc = None  # StrayLightPSF.load says what is wrong
        if isinstance(doc, dict) and "format" not in doc and "causes" in doc:
            return psf_from_diagnosis(doc, p)
    return StrayLightPSF.load(p)


def psf_from_diagnosis(doc: dict[str, Any], path: str | Path) -> StrayLightPSF:
    """The stray-light PSF ``tofhil diagnose`` fitted (``params.stray_light`` of diagnosis.json),
    read through the effect's own parameter conversion (its defaults for what was not fitted)."""
    from tofhil.sim.effects import EFFECTS

    params = (doc.get("params") or {}).get("stray_light") if isinstance(doc.get("params"), dict) else None
    if not isinstance(params, dict):
        causes = ", ".join(doc.get("causes") or []) or "none"
        raise InputFileError(f"the diagnosis found no stray light (causes: {causes})", file=path,
                             field="params.stray_light", expected="a diagnosis whose causes include stray_light")
    effect = EFFECTS["stray_light"]
    values = effect.validate(params, source=path, prefix="params.stray_light")
    psf = effect.psf(values, source=path, prefix="params.stray_light", base_dir=Path(path).parent)
    return replace(psf, info={"source": "diagnosis", "file": str(path)})
