"""Calibration of the stray-light PSF (the one type of ``sim/straylight/``) from captures.

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

from dataclasses import replace
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
from scipy.optimize import lsq_linear, minimize, nnls

from tofhil.errors import TofhilError
from tofhil.sim.straylight import (GaussianBlur, GaussianLobe, Ghost, StrayLightOperator, StrayLightPSF,
                                   field_rho2, flip_image, ghost_shift)

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
                  ghost_center_px: tuple[float, float] | str | None = None,
                  sigmas: np.ndarray | None = None, veil: bool = True, ghost: bool = True,
                  fit_direct: bool = True, weight: np.ndarray | None = None,
                  refine: bool = True, field: bool | int | str = False,
                  lambdas: Sequence[float] | None = None,
                  ghost_magnification: float | str = -1.0) -> StrayLightPSF:
    """Fit ``direct`` and ``h`` so that ``direct * S_true + h * S_true`` matches ``S_meas``.

    Bounded least squares over all pixels (real and imaginary parts). ``s_meas`` and
    ``s_true`` are ``[..., H, W]`` complex (captures / frequencies stacked in front);
    ``s_true`` is the stray-light-free signal of the calibration scene -- the twin's
    render without stray light, or the target pixels of a bright target on a dark
    background (:func:`calibrate_psf_target`). ``(cx, cy)`` is the camera's principal
    point. The ghost mirrors through ``ghost_center_px``: default the principal point (the
    PSF then follows the camera it corrects), a given ``(x, y)``, or ``"fit"``: found by
    correlating the residual of a fit without ghost with the mirrored image, then refined
    to sub-pixel with the lobes' widths. The dictionary: one Gaussian lobe per width in
    ``sigmas`` (default :func:`default_sigmas`; many widths make any radial fall-off,
    power-law tails included), with ``field`` the same lobes applied to ``rho^2 S`` (signed:
    a shift-variant lobe that grows or shrinks towards the field edge) and, with ``field=2``,
    to ``rho^4 S`` as well (second order in ``rho^2``: a lobe that widens towards the edge;
    :data:`FREE_FORM` has ``field="select"``: the order chosen on held-out captures by
    :func:`select_field_order`, order 1 here with a twin reference), a uniform veil, the
    ghost (sharp and blurred by each width), and, with ``fit_direct``, the loss ``-S_true``.
    ``weight`` (broadcastable to ``s_true``) weights pixels. ``lambdas``: strengths of a
    smoothness penalty on the lobe fractions across widths, the one with the least error on
    held-out pixels (interleaved 8 x 8 blocks) is used; None = no penalty. With ``refine``
    the active Gaussians' widths are optimised continuously, separately in x and y
    (variable projection). ``info`` holds the fit-quality report (:func:`_quality`).
    """
    if field == "select":  # the order is chosen on held-out captures by calibrate_psf_target
        field = 1
    s_meas = np.asarray(s_meas, dtype=np.complex128)
    s_true = np.asarray(s_true, dtype=np.complex128)
    if s_meas.shape != s_true.shape:
        raise ValueError(f"measured {s_meas.shape} and true {s_true.shape} signals differ in shape")
    h, w = s_true.shape[-2:]
    sig = default_sigmas(h, w) if sigmas is None else np.asarray(sigmas, dtype=np.float64)
    wt = np.ones((h, w)) if weight is None else np.sqrt(np.asarray(weight, dtype=np.float64))
    wt = np.broadcast_to(wt, s_true.shape).ravel()
    fit_centre = isinstance(ghost_center_px, str)
    if fit_centre and ghost_center_px != "fit":
        raise ValueError(f"ghost_center_px must be (x, y), None or 'fit', got {ghost_center_px!r}")
    center = ((float(cx), float(cy)) if ghost_center_px is None or fit_centre
              else (float(ghost_center_px[0]), float(ghost_center_px[1])))
    fit_mag = isinstance(ghost_magnification, str)
    if fit_mag and ghost_magnification != "fit":
        raise ValueError(f"ghost_magnification must be a number or 'fit', got {ghost_magnification!r}")
    mag = -1.0 if fit_mag else float(ghost_magnification)

    problem = _Problem(s_meas, s_true, (float(cx), float(cy)), wt, len(sig), field=field, ghost=ghost)
    terms = _dictionary(problem, sig, field=field, veil=veil, fit_direct=fit_direct)
    visibility = _ghost_visibility(problem.ghost_image(0.0, center, mag), wt.reshape(s_true.shape)) if ghost else None
    mag_scores: dict[float, float] = {}
    if ghost:
        center, mag, mag_scores = _place_ghost(problem, terms, center, mag, sig, fit_centre=fit_centre, fit_mag=fit_mag)
        terms += problem.ghost_terms(center, mag, sig)
    lam, scores = _smoothness(problem, terms, lambdas)
    coef, rnorm = problem.fit(terms, lam)
    if refine and np.any(coef[:problem.n_gauss] > 0):
        terms, coef, rnorm, center, mag = _refine_widths(problem, terms, coef, rnorm, center, mag, sig,
                                                         fit_centre=fit_centre, fit_mag=fit_mag)
    psf, loss = _psf_of_terms(terms, coef, None if ghost_center_px is None else center)
    info = _quality(terms, coef, problem.rhs, rnorm, float(np.linalg.norm(s_meas)), lam, scores,
                    captures=int(s_true.shape[0]) if s_true.ndim == 4 else 1)
    info["direct"] = 1.0 - loss
    if psf.ghosts and fit_centre:
        info["ghost_center_px"] = [float(center[0]), float(center[1])]
    if ghost:
        _report_ghost(info, psf, center, mag, mag_scores, visibility, fit_mag=fit_mag,
                      captures=int(s_true.shape[0]) if s_true.ndim == 4 else 1)
    psf = replace(psf, info=info)
    info["scattered_fraction"] = StrayLightOperator(psf, (h, w), (cx, cy)).scattered_fraction
    return psf


#: One dictionary term: (kind, label, widths, column). Kinds: gauss, field, field4 (widths
#: ``(sigma_x, sigma_y)``), ghost (``(sigma, sigma, magnification)``), veil, loss (None).
Term = tuple[str, str, Any, np.ndarray]


class _Problem:
    """The linear problem of one calibration: the right-hand side ``S_meas - S_true`` and the
    columns of the dictionary, each exactly what the simulator's operator does with a unit
    weight (real and imaginary parts of every pixel, weighted: :meth:`column`), and their
    bounded least-squares fit (:meth:`fit`)."""

    def __init__(self, s_meas: np.ndarray, s_true: np.ndarray, principal_px: tuple[float, float], wt: np.ndarray,
                 n_gauss: int, *, field: bool | int, ghost: bool) -> None:
        self.s_true = s_true
        self.shape = s_true.shape[-2:]
        self.principal_px = principal_px
        self.wt = wt
        #: The first ``n_gauss`` terms are the dictionary's Gaussian lobes.
        self.n_gauss = n_gauss
        self.blur = GaussianBlur(s_true)
        rho2 = field_rho2(self.shape, principal_px)
        self.fblur = GaussianBlur(rho2 * s_true) if field else None
        # Second order: a lobe whose width triples from axis to corner is not linear in rho^2.
        self.fblur4 = GaussianBlur(rho2 ** 2 * s_true) if field and int(field) >= 2 else None
        self.mirror = GaussianBlur(flip_image(s_true)) if ghost else None
        self.rhs = self.column(s_meas - s_true)
        self.bb = float(self.rhs @ self.rhs)

    def column(self, b: np.ndarray) -> np.ndarray:
        bw = np.broadcast_to(b, self.s_true.shape).ravel() * self.wt
        return np.concatenate([bw.real, bw.imag])

    def ghost_image(self, sg: float, c: tuple[float, float], m: float) -> np.ndarray:
        if m == -1.0:  # the mirror: a convolution of the flipped image (one FFT for all widths)
            return self.mirror(sg, sg, ghost_shift(self.shape, c))
        op = StrayLightOperator(StrayLightPSF(ghosts=(Ghost(1.0, sg, c, m),), conserve=False), self.shape, c)
        return op.scatter(self.s_true)

    def ghost_terms(self, c: tuple[float, float], m: float, sig: np.ndarray) -> list[Term]:
        # Terms carry (sigma, sigma, m): the magnification travels with the column.
        return [("ghost", f"ghost_{sg:.3g}" + ("" if m == -1.0 else f"_m{m:.3g}"), (sg, sg, m),
                 self.column(self.ghost_image(sg, c, m))) for sg in np.concatenate([[0.0], sig])]

    @staticmethod
    def bounds(ts: list[Term]) -> tuple[np.ndarray, np.ndarray]:
        # Every weight is a fraction of light in [0, 1] (a field term in [-1, 1]); the loss at
        # most 0.9 (a lens that keeps less than a tenth of the light on its pixel is not a
        # camera). The bounds keep an ill-posed fit from trading huge terms against each other.
        lo = np.array([-1.0 if k[0] in ("field", "field4") else 0.0 for k in ts])
        up = np.array([0.9 if k[0] == "loss" else 1.0 for k in ts])
        return lo, up

    @staticmethod
    def penalty(ts: list[Term]) -> np.ndarray:
        p = np.zeros((len(ts), len(ts)))
        for kind in ("gauss", "field", "field4"):
            idx = [i for i, k in enumerate(ts) if k[0] == kind]
            if len(idx) > 2:
                d2 = _second_differences(len(idx))
                p[np.ix_(idx, idx)] += d2.T @ d2
        return p

    def fit(self, ts: list[Term], lam: float, rows: np.ndarray | None = None) -> tuple[np.ndarray, float]:
        """The bounded least-squares weights of the terms ``ts`` (on ``rows`` only, if given),
        with the smoothness penalty of strength ``lam``, and the residual norm on all rows."""
        a = np.stack([k[3] for k in ts], axis=1)
        am, bm = (a, self.rhs) if rows is None else (a[rows], self.rhs[rows])
        gram = am.T @ am
        lo, up = self.bounds(ts)
        scale = float(np.mean(np.diag(gram)[:self.n_gauss])) or 1.0
        coef = _bounded_gram(gram + lam * scale * self.penalty(ts), am.T @ bm, lo, up)
        r = a @ coef - self.rhs
        return coef, float(np.sqrt(r @ r))


def _dictionary(problem: _Problem, sig: np.ndarray, *, field: bool | int, veil: bool, fit_direct: bool) -> list[Term]:
    """The dictionary without its ghost: a lobe per width (and their field copies), the veil
    and the loss."""
    terms: list[Term] = []
    for sg in sig:
        terms.append(("gauss", f"gauss_{sg:.3g}", (sg, sg), problem.column(problem.blur(sg, sg))))
    if field:
        for sg in sig:
            terms.append(("field", f"field_{sg:.3g}", (sg, sg), problem.column(problem.fblur(sg, sg))))
        for sg in sig if problem.fblur4 is not None else ():
            terms.append(("field4", f"field4_{sg:.3g}", (sg, sg), problem.column(problem.fblur4(sg, sg))))
    if veil:
        # Unit fraction spread evenly: every pixel gets sum(S) / (H W).
        h, w = problem.shape
        terms.append(("veil", "veil", None, problem.column(problem.s_true.sum(axis=(-2, -1), keepdims=True) / (h * w))))
    if fit_direct:
        terms.append(("loss", "loss", None, problem.column(-problem.s_true)))
    return terms


def _place_ghost(problem: _Problem, terms: list[Term], center: tuple[float, float], mag: float, sig: np.ndarray, *,
                 fit_centre: bool, fit_mag: bool) -> tuple[tuple[float, float], float, dict[float, float]]:
    """The ghost's centre (``fit_centre``: the mirror shift that best explains the residual of a
    fit without ghost) and magnification (``fit_mag``: the dictionary fitted with the ghost at
    each of :data:`MAGNIFICATIONS`, the least residual wins), and the residual of each."""
    h, w = problem.shape
    if fit_centre:
        coef0, _ = problem.fit(terms, 0.0)
        a0 = np.stack([k[3] for k in terms], axis=1)
        s_true = problem.s_true
        d = _find_ghost(a0 @ coef0 - problem.rhs, s_true,
                        np.broadcast_to(problem.wt.reshape(s_true.shape) ** 2, s_true.shape), (h, w),
                        problem.principal_px)
        if d is not None:
            center = (0.5 * (d[0] + (w - 1)), 0.5 * (d[1] + (h - 1)))
    mag_scores: dict[float, float] = {}
    if fit_mag:
        # Coarse: the whole dictionary with the ghost at each magnification (the mirror's centre
        # found above; a magnified ghost about the same centre), the least residual wins.
        for m in MAGNIFICATIONS:
            mag_scores[m] = problem.fit(terms + problem.ghost_terms(center, m, sig), 0.0)[1]
        mag = min(mag_scores, key=mag_scores.get)
    return center, mag, mag_scores


def _smoothness(problem: _Problem, terms: list[Term], lambdas: Sequence[float] | None) -> tuple[float, dict[float, float]]:
    """The strength of the smoothness penalty with the least error on held-out pixels
    (interleaved 8 x 8 blocks, real and imaginary rows of a pixel together), and each
    strength's error; 0 without ``lambdas``."""
    lam, scores = 0.0, {}
    if lambdas:
        h, w = problem.shape
        yy, xx = np.mgrid[0:h, 0:w]
        fold = np.tile(np.broadcast_to(((yy // 8 + xx // 8) % 2).astype(bool), problem.s_true.shape).ravel(), 2)
        a = np.stack([k[3] for k in terms], axis=1)
        for lm in lambdas:
            err = 0.0
            for f in (fold, ~fold):
                c, _ = problem.fit(terms, lm, f)
                r = a[~f] @ c - problem.rhs[~f]
                err += float(r @ r)
            scores[float(lm)] = err
        lam = min(scores, key=scores.get)
    return lam, scores


def _refine_widths(problem: _Problem, terms: list[Term], coef: np.ndarray, rnorm: float, center: tuple[float, float],
                   mag: float, sig: np.ndarray, *, fit_centre: bool, fit_mag: bool
                   ) -> tuple[list[Term], np.ndarray, float, tuple[float, float], float]:
    """Variable projection: each run of neighbouring active widths becomes one Gaussian with
    free (sigma_x, sigma_y); with a fitted ghost its centre is refined too; the weights are
    re-solved linearly for every trial. Returns the terms, weights and residual norm (the
    refined ones where they fit better) and the ghost's centre and magnification."""
    n_gauss, rhs, bb = problem.n_gauss, problem.rhs, problem.bb
    groups = _active_groups(coef[:n_gauss])
    fixed = [k for k, c in zip(terms[n_gauss:], coef[n_gauss:]) if c != 0 and k[0] != "ghost"]
    fixed_a = np.stack([k[3] for k in fixed], axis=1) if fixed else np.zeros((rhs.size, 0))
    g_ff, c_f = fixed_a.T @ fixed_a, fixed_a.T @ rhs
    gi = [i for i, k in enumerate(terms) if k[0] == "ghost"]
    g_sig = np.array([terms[i][2][0] for i in gi])
    # Each run of neighbouring active blurs becomes one ghost of continuous width.
    # A ghost the dictionary gives almost no light (< GHOST_MIN_WEIGHT: a lens without one) is
    # not refined: its extra parameters only slow the lobes' refinement (docs/evaluation.md).
    ghost_groups = _active_groups(coef[gi]) if gi and float(np.sum(coef[gi])) > GHOST_MIN_WEIGHT else []
    ghost_init = [max(float(np.average(g_sig[g], weights=coef[gi][g])), 0.3) for g in ghost_groups]
    init = np.array([np.exp(np.average(np.log(sig[g]), weights=coef[g])) for g in groups])
    n_lobe = 2 * len(groups)
    n_gc = 2 if ghost_groups and fit_centre else 0
    n_gs = len(ghost_groups)

    dictionary_lobes = [k for k, c in zip(terms[:n_gauss], coef[:n_gauss]) if c > 0]

    def solve(x: np.ndarray, nl: int) -> tuple[np.ndarray, float, list[Term]]:
        # nl = 0: the dictionary's active lobes as they are, only the ghost refined.
        gs = dictionary_lobes if nl == 0 else [
            ("gauss", f"gauss_{sx:.3g}x{sy:.3g}", (sx, sy), problem.column(problem.blur(sx, sy)))
            for sx, sy in np.exp(np.clip(x[:nl], LOG_SIGMA_RANGE[0], LOG_SIGMA_RANGE[1])).reshape(-1, 2)]
        extra: list[Term] = []
        if ghost_groups:
            c = (center[0] + x[nl], center[1] + x[nl + 1]) if n_gc else center
            m = float(x[nl + n_gc + n_gs]) if fit_mag else mag
            for sg in np.exp(np.clip(x[nl + n_gc:nl + n_gc + n_gs], np.log(0.05), LOG_SIGMA_RANGE[1])):
                extra.append(("ghost", f"ghost_{sg:.3g}" + ("" if m == -1.0 else f"_m{m:.3g}"), (sg, sg, m),
                              problem.column(problem.ghost_image(float(sg), c, m))))
        new = gs + extra
        a_g = np.stack([k[3] for k in new], axis=1)
        gram = np.block([[a_g.T @ a_g, a_g.T @ fixed_a], [fixed_a.T @ a_g, g_ff]])
        lo, up = problem.bounds(new + fixed)
        cc = _bounded_gram(gram, np.concatenate([a_g.T @ rhs, c_f]), lo, up)
        res2 = bb - 2 * cc @ np.concatenate([a_g.T @ rhs, c_f]) + cc @ gram @ cc
        return cc, float(np.sqrt(max(res2, 0.0))), new + fixed

    # First lobes and ghost together; then, if there is a ghost, the ghost alone beside the
    # dictionary's lobes: merging a run of active widths into one lobe can lose more than
    # the ghost's refinement gains (three lobes a factor 4-5 apart), and the ghost's blur
    # and magnification must not be lost with it. The better fit is kept.
    for nl in ([n_lobe, 0] if ghost_groups else [n_lobe]):
        x0 = np.concatenate([np.log(np.repeat(init, 2))[:nl], np.zeros(n_gc), np.log(ghost_init),
                             [mag] if ghost_groups and fit_mag else []])
        # The first simplex spans steps the fit can feel (scipy's default steps a parameter
        # that starts at 0 by 2.5e-4: a centre offset would never leave the integer shift the
        # correlation found): 10 % in width, half a pixel in the centre, 0.05 in magnification.
        steps = np.concatenate([np.full(nl, 0.1), np.full(n_gc, 0.5), np.full(n_gs, 0.1),
                                [0.05] if ghost_groups and fit_mag else []])
        res = minimize(lambda x: solve(x, nl)[1], x0, method="Nelder-Mead",
                       options={"xatol": 1e-3, "fatol": 1e-7 * rnorm, "maxfev": min(80 * x0.size + 40, 600),
                                "initial_simplex": np.vstack([x0, x0 + np.diag(steps)])})
        c_ref, r_ref, ts = solve(res.x, nl)
        if r_ref < rnorm:
            terms, coef, rnorm = ts, c_ref, r_ref
            if n_gc:
                center = (center[0] + res.x[nl], center[1] + res.x[nl + 1])
            if ghost_groups and fit_mag:
                mag = float(res.x[nl + n_gc + n_gs])
    return terms, coef, rnorm, center, mag


def _psf_of_terms(terms: list[Term], coef: np.ndarray, ghost_center_px: tuple[float, float] | None
                  ) -> tuple[StrayLightPSF, float]:
    """The PSF of the fitted weights (additive, ``direct = 1 - loss``) and the loss."""
    lobes, ghosts, veil_w, loss = [], [], 0.0, 0.0
    field_w: dict[float, list[float]] = {}
    for (kind, _, sxy, _), c in zip(terms, coef):
        if kind in ("field", "field4") and c != 0:
            field_w.setdefault(float(sxy[0]), [0.0, 0.0])[kind == "field4"] = float(c)
        if c <= 0:
            continue
        if kind == "gauss":
            lobes.append(GaussianLobe(float(c), float(sxy[0]), float(sxy[1])))
        elif kind == "veil":
            veil_w += float(c)
        elif kind == "ghost":
            ghosts.append(Ghost(float(c), float(sxy[0]), ghost_center_px, float(sxy[2])))
        elif kind == "loss":
            loss += float(c)
    # A field term is a lobe of its own (weight 0 on axis, signed growth) with its own width.
    lobes += [GaussianLobe(0.0, s, s, fw[0], fw[1]) for s, fw in field_w.items()]
    psf = StrayLightPSF(gaussians=tuple(lobes), veil=veil_w, ghosts=tuple(ghosts), conserve=False,
                        direct=1.0 - loss)
    return psf, loss


def _report_ghost(info: dict[str, Any], psf: StrayLightPSF, center: tuple[float, float], mag: float,
                  mag_scores: dict[float, float], visibility: float, *, fit_mag: bool, captures: int) -> None:
    """What the fit says about its ghost (in ``info``): how much of it the fit pixels see, the
    magnification found, and the warnings when the data cannot constrain it."""
    info["ghost_visibility"] = visibility
    if fit_mag:
        info["ghost_magnification"] = mag
        info["ghost_magnification_scan"] = {f"{k:g}": v for k, v in mag_scores.items()}
    if visibility < GHOST_VISIBILITY_MIN:
        info["warnings"].append(
            f"the calibration cannot see a ghost through ({center[0]:.1f}, {center[1]:.1f}) px: only "
            f"{100 * visibility:.0f} % of its image falls on the fit pixels (it lands on the target itself); its "
            "weight, blur and centre are not constrained: add a capture with the target away from the centre")
    if psf.ghosts and fit_mag and captures == 1 and abs(mag + 1.0) > GHOST_MAGNIFICATION_TOL:
        # A ghost magnified about its centre spreads the target's light more toward the
        # corners, as a lobe that widens across the field does: one target position shows
        # the two alike (docs/evaluation.md).
        info["warnings"].append(
            f"the fitted ghost is magnified x{mag:.2f} (not the inverted image through its centre): from one "
            "capture it cannot be told apart from a stray-light lobe that widens across the field; calibrate "
            "from the target at several field positions (the bench procedure: a card and bright patches)")


def _quality(terms: list[tuple[str, str, Any, np.ndarray]], coef: np.ndarray, rhs: np.ndarray, rnorm: float,
             signal: float, lam: float, scores: dict[float, float], captures: int = 1) -> dict[str, Any]:
    """The fit-quality report: residual relative to the stray light and to the signal, the
    condition of the (column-scaled) design, each active component's variance inflation
    (``(C^-1)_jj`` of the correlation matrix: 1 = independent of the others, > 1e6 = the data
    cannot tell it from the others), and warnings."""
    a = np.stack([k[3] for k in terms], axis=1)
    gram = a.T @ a
    dg = np.sqrt(np.clip(np.diag(gram), 1e-300, None))
    corr = gram / np.outer(dg, dg)
    active = np.flatnonzero(coef != 0)
    vif = np.abs(np.diag(np.linalg.pinv(corr[np.ix_(active, active)]))) if active.size else np.zeros(0)
    stray_raw = float(np.linalg.norm(rhs))  # the stray light on the fit's pixels
    stray = stray_raw or 1.0
    sig = signal or 1.0  # the whole capture's signal
    names = [terms[i][1] for i in active]
    warnings: list[str] = []
    rel = rnorm / stray
    if rel > 0.1:
        warnings.append(f"the fit leaves {100 * rel:.0f} % of the calibration's stray light unexplained: the lens "
                        "has a form the PSF model cannot represent, the reference is wrong, or the capture is noisy")
    weak = [n for n, v in zip(names, vif) if v > VIF_LIMIT]
    if weak:
        warnings.append("the calibration data cannot constrain " + ", ".join(weak) + " (variance inflation > 1e6): "
                        "add captures (a bright patch at other field positions, a card off-axis) or average more "
                        "frames")
    if any(terms[i][0] in ("field", "field4") for i in active) and captures == 1:
        warnings.append("shift-variant (field) lobes were fitted from one capture: a source at one field "
                        "position cannot tell them from the others; add a bright patch at other field positions")
    if stray_raw / sig < 1e-4:
        warnings.append("the calibration capture shows almost no stray light (< 1e-4 of the signal)")
    return {"basis": [k[1] for k in terms], "weights": [float(c) for c in coef],
            "relative_residual": rel, "residual_relative_to_signal": rnorm / sig,
            "condition": float(np.linalg.cond(corr)), "variance_inflation": dict(zip(names, map(float, vif))),
            "lambda": lam, "heldout_error": {str(k): v for k, v in scores.items()}, "warnings": warnings}


#: Variance inflation above which a component is reported as not constrained by the data.
VIF_LIMIT = 1e6
#: Ghost fraction of light below which the refinement leaves the ghost out.
GHOST_MIN_WEIGHT = 1e-3
#: A fitted ghost magnification farther than this from -1 (the image inverted through its
#: centre) is a magnified ghost.
GHOST_MAGNIFICATION_TOL = 0.05
#: Fraction of a sharp ghost's image on the fit pixels below which the ghost is reported unseen.
GHOST_VISIBILITY_MIN = 0.1
#: Ghost magnifications the dictionary is fitted with before the continuous refinement
#: (``ghost_magnification="fit"``): mirrors (lens ghosts that invert) and upright ghosts
#: (a filter's or a cover glass's, slightly magnified; sim/optics.py traces 1.2-1.5).
MAGNIFICATIONS = (-1.5, -1.25, -1.0, -0.8, 0.8, 1.1, 1.25, 1.5)


def _ghost_visibility(image: np.ndarray, weight: np.ndarray) -> float:
    """Fraction (in energy) of a ghost's image that lands on the fit pixels (``weight``: the
    square root of the pixel weights): 0 when every capture's ghost falls on its own target."""
    total = float(np.sum(np.abs(image) ** 2))
    return float(np.sum(np.abs(image * weight) ** 2)) / total if total > 0 else 0.0


def _second_differences(n: int) -> np.ndarray:
    d = np.zeros((max(n - 2, 0), n))
    for i in range(n - 2):
        d[i, i:i + 3] = (1.0, -2.0, 1.0)
    return d


def _bounded_gram(gram: np.ndarray, atb: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """``min ||A x - b||`` with ``lower <= x <= upper`` from the normal equations (Cholesky of
    the column-scaled Gram matrix: a k x k problem instead of one row per pixel)."""
    d = np.sqrt(np.clip(np.diag(gram), 0, None))
    d[d == 0] = 1.0
    g = gram / np.outer(d, d)
    k = g.shape[0]
    r = np.linalg.cholesky(g + 1e-12 * np.eye(k))
    y = np.linalg.solve(r, atb / d)  # r lower-triangular: R^T = r, so R^-T c = r^-1 c
    if not np.any(lower < 0):
        coef, _ = nnls(r.T, y, maxiter=50 * k)
        if np.all(coef <= upper * d):
            return coef / d
    res = lsq_linear(r.T, y, bounds=(lower * d, upper * d), method="bvls")
    return res.x / d


def _find_ghost(resid: np.ndarray, s_true: np.ndarray, weight: np.ndarray, shape: tuple[int, int],
                center: tuple[float, float], search_px: float | None = None) -> tuple[float, float] | None:
    """The shift ``d`` of the mirrored image (``d = 2c - (W-1, H-1)``) that best explains the
    residual ``A c - b`` (weighted rows) of a fit without ghost: normalised cross-correlation
    over integer shifts within ``search_px`` (default 0.4 of the sensor's larger side) of the
    principal point's mirror."""
    # (A search over every shift, the full [2H-1, 2W-1] correlation of two images: scipy's
    # 'full' fftconvolve, not the PSF's same-size operator of sim/straylight/.)
    from scipy.signal import fftconvolve

    h, w = shape
    size = s_true.size
    r = -(resid[:size] + 1j * resid[size:]).reshape(s_true.shape)  # b - A c, rows weighted by sqrt(w)
    r = (r * np.sqrt(weight)).reshape((-1, h, w))
    m = flip_image(s_true).reshape((-1, h, w))
    wts = np.asarray(weight).reshape((-1, h, w))
    num = np.zeros((2 * h - 1, 2 * w - 1))
    den = np.zeros_like(num)
    for k in range(m.shape[0]):
        # num[d] = Re sum_q r(q) conj(m(q - d)) sqrt(w(q)); index (h-1, w-1) is d = 0.
        num += fftconvolve(r[k], np.conj(m[k][::-1, ::-1]), mode="full").real
        den += fftconvolve(wts[k], (np.abs(m[k]) ** 2)[::-1, ::-1], mode="full")
    dy, dx = np.mgrid[-(h - 1):h, -(w - 1):w]
    d0 = ghost_shift(shape, center)
    lim = search_px if search_px is not None else 0.4 * max(h, w)
    score = np.where((den > 0) & (num > 0) & (np.hypot(dx - d0[0], dy - d0[1]) <= lim),
                     num / np.sqrt(np.maximum(den, 1e-300)), -np.inf)
    if not np.isfinite(score.max()):
        return None
    iy, ix = np.unravel_index(int(np.argmax(score)), score.shape)
    return float(dx[iy, ix]), float(dy[iy, ix])


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


def calibrate_psf_target(s_meas: np.ndarray | Sequence[np.ndarray], cx: float, cy: float, *,
                         threshold: float = 0.2, rounds: int = 4, **kwargs: Any) -> StrayLightPSF:
    """Calibrate from bright targets on a dark background alone (no twin needed): one capture
    ``[..., H, W]`` or several of the same camera (a card on black, a bright patch at several
    field positions), fitted together.

    The fit uses the background pixels only (their true signal is zero). Round 0 takes
    the measured target pixels as the true source, which still holds the stray light the
    target throws on itself; each further round uses the target pixels of the measurement
    deconvolved with the previous PSF instead. Scattering that never leaves the target
    cannot be seen this way (nor does it matter for other pixels).
    """
    many = isinstance(s_meas, (list, tuple))
    stack = np.stack([np.asarray(s, dtype=np.complex128) for s in s_meas]) if many \
        else np.asarray(s_meas, dtype=np.complex128)[None]
    if stack.ndim == 3:
        stack = stack[:, None]
    masks = np.stack([target_mask(s, threshold) for s in stack])[:, None]  # [N, 1, H, W]
    selection = None
    if kwargs.get("field") == "select":
        kwargs["field"], selection = select_field_order(list(stack), cx, cy, threshold=threshold, **kwargs)
    # The target's own pixels say nothing about h (their true value is unknown): fit
    # only the background, where the true signal is known to be zero.
    kwargs.setdefault("weight", (~masks).astype(np.float64))
    s_true = np.where(masks, stack, 0)
    psf = calibrate_psf(stack, s_true, cx, cy, **kwargs)
    for _ in range(rounds - 1):
        s_true = np.where(masks, StrayLightOperator(psf, stack.shape[-2:], (cx, cy)).invert(stack), 0)
        psf = calibrate_psf(stack, s_true, cx, cy, **kwargs)
    psf.info["calibration"] = {"mode": "target", "threshold": threshold, "rounds": rounds, "captures": len(stack),
                               "target_pixels": [int(m.sum()) for m in masks]}
    if selection is not None:
        psf.info["field_order_selection"] = selection
    return psf


def select_field_order(captures: Sequence[np.ndarray], cx: float, cy: float, *, threshold: float = 0.2,
                       orders: Sequence[int] = (1, 2), **kwargs: Any) -> tuple[int, dict[str, Any]]:
    """The order of the shift-variant lobes (1: ``rho^2``; 2: ``rho^2`` and ``rho^4``) that
    best predicts a capture the fit has not seen: leave one capture (one field position)
    out, fit the others, predict its background. The error that matters is the extrapolation
    to other field positions, which held-out pixels of the same captures do not see: on a
    shift-invariant lens the second order's extra terms, unconstrained by five positions,
    trade against the lobes and the veil and predict a new position worse. Fewer than three
    captures: order 1. The fits here are the quick ones (one round, no width refinement, no
    smoothness search: the same choice as two rounds on every test lens, at half the cost).
    Returns the order and the leave-one-out residuals."""
    if len(captures) < 3:
        # One capture cannot constrain a shift-variant lobe at all; two only at first order.
        order = int(len(captures) > 1)
        return order, {"orders": {}, "chosen": order, "reason": "fewer than three captures"}
    kw = {k: v for k, v in kwargs.items() if k not in ("field", "refine", "lambdas", "weight")}
    scores: dict[int, float] = {}
    for order in orders:
        err = 0.0
        for i in range(len(captures)):
            train = [c for j, c in enumerate(captures) if j != i]
            psf = calibrate_psf_target(train, cx, cy, threshold=threshold, rounds=1, refine=False, field=order,
                                       lambdas=None, **kw)
            c = np.asarray(captures[i])
            m = target_mask(c, threshold)
            op = StrayLightOperator(psf, c.shape[-2:], (cx, cy))
            r = (op.apply(np.where(m, op.invert(c), 0)) - c)[..., ~m]
            err += float(np.sum(np.abs(r) ** 2))
        scores[int(order)] = err
    best = min(scores, key=scores.get)
    return best, {"orders": {str(k): v for k, v in scores.items()}, "chosen": best,
                  "reason": "least leave-one-capture-out residual"}


#: The free-form calibration's options (:func:`calibrate_psf`): many widths with a
#: shift-variant copy (its order chosen on held-out captures, :func:`select_field_order`),
#: a fitted ghost centre, smoothness chosen on held-out pixels.
FREE_FORM: dict[str, Any] = {"field": "select", "ghost_center_px": "fit", "ghost_magnification": "fit",
                             "lambdas": (0.0, 1e-6, 1e-5, 1e-4, 1e-3, 1e-2)}


def calibrate_from_sessions(capture: str | Path | Sequence[str | Path],
                            reference: str | Path | Sequence[str | Path] | None = None, *,
                            target_threshold: float = 0.2, flat: Any = None,
                            ghost_center_px: tuple[float, float] | str | None = None, form: str = "gaussian",
                            progress: Callable[[Any, int, str], Any] | None = None) -> StrayLightPSF:
    """Fit the PSF from one or more calibration sessions (frames averaged in the taps), each
    against its stray-light-free twin in ``reference`` (as many, in the same order) or,
    without, as bright targets on a dark background. ``flat`` (a tap calibration) is applied
    first, as to the sessions the PSF will correct. ``form``: ``"gaussian"`` (a dictionary of
    Gaussian widths, veil, ghost through ``ghost_center_px``) or ``"free"`` (:data:`FREE_FORM`:
    shift-variant lobes when there are several captures, fitted ghost centre, regularised).
    Refuses a degenerate fit."""
    from tofhil.demod import phasor
    from tofhil.eval.calibration.taps import mean_taps

    if not 0 < target_threshold < 1:
        raise TofhilError(f"got {target_threshold!r}", field="target_threshold", expected="a fraction in (0, 1)")
    if form not in ("gaussian", "free"):
        raise TofhilError(f"got {form!r}", field="--psf-form", expected="gaussian or free")
    captures = [capture] if isinstance(capture, (str, Path)) else list(capture)
    refs = None if reference is None else ([reference] if isinstance(reference, (str, Path)) else list(reference))
    if refs is not None and len(refs) != len(captures):
        raise TofhilError(f"{len(refs)} references for {len(captures)} calibration captures", field="--reference",
                          expected="one --reference per --calibrate, in the same order")

    def mean_s(path: str | Path) -> tuple[np.ndarray, Any]:
        taps, camera, theta = mean_taps(path, progress)
        if flat is not None:
            taps = flat.apply(taps)
        return phasor(taps, theta), camera

    kw: dict[str, Any] = dict(FREE_FORM) if form == "free" else {}
    if form == "free":
        # One capture sees each source at one field position: a shift-variant lobe is not
        # identifiable from it (the fit would trade it against the others).
        kw["field"] = "select" if len(captures) > 2 else len(captures) > 1
    if ghost_center_px is not None:
        kw["ghost_center_px"] = ghost_center_px
    meas = [mean_s(c) for c in captures]
    cam = meas[0][1]
    for c, (s, _) in zip(captures, meas):
        if s.shape != meas[0][0].shape:
            raise TofhilError(f"has signals of shape {s.shape}, the first calibration capture {meas[0][0].shape}",
                              file=c, field="raw/taps", expected="the same camera and frequencies")
    if refs is not None:
        trues = [mean_s(r)[0] for r in refs]
        for r, s_true, (s, _) in zip(refs, trues, meas):
            if s_true.shape != s.shape:
                raise TofhilError(f"has signals of shape {s_true.shape}, the calibration capture {s.shape}",
                                  file=r, field="raw/taps", expected="the same camera and frequencies")
        psf = calibrate_psf(np.stack([m[0] for m in meas]), np.stack(trues), cam.cx, cam.cy, **kw)
        psf.info["calibration"] = {"mode": "reference", "capture": [str(c) for c in captures],
                                   "reference": [str(r) for r in refs]}
    else:
        psf = calibrate_psf_target([m[0] for m in meas], cam.cx, cam.cy, threshold=target_threshold, **kw)
        psf.info["calibration"]["capture"] = [str(c) for c in captures]
    psf.info["calibration"]["form"] = form
    if psf.keep <= 0.1 + 1e-9 or psf.info["scattered_fraction"] >= psf.keep:
        raise TofhilError(f"the PSF fit is degenerate (direct {psf.keep:.3f}, scattered "
                          f"{psf.info['scattered_fraction']:.3f})", file=(refs or captures)[0],
                          expected="a noise-free twin reference (tofhil simulate --no-noise) or more frames "
                                   "averaged, and a capture whose stray light is visible")
    return psf
