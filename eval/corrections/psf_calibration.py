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

from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
from scipy.optimize import lsq_linear, minimize, nnls

from tofhil.errors import TofhilError
from tofhil.sim.straylight import (GaussianBlur, GaussianLobe, Ghost, PaddedConvolution, RadialProfile,
                                   StrayLightOperator, StrayLightPSF, field_rho2, flip_image, ghost_shift,
                                   radial_hat_sums, radial_hats, shift_grid)

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


# ---------------------------------------------------------------------------------------------
# Free-form calibration: radial profile, fitted ghost, field-dependent lobe, veil
# ---------------------------------------------------------------------------------------------
#: Smoothness strengths tried (times the mean diagonal of the radial block of the Gram matrix).
LAMBDAS = (0.0, 1e-7, 1e-6, 1e-5, 1e-4, 1e-3, 1e-2)
#: Variance inflation above which a component is reported as not constrained by the data.
VIF_LIMIT = 1e6


def radial_knots(height: int, width: int, ratio: float = 2 ** 0.5) -> np.ndarray:
    """Log-spaced knots from 1 px to beyond the sensor diagonal (ratio sqrt 2)."""
    top = float(np.hypot(height, width))
    n = int(np.ceil(np.log(top) / np.log(ratio))) + 1
    return ratio ** np.arange(n)


@dataclass
class _Capture:
    """One calibration capture: measured and stray-light-free signals, pixel weights."""

    s_meas: np.ndarray
    s_true: np.ndarray
    weight: np.ndarray

    @cached_property
    def sqrt_w(self) -> np.ndarray:
        return np.broadcast_to(np.sqrt(self.weight), self.s_true.shape)

    def column(self, b: np.ndarray) -> np.ndarray:
        bw = np.broadcast_to(b, self.s_true.shape) * self.sqrt_w
        return np.concatenate([bw.real.ravel(), bw.imag.ravel()])

    @cached_property
    def mirror(self) -> GaussianBlur:
        return GaussianBlur(flip_image(self.s_true))


def _second_differences(n: int) -> np.ndarray:
    d = np.zeros((max(n - 2, 0), n))
    for i in range(n - 2):
        d[i, i:i + 3] = (1.0, -2.0, 1.0)
    return d


