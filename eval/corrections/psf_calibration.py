"""Calibration of the stray-light PSF (the one type of ``sim/straylight.py``) from captures.

``h`` is fitted from a calibration capture whose stray-light-free signal is known (the twin's
render without stray light, or a bright target on a dark background) as a non-negative
combination of a fixed dictionary of shapes -- pixel-integrated Gaussians on a log-spaced
grid of widths, a uniform veil, and ghosts mirrored through the principal point (or a given
centre), sharp and blurred -- so the fit is linear (bounded NNLS) and needs no tuning; the
active Gaussians' widths are then refined continuously. Each weight is a fraction of light;
``direct`` (the light a pixel keeps) is fitted too, since both the additive and the
energy-conserving form occur in the literature. The basis columns are computed with the
simulator's own operators (:class:`GaussianBlur` on the image and on its mirror), so the
fitted PSF applied by :class:`StrayLightOperator` reproduces the fit exactly.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable

import numpy as np
from scipy.optimize import lsq_linear, minimize, nnls

from tofhil.errors import TofhilError
from tofhil.sim.straylight import (GaussianBlur, GaussianLobe, Ghost, StrayLightOperator, StrayLightPSF,
                                   flip_image, ghost_shift)

#: Narrowest lobe fitted (pixels); see :func:`default_sigmas`.
MIN_SIGMA_PX = 1.0
LOG_SIGMA_RANGE = (float(np.log(0.8)), float(np.log(3000.0)))


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
                  ghost_center_px: tuple[float, float] | None = None,
                  sigmas: np.ndarray | None = None, veil: bool = True, ghost: bool = True,
                  fit_direct: bool = True, weight: np.ndarray | None = None,
                  refine: bool = True) -> StrayLightPSF:
    """Fit ``direct`` and ``h`` so that ``direct * S_true + h * S_true`` matches ``S_meas``.

    Non-negative least squares over all pixels (real and imaginary parts). ``s_meas`` and
    ``s_true`` are ``[..., H, W]`` complex (frequencies / frames stacked in front);
    ``s_true`` is the stray-light-free signal of the calibration scene -- the twin's
    render without stray light, or the target pixels of a bright target on a dark
    background (:func:`calibrate_psf_target`). ``(cx, cy)`` is the camera's principal
    point; ghosts mirror through ``ghost_center_px`` (default the principal point, and the
    PSF then follows the camera it corrects). The dictionary: one Gaussian lobe per width
    in ``sigmas`` (default :func:`default_sigmas`), a uniform veil, the ghost (sharp and
    blurred by each width), and, with ``fit_direct``, the loss ``-S_true`` (light scattered
    away from its pixel). ``weight`` (``[H, W]``) weights pixels in the fit. With ``refine``
    the active Gaussians' widths are then optimised continuously and separately in x and y
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
    center = (float(cx), float(cy)) if ghost_center_px is None else (float(ghost_center_px[0]),
                                                                      float(ghost_center_px[1]))

    def column(b: np.ndarray) -> np.ndarray:
        bw = np.broadcast_to(b, s_true.shape).ravel() * wt
        return np.concatenate([bw.real, bw.imag])

    # Terms: (kind, label, (sigma_x, sigma_y) or None, column). kinds: gauss, veil, ghost, loss.
    # Each column is exactly what the simulator's operator does with a unit weight.
    terms: list[tuple[str, str, Any, np.ndarray]] = []
    blur = GaussianBlur(s_true)
    for sg in sig:
        terms.append(("gauss", f"gauss_{sg:.3g}", (sg, sg), column(blur(sg, sg))))
    if veil:
        # Unit fraction spread evenly: every pixel gets sum(S) / (H W).
        terms.append(("veil", "veil", None, column(s_true.sum(axis=(-2, -1), keepdims=True) / (h * w))))
    if ghost:
        mirror = GaussianBlur(flip_image(s_true))
        d = ghost_shift((h, w), center)
        for sg in np.concatenate([[0.0], sig]):
            terms.append(("ghost", f"ghost_{sg:.3g}", (sg, sg), column(mirror(sg, sg, d))))
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

        def solve(x: np.ndarray) -> tuple[np.ndarray, float, list[tuple[str, str, Any, np.ndarray]]]:
            gs = [("gauss", f"gauss_{sx:.3g}x{sy:.3g}", (sx, sy), column(blur(sx, sy)))
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
            terms, coef, rnorm = gs + fixed, c_ref, r_ref
    lobes, ghosts, veil_w, loss = [], [], 0.0, 0.0
    gc = None if ghost_center_px is None else center
    for (kind, _, sxy, _), c in zip(terms, coef):
        if c <= 0:
            continue
        if kind == "gauss":
            lobes.append(GaussianLobe(float(c), float(sxy[0]), float(sxy[1])))
        elif kind == "veil":
            veil_w += float(c)
        elif kind == "ghost":
            ghosts.append(Ghost(float(c), float(sxy[0]), gc))
        else:
            loss += float(c)
    info = {"basis": [t[1] for t in terms], "weights": [float(c) for c in coef],
            "relative_residual": float(rnorm / (np.linalg.norm(rhs) or 1.0)), "direct": 1.0 - loss}
    psf = StrayLightPSF(gaussians=tuple(lobes), veil=veil_w, ghosts=tuple(ghosts), conserve=False,
                        direct=1.0 - loss, info=info)
    info["scattered_fraction"] = StrayLightOperator(psf, (h, w), (cx, cy)).scattered_fraction
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
        s_true = np.where(mask, StrayLightOperator(psf, s_meas.shape[-2:], (cx, cy)).invert(s_meas), 0)
        psf = calibrate_psf(s_meas, s_true, cx, cy, **kwargs)
    psf.info["calibration"] = {"mode": "target", "threshold": threshold, "rounds": rounds,
                               "target_pixels": int(mask.sum())}
    return psf


def calibrate_from_sessions(capture: str | Path, reference: str | Path | None = None, *,
                            target_threshold: float = 0.2, flat: Any = None,
                            ghost_center_px: tuple[float, float] | None = None,
                            progress: Callable[[Any, int, str], Any] | None = None) -> StrayLightPSF:
    """Fit the PSF from a calibration session (frames averaged in the taps), against its
    stray-light-free twin ``reference`` or, without one, as a bright target on a dark
    background. ``flat`` (a tap calibration) is applied first, as to the sessions the PSF
    will correct. Refuses a degenerate fit."""
    from tofhil.demod import phasor
    from tofhil.eval.fixed_pattern import mean_taps

    if not 0 < target_threshold < 1:
        raise TofhilError(f"got {target_threshold!r}", field="target_threshold", expected="a fraction in (0, 1)")

    def mean_s(path: str | Path) -> tuple[np.ndarray, Any]:
        taps, camera, theta = mean_taps(path, progress)
        if flat is not None:
            taps = flat.apply(taps)
        return phasor(taps, theta), camera

    s_meas, cam = mean_s(capture)
    if reference is not None:
        s_true, _ = mean_s(reference)
        if s_true.shape != s_meas.shape:
            raise TofhilError(f"has signals of shape {s_true.shape}, the calibration capture {s_meas.shape}",
                              file=reference, field="raw/taps", expected="the same camera and frequencies")
        psf = calibrate_psf(s_meas, s_true, cam.cx, cam.cy, ghost_center_px=ghost_center_px)
        psf.info["calibration"] = {"mode": "reference", "capture": str(capture), "reference": str(reference)}
    else:
        psf = calibrate_psf_target(s_meas, cam.cx, cam.cy, threshold=target_threshold,
                                   ghost_center_px=ghost_center_px)
        psf.info["calibration"]["capture"] = str(capture)
    if psf.keep <= 0.1 + 1e-9 or psf.info["scattered_fraction"] >= psf.keep:
        raise TofhilError(f"the PSF fit is degenerate (direct {psf.keep:.3f}, scattered "
                          f"{psf.info['scattered_fraction']:.3f})", file=reference or capture,
                          expected="a noise-free twin reference (tofhil simulate --no-noise) or more frames "
                                   "averaged, and a capture whose stray light is visible")
    return psf