def calibrate_psf_free(captures: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray | None]], cx: float, cy: float,
                       *, knots: np.ndarray | None = None, field: bool = True, veil: bool = True,
                       ghost: bool = True, fit_direct: bool = True, lambdas: Sequence[float] = LAMBDAS,
                       ghost_search_px: float | None = None) -> StrayLightPSF:
    """Fit a free-form PSF to one or more calibration captures ``(s_meas, s_true, weight)``.

    ``h`` = a radial profile on log-spaced ``knots`` (non-negative, any fall-off: heavy
    tails included) + with ``field`` the same profile's growth towards the field edge
    (``rho^2`` times a second profile: a shift-variant lobe) + a uniform veil + a ghost with
    FITTED centre and blur (found by correlating the residual with the mirrored image, then
    refined) + the loss ``-S_true`` (``direct``). Every weight is a fraction of light. The
    radial profiles are regularised by the second differences of their per-knot fractions;
    the strength is chosen on held-out pixels (two interleaved 8 x 8-block folds of the fit
    pixels). ``info`` reports the relative residual, the chosen strength, each component's
    variance inflation (how well the data pin it down) and ``warnings``.
    """
    h, w = captures[0][1].shape[-2:]
    center = (float(cx), float(cy))
    caps = [_Capture(np.asarray(m, np.complex128), np.asarray(t, np.complex128),
                     np.ones((h, w)) if wt is None else np.asarray(wt, np.float64)) for m, t, wt in captures]
    for c in caps:
        if c.s_meas.shape != c.s_true.shape or c.s_true.shape[-2:] != (h, w):
            raise ValueError(f"measured {c.s_meas.shape} and true {c.s_true.shape} signals differ in shape")
    kn = radial_knots(h, w) if knots is None else np.asarray(knots, np.float64)
    sums = radial_hat_sums(tuple(kn))
    hats = radial_hats(kn, *shift_grid((h, w)))
    rho2 = field_rho2((h, w), center)
    # Columns per capture; radial columns are unit fractions of light (hat / its plane sum).
    labels: list[str] = [f"radial_{r:.3g}" for r in kn]
    if field:
        labels += [f"field_{r:.3g}" for r in kn]
    if veil:
        labels.append("veil")
    if fit_direct:
        labels.append("loss")
    blocks, rhs = [], []
    for c in caps:
        cols = []
        for j in range(kn.size):
            cols.append(c.column(PaddedConvolution(hats[j] / sums[j], (h, w), (h - 1, w - 1))(c.s_true)))
        if field:
            src = rho2 * c.s_true
            for j in range(kn.size):
                cols.append(c.column(PaddedConvolution(hats[j] / sums[j], (h, w), (h - 1, w - 1))(src)))
        if veil:
            cols.append(c.column(c.s_true.sum(axis=(-2, -1), keepdims=True) / (h * w)))
        if fit_direct:
            cols.append(c.column(-c.s_true))
        blocks.append(np.stack(cols, axis=1))
        rhs.append(c.column(c.s_meas - c.s_true))
    a = np.concatenate(blocks)
    b = np.concatenate(rhs)
    n_rad = kn.size * (2 if field else 1)
    lower = np.zeros(len(labels))
    upper = np.ones(len(labels))
    if fit_direct:
        upper[-1] = 0.9
    if field:
        lower[kn.size:n_rad] = -1.0  # a lobe may also weaken towards the field edge
    pen = np.zeros((len(labels), len(labels)))
    d2 = _second_differences(kn.size)
    for s0 in ((0, kn.size), (kn.size, n_rad)) if field else ((0, kn.size),):
        pen[s0[0]:s0[1], s0[0]:s0[1]] = d2.T @ d2

    # Held-out folds: interleaved 8 x 8 blocks of every capture's pixels (real and imaginary
    # rows of a pixel stay in the same fold).
    yy, xx = np.mgrid[0:h, 0:w]
    fold_px = ((yy // 8 + xx // 8) % 2).astype(bool)
    fold = np.concatenate([np.tile(np.broadcast_to(fold_px, c.s_true.shape).ravel(), 2) for c in caps])

    def ghost_cols(g: tuple[float, float, float] | None) -> np.ndarray:
        if g is None:
            return np.zeros((b.size, 0))
        dx, dy, sg = g
        return np.concatenate([c.column(c.mirror(sg, sg, (dx, dy))) for c in caps])[:, None]

    def solve(g: tuple[float, float, float] | None, lam: float, rows: np.ndarray | None = None
              ) -> tuple[np.ndarray, float]:
        ag = np.concatenate([a, ghost_cols(g)], axis=1)
        lo = np.concatenate([lower, np.zeros(ag.shape[1] - a.shape[1])])
        up = np.concatenate([upper, np.full(ag.shape[1] - a.shape[1], 1.0)])
        p = np.zeros((ag.shape[1],) * 2)
        p[:len(labels), :len(labels)] = pen
        am, bm = (ag, b) if rows is None else (ag[rows], b[rows])
        gram = am.T @ am
        scale = float(np.mean(np.diag(gram)[:kn.size])) or 1.0
        coef = _bounded_gram(gram + lam * scale * p, am.T @ bm, lo, up)
        return coef, float(np.linalg.norm(ag @ coef - b) if rows is None else 0.0)

    def heldout(g: tuple[float, float, float] | None, lam: float) -> float:
        err = 0.0
        ag = np.concatenate([a, ghost_cols(g)], axis=1)
        for f in (fold, ~fold):
            coef, _ = solve(g, lam, f)
            err += float(np.sum((ag[~f] @ coef - b[~f]) ** 2))
        return err

    lam = lambdas[0]
    g_fit: tuple[float, float, float] | None = None
    if ghost:
        coef0, _ = solve(None, 1e-5)
        g_fit = _find_ghost(caps, a @ coef0 - b, (h, w), center, ghost_search_px)
    scores = {lm: heldout(g_fit, lm) for lm in lambdas}
    lam = min(scores, key=scores.get)
    if ghost and g_fit is not None:
        from scipy.optimize import minimize as _min

        def obj(x: np.ndarray) -> float:
            return solve((x[0], x[1], float(np.exp(x[2]))), lam)[1]

        x0 = np.array([g_fit[0], g_fit[1], np.log(max(g_fit[2], 0.5))])
        res = _min(obj, x0, method="Nelder-Mead", options={"xatol": 1e-2, "fatol": 1e-9, "maxfev": 200})
        g_fit = (float(res.x[0]), float(res.x[1]), float(np.exp(res.x[2])))
    coef, rnorm = solve(g_fit, lam)
    # Components -> the one PSF type.
    c_rad = coef[:kn.size]
    c_field = coef[kn.size:n_rad] if field else np.zeros(0)
    i = n_rad
    veil_w = float(coef[i]) if veil else 0.0
    i += int(veil)
    loss = float(coef[i]) if fit_direct else 0.0
    i += int(fit_direct)
    ghosts: tuple[Ghost, ...] = ()
    if g_fit is not None and coef[i] > 0:
        gcx = 0.5 * (g_fit[0] + (w - 1))  # d = 2c - (W-1, H-1)
        gcy = 0.5 * (g_fit[1] + (h - 1))
        ghosts = (Ghost(float(coef[i]), g_fit[2], (gcx, gcy)),)
    radial = RadialProfile(tuple(float(r) for r in kn), tuple(float(v) for v in c_rad / sums),
                           tuple(float(v) for v in c_field / sums) if field else ())
    # Quality: residual, identifiability (variance inflation of each column, unregularised
    # and with the chosen smoothness), warnings.
    ag = np.concatenate([a, ghost_cols(g_fit)], axis=1)
    names = labels + (["ghost"] if g_fit is not None else [])
    gram = ag.T @ ag
    dg = np.sqrt(np.clip(np.diag(gram), 1e-300, None))
    corr = gram / np.outer(dg, dg)
    p = np.zeros_like(gram)
    p[:len(labels), :len(labels)] = pen
    scale = float(np.mean(np.diag(gram)[:kn.size])) or 1.0
    corr_reg = (gram + lam * scale * p) / np.outer(dg, dg)
    vif = np.diag(np.linalg.pinv(corr_reg))
    cond = float(np.linalg.cond(corr))
    stray = float(np.linalg.norm(b)) or 1.0
    signal = float(np.linalg.norm(np.concatenate([c.column(c.s_meas) for c in caps]))) or 1.0
    warnings: list[str] = []
    rel = rnorm / stray
    if rel > 0.1:
        warnings.append(f"the fit leaves {100 * rel:.0f} % of the calibration's stray light unexplained: "
                        "the lens has a form the PSF model cannot represent, or the reference is wrong")
    weak = [nm for nm, v in zip(names, vif) if v > VIF_LIMIT]
    if weak:
        warnings.append("the calibration data cannot constrain " + ", ".join(weak)
                        + " (variance inflation > 1e6): add captures (a bright patch at other field "
                          "positions, a card off-axis) or average more frames")
    if stray / signal < 1e-4:
        warnings.append("the calibration capture shows almost no stray light (< 1e-4 of the signal)")
    info = {"form": "free", "knots_px": kn.tolist(), "weights": [float(x) for x in coef], "basis": names,
            "lambda": lam, "heldout_error": {str(k): v for k, v in scores.items()},
            "relative_residual": rel, "residual_relative_to_signal": rnorm / signal,
            "condition": cond, "variance_inflation": {nm: float(v) for nm, v in zip(names, vif)},
            "direct": 1.0 - loss, "warnings": warnings, "captures": len(caps)}
    psf = StrayLightPSF(veil=veil_w, ghosts=ghosts, radial=radial, conserve=False, direct=1.0 - loss, info=info)
    info["scattered_fraction"] = StrayLightOperator(psf, (h, w), center).scattered_fraction
    return psf


def _bounded_gram(gram: np.ndarray, atb: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """``min x^T G x - 2 x^T c`` with ``lower <= x <= upper`` (bounded least squares via the
    Cholesky factor of the column-scaled Gram matrix)."""
    d = np.sqrt(np.clip(np.diag(gram), 0, None))
    d[d == 0] = 1.0
    g = gram / np.outer(d, d)
    k = g.shape[0]
    r = np.linalg.cholesky(g + 1e-12 * np.eye(k))
    y = np.linalg.solve(r, atb / d)
    res = lsq_linear(r.T, y, bounds=(lower * d, upper * d), method="bvls")
    return res.x / d


def _find_ghost(caps: Sequence[_Capture], resid: np.ndarray, shape: tuple[int, int], center: tuple[float, float],
                search_px: float | None) -> tuple[float, float, float] | None:
    """The ghost's shift ``d`` (of the mirrored image) that best explains the residual
    ``A c - b`` of a fit without ghost: normalised cross-correlation over integer shifts
    within ``search_px`` of the principal point's mirror, then a blur guess of 2 px."""
    from scipy.signal import fftconvolve

    h, w = shape
    n = 0
    num = np.zeros((2 * h - 1, 2 * w - 1))
    den = np.zeros_like(num)
    for c in caps:
        size = c.s_true.size
        r = -(resid[n:n + size] + 1j * resid[n + size:n + 2 * size]).reshape(c.s_true.shape)  # b - A c
        n += 2 * size
        r = r * np.sqrt(c.weight)  # the residual rows are weighted by sqrt(w); the model too
        m = flip_image(c.s_true)
        for k in range(m.shape[0] if m.ndim == 3 else 1):
            mk = m[k] if m.ndim == 3 else m
            rk = r[k] if r.ndim == 3 else r
            # num[d] = Re sum_q r(q) conj(m(q - d)) * sqrt(w(q)): correlation of r with m.
            num += fftconvolve(rk, np.conj(mk[::-1, ::-1]), mode="full").real
            den += fftconvolve(c.weight, (np.abs(mk) ** 2)[::-1, ::-1], mode="full")
    # Index (h-1, w-1) of the 'full' output is shift 0.
    dy, dx = np.mgrid[-(h - 1):h, -(w - 1):w]
    d0 = ghost_shift(shape, center)
    lim = search_px if search_px is not None else 0.4 * max(h, w)
    score = np.where((den > 0) & (num > 0) & (np.hypot(dx - d0[0], dy - d0[1]) <= lim),
                     num / np.sqrt(np.maximum(den, 1e-300)), -np.inf)
    if not np.isfinite(score.max()):
        return None
    iy, ix = np.unravel_index(int(np.argmax(score)), score.shape)
    return float(dx[iy, ix]), float(dy[iy, ix]), 2.0


def calibrate_free_target(s_meas: Sequence[np.ndarray], cx: float, cy: float, *, threshold: float = 0.2,
                          rounds: int = 3, **kwargs: Any) -> StrayLightPSF:
    """Free-form calibration from bright targets on a dark background alone (one or more
    captures, e.g. a card on black and a bright patch at several field positions): fit on
    the background pixels (true signal zero); the targets' true signal is the measurement,
    then, each further round, the measurement deconvolved with the previous fit."""
    meas = [np.asarray(s, np.complex128) for s in s_meas]
    masks = [target_mask(s, threshold) for s in meas]
    trues = [np.where(m, s, 0) for s, m in zip(meas, masks)]
    psf = None
    for k in range(rounds):
        if psf is not None:
            op = StrayLightOperator(psf, meas[0].shape[-2:], (cx, cy))
            trues = [np.where(m, op.invert(s), 0) for s, m in zip(meas, masks)]
        psf = calibrate_psf_free([(s, t, (~m).astype(np.float64)) for s, t, m in zip(meas, trues, masks)],
                                 cx, cy, **kwargs)
    assert psf is not None
    psf.info["calibration"] = {"mode": "target", "form": "free", "threshold": threshold, "rounds": rounds,
                               "target_pixels": [int(m.sum()) for m in masks]}
    return psf
