"""Photon transfer (EMVA 1288) of a correlation (ToF) sensor from flat-field and dark captures.

Inputs are captures at a series of integration times: each a stack of raw frames
``[N, K, H, W]`` (DN, the taps as the driver delivers them), flat (uniform modulated light)
or dark. Per capture and tap: the spatial mean of the per-pixel temporal mean and variance
(the variance with its standard error over the pixels).

Two readouts are handled:

* **single-ended taps** (each tap one gate's charge, plus a black level): EMVA 1288 as written.
  ``var = K (mu - mu_dark) + var_dark``, ``var_dark = K^2 sigma_r^2 + K^2 D t + 1/12``,
  ``mu_dark = mu_0 + K D t``.
* **differential taps** (``tap_{k+2} = -tap_k``: the pixel reads the difference of its two
  gates, as the epc635 does; the common mode -- the collected charge EMVA plots -- cancels).
  ``d_k = (c_k - c_{k+2}) / 2`` has mean ``A cos(phi - theta_k)`` and temporal variance
  ``K (c_k + c_{k+2}) / 4 + K^2 sigma_r^2 / 2 + 1/12`` with ``c_k + c_{k+2} = 2 (A / m + K D t)``
  (``m`` the modulation contrast: the unmodulated part of the modulated light is ``A / m``).
  So ``var = alpha A + beta t + gamma`` with ``alpha = K / (2 m)``, ``beta = K^2 D / 2``,
  ``gamma = K^2 sigma_r^2 / 2 + 1/12``: the conversion gain is known only with the
  contrast, which the differential taps cannot see (it is taken from the sensor block or a
  grayscale capture). DSNU shows as the difference of two gates' offsets (``/ sqrt 2``); the
  full well as the clip of the brighter gate, read back through the other gate's expected
  charge.

Every quantity comes with a 1-sigma uncertainty: the weighted least-squares covariance (the
weights from the variances' standard errors over pixels, scaled by the reduced chi-square
when it exceeds 1), spatial variances with their sampling variance ``2 s^4 / (n - 1)``, and
first-order propagation. What is taken as known (the contrast) is stated, not fitted.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from tofhil.errors import TofhilError

#: Variance of rounding to whole DN (uniform quantisation), DN^2.
QUANT_VAR_DN2 = 1.0 / 12.0


@dataclass
class PtcCapture:
    """One capture of the series: ``frames[N, K, H, W]`` (DN), flat or dark, at one exposure."""

    integration_time_s: float
    flat: bool
    frames: np.ndarray
    label: str = ""
    freq_hz: float = math.nan


@dataclass
class Estimate:
    """A value with its 1-sigma uncertainty and unit."""

    value: float
    sigma: float
    unit: str = ""

    def to_dict(self) -> dict[str, Any]:
        return {"value": self.value, "sigma": self.sigma, "unit": self.unit}

    def covers(self, truth: float, k: float = 1.0) -> bool:
        return abs(self.value - truth) <= k * self.sigma


@dataclass
class CaptureStats:
    """Per capture: exposure, the signal tap's mean, amplitude and temporal variance (+- s.e.)."""

    label: str
    integration_time_s: float
    flat: bool
    mean_dn: float
    amplitude_dn: float
    var_dn2: float
    var_se_dn2: float
    spatial_var_dn2: float
    used: bool = True


@dataclass
class PhotonTransfer:
    """The EMVA 1288 quantities of one sensor (one frequency), with uncertainties."""

    readout: str
    conversion_gain_dn_per_e: Estimate
    read_noise_e: Estimate
    dark_current_e_per_s: Estimate
    dsnu_e: Estimate
    prnu: Estimate
    full_well_e: Estimate
    linearity_error_pct: Estimate
    modulation_contrast: float
    captures: list[CaptureStats]
    fit: dict[str, Any] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    #: Every tap's per-pixel dark offset ``[K, H, W]`` (DN): the mean of the dark captures.
    dark_offset_dn: np.ndarray | None = field(default=None, repr=False)

    def tap_gains(self) -> np.ndarray:
        """Every tap's conversion gain relative to the taps' mean ``[K]`` (differential taps: tap
        ``k + K/2`` shares tap ``k``'s, its gates being the same two)."""
        per = self.fit.get("per_tap") or []
        if not per:
            return np.ones(0)
        g = np.array([t["conversion_gain_dn_per_e"] for t in per])
        g = g / g.mean()
        return np.concatenate([g, g]) if self.readout == "differential" else g

    def quantities(self) -> dict[str, Estimate]:
        return {"conversion_gain_dn_per_e": self.conversion_gain_dn_per_e, "read_noise_e": self.read_noise_e,
                "dark_current_e_per_s": self.dark_current_e_per_s, "dsnu_e": self.dsnu_e, "prnu": self.prnu,
                "full_well_e": self.full_well_e, "linearity_error_pct": self.linearity_error_pct}

    def to_dict(self) -> dict[str, Any]:
        return {"readout": self.readout, "modulation_contrast": self.modulation_contrast,
                "quantities": {k: v.to_dict() for k, v in self.quantities().items()},
                "captures": [c.__dict__ for c in self.captures], "fit": self.fit, "notes": self.notes}

    def sensor_block(self, base: dict[str, Any] | None = None) -> dict[str, Any]:
        """The scene's ``sensor:`` block with the measured quantities (over ``base``, e.g. the
        twin's block, for the fields photon transfer does not measure)."""
        out = dict(base or {})
        out.update({"conversion_gain_dn_per_e": self.conversion_gain_dn_per_e.value,
                    "read_noise_e": max(self.read_noise_e.value, 0.0),
                    "dark_current_e_per_s": max(self.dark_current_e_per_s.value, 0.0),
                    "modulation_contrast": self.modulation_contrast})
        if math.isfinite(self.full_well_e.value) and self.full_well_e.value > 0:
            out["full_well_e"] = self.full_well_e.value
        fp = dict(out.get("fixed_pattern") or {})
        fp.update({"dsnu_e": max(self.dsnu_e.value, 0.0), "prnu": max(self.prnu.value, 0.0)})
        out["fixed_pattern"] = fp
        return out


def is_differential(frames: np.ndarray) -> bool:
    """Taps ``k + K/2`` are the negatives of taps ``k`` (a two-gate differential readout): within
    one DN (the rounding of ``offset +- x`` differs by one where ``x`` falls on a half DN) for
    at least 99 % of the values."""
    k = frames.shape[1]
    if k % 2:
        return False
    h = k // 2
    s = frames[:, h:].astype(np.float64) + frames[:, :h]
    return bool(np.all(np.abs(s) <= 1.0) and np.mean(s != 0) < 0.01)


def _wls(x: np.ndarray, y: np.ndarray, se: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Weighted least squares ``y = x @ p``; the covariance scaled by the reduced chi-square when > 1."""
    w = 1.0 / np.maximum(se, 1e-300)
    a = x * w[:, None]
    b = y * w
    p, *_ = np.linalg.lstsq(a, b, rcond=None)
    cov = np.linalg.pinv(a.T @ a)
    dof = len(y) - x.shape[1]
    chi2 = float(np.sum((a @ p - b) ** 2))
    red = chi2 / dof if dof > 0 else 1.0
    return p, cov * max(red, 1.0), red


def _pattern_and_noise(s2: float, n: int, var_each: Sequence[float]) -> float:
    """Standard error of a fixed pattern's variance ``s2`` estimated from several captures of
    ``n`` pixels each, whose variances ``var_each`` hold the pattern's own sampling part
    ``2 s2^2 / (n - 1)`` (the same in every capture) and the temporal noise's (independent)."""
    pattern = 2.0 * s2 ** 2 / (n - 1)
    noise = np.maximum(np.asarray(var_each, dtype=np.float64) - pattern, 1e-300)
    return math.sqrt(pattern + 1.0 / float(np.sum(1.0 / noise)))


def _pixel_stats(frames: np.ndarray, taps: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel temporal mean and variance ``[len(taps), H, W]``."""
    f = frames[:, list(taps)].astype(np.float64)
    return f.mean(axis=0), f.var(axis=0, ddof=1)


def photon_transfer(captures: Sequence[PtcCapture], *, modulation_contrast: float | None = None,
                    theta_rad: Sequence[float] | None = None) -> PhotonTransfer:
    """The EMVA 1288 quantities from a series of flat and dark captures (see the module doc).

    ``modulation_contrast`` is needed for differential taps (the conversion gain is otherwise
    known only as K / m); ``theta_rad`` the taps' phases (default equally spaced)."""
    flats = sorted((c for c in captures if c.flat), key=lambda c: c.integration_time_s)
    darks = sorted((c for c in captures if not c.flat), key=lambda c: c.integration_time_s)
    if len(darks) < 2 or len(flats) < 3:
        raise TofhilError(f"{len(flats)} flat and {len(darks)} dark captures", field="captures",
                          expected="at least 3 flat and 2 dark captures at different integration times")
    if any(c.frames.shape[0] < 2 for c in captures):
        raise TofhilError("a capture has fewer than 2 frames", field="frames", expected="2 or more frames per capture")
    k_taps = captures[0].frames.shape[1]
    diff = all(is_differential(c.frames) for c in captures)
    theta = np.asarray(theta_rad if theta_rad is not None else 2 * np.pi * np.arange(k_taps) / k_taps)
    taps = list(range(k_taps // 2)) if diff else list(range(k_taps))
    notes: list[str] = []
    if diff:
        if modulation_contrast is None or not modulation_contrast > 0:
            raise TofhilError("differential taps hide the common mode", field="modulation_contrast",
                              expected="the sensor's modulation contrast (from its sensor block)")
        m = float(modulation_contrast)
        notes.append(f"differential taps (tap k+{k_taps // 2} = -tap k): the collected charge cancels; the "
                     f"conversion gain is K = 2 m alpha with the modulation contrast m = {m:g} taken as known")
    else:
        m = float(modulation_contrast) if modulation_contrast else math.nan

    # the signal tap: the one the flat field drives hardest (its mean is largest in magnitude)
    mu_last, _ = _pixel_stats(flats[0].frames, taps)
    sig = int(np.argmax(np.abs(mu_last.reshape(len(taps), -1).mean(axis=1))))
    sign = float(np.sign(mu_last[sig].mean())) or 1.0

    stats: list[CaptureStats] = []
    per: dict[int, dict[str, np.ndarray]] = {}

    def pixel_phasor(c: PtcCapture) -> np.ndarray:
        full_mu, _ = _pixel_stats(c.frames, range(k_taps))
        return (2.0 / k_taps) * np.tensordot(np.exp(1j * theta), full_mu, axes=(0, 0))

    # the dark phasor of each pixel (its gates' fixed offsets) is taken off the flats' before the
    # amplitude: |S| of a flat would otherwise carry the DSNU's share (+ sigma^2 / 2A at low A)
    s_dark = np.mean([pixel_phasor(c) for c in darks], axis=0)
    for c in [*darks, *flats]:
        mu, var = _pixel_stats(c.frames, taps)
        n_pix = var[0].size
        s = pixel_phasor(c) - s_dark
        amp = np.abs(s)
        v_all = var.reshape(len(taps), -1)
        # the variance of every independent tap carries the same (common-mode) information
        # when differential; a single-ended signal tap only its own
        v_use = v_all if diff else v_all[sig:sig + 1]
        v_mean = float(v_use.mean())
        v_se = float(v_use.mean(axis=0).std(ddof=1) / math.sqrt(n_pix))
        st = CaptureStats(c.label, c.integration_time_s, c.flat, float(sign * mu[sig].mean()),
                          float(amp.mean()) if c.flat else 0.0, v_mean, v_se,
                          float(mu[sig].var(ddof=1)))
        stats.append(st)
        per[id(st)] = {"mu": mu[sig] * sign, "amp": amp, "var": var[sig], "s": s, "mu_all": mu,
                       "var_taps": [(float(v.mean()), float(v.std(ddof=1) / math.sqrt(v.size))) for v in v_all]}

    dark_st = [s for s in stats if not s.flat]
    flat_st = [s for s in stats if s.flat]
    # the photon-transfer curve turns down where the brighter gate saturates; fit below 70 % of the peak
    peak = int(np.argmax([s.var_dn2 for s in flat_st]))
    lin_cap = 0.7 * flat_st[peak].amplitude_dn
    lin = [s for s in flat_st if s.amplitude_dn <= lin_cap]
    if len(lin) < 2:
        lin = flat_st[: max(peak, 2)]
    for s in flat_st:
        s.used = s in lin
    t_d = np.array([s.integration_time_s for s in dark_st])
    v_d = np.array([s.var_dn2 for s in dark_st])
    se_d = np.array([s.var_se_dn2 for s in dark_st])
    t_f = np.array([s.integration_time_s for s in lin])
    v_f = np.array([s.var_dn2 for s in lin])
    se_f = np.array([s.var_se_dn2 for s in lin])
    if diff:
        x_f = np.array([s.amplitude_dn for s in lin])
    else:
        # signal above dark: the dark mean at the same exposure (a line through the dark captures)
        mu_d = np.array([s.mean_dn for s in dark_st])
        dpar = np.polyfit(t_d, mu_d, 1)
        x_f = np.array([s.mean_dn for s in lin]) - np.polyval(dpar, t_f)
    x = np.concatenate([np.column_stack([np.zeros_like(t_d), t_d, np.ones_like(t_d)]),
                        np.column_stack([x_f, t_f, np.ones_like(t_f)])])
    y = np.concatenate([v_d, v_f])
    se = np.concatenate([se_d, se_f])
    (alpha, beta, gamma), cov, red = _wls(x, y, se)
    # per tap: the same fit on each tap's own variances (a tap whose gain differs shows here)
    per_tap = []
    if diff or k_taps > 1:
        for j in range(len(taps)):
            yj = np.array([per[id(s_)]["var_taps"][j][0] for s_ in [*dark_st, *lin]])
            sj = np.array([per[id(s_)]["var_taps"][j][1] for s_ in [*dark_st, *lin]])
            pj, cj, _ = _wls(x, yj, sj)
            fac = 2.0 * m if diff else 1.0
            per_tap.append({"tap": taps[j], "conversion_gain_dn_per_e": float(fac * pj[0]),
                            "sigma": float(fac * math.sqrt(cj[0, 0]))})
    sa, sb, sg = np.sqrt(np.diag(cov))

    if diff:
        k = 2.0 * m * alpha
        sk = 2.0 * m * sa
        rn2 = 2.0 * (gamma - QUANT_VAR_DN2) / k ** 2
        # d(rn2) = 2 dgamma / k^2 - 4 (gamma - q) dk / k^3
        j_rn = np.array([-2 * 2.0 * (gamma - QUANT_VAR_DN2) / k ** 3 * 2 * m, 0.0, 2.0 / k ** 2])
        dark = 2.0 * beta / k ** 2
        j_dark = np.array([-4.0 * beta / k ** 3 * 2 * m, 2.0 / k ** 2, 0.0])
    else:
        k, sk = alpha, sa
        rn2 = (gamma - QUANT_VAR_DN2) / k ** 2
        j_rn = np.array([-2.0 * (gamma - QUANT_VAR_DN2) / k ** 3, 0.0, 1.0 / k ** 2])
        # single-ended: the dark current from the dark mean's slope (EMVA's own method)
        dark = float(dpar[0]) / k
        j_dark = np.zeros(3)
    s_rn2 = math.sqrt(max(float(j_rn @ cov @ j_rn), 0.0))
    rn = math.sqrt(max(rn2, 0.0))
    s_rn = s_rn2 / (2 * rn) if rn > 0 else math.sqrt(s_rn2)
    if diff:
        s_dark = math.sqrt(max(float(j_dark @ cov @ j_dark), 0.0))
    else:
        res = mu_d - np.polyval(dpar, t_d)
        s_slope = math.sqrt(np.sum(res ** 2) / max(len(t_d) - 2, 1) / np.sum((t_d - t_d.mean()) ** 2)) \
            if len(t_d) > 2 else abs(dpar[0]) * 0.1
        s_dark = abs(dark) * math.hypot(s_slope / abs(dpar[0]) if dpar[0] else 0.0, sk / k)

    # DSNU: the dark captures' spatial variance of the temporal mean, less the temporal part
    dsnu2, dsnu2_var = [], []
    for s in dark_st:
        p = per[id(s)]
        n_pix = p["mu"].size
        n_fr = next(c.frames.shape[0] for c in darks if c.label == s.label)
        mu_all = p["mu_all"]
        sp = mu_all.reshape(mu_all.shape[0], -1).var(axis=1, ddof=1).mean() - s.var_dn2 / n_fr
        dsnu2.append(sp)
        dsnu2_var.append(2.0 * (sp + s.var_dn2 / n_fr) ** 2 / (n_pix * mu_all.shape[0] - 1))
    w = 1.0 / np.asarray(dsnu2_var)
    dsnu2_dn = float(np.sum(w * np.asarray(dsnu2)) / np.sum(w))
    # one pattern seen in every dark capture: its sampling error (2 s^4 / (n - 1)) does not
    # average out over them; the temporal noise's share does
    n_pat = p["mu_all"].size
    s_dsnu2_dn = _pattern_and_noise(dsnu2_dn, n_pat, dsnu2_var)
    fac = 2.0 if diff else 1.0  # a differential tap sees the difference of two gates' offsets
    dsnu = math.sqrt(max(fac * dsnu2_dn, 0.0)) / k
    s_dsnu = (math.sqrt(fac) * s_dsnu2_dn / (2 * math.sqrt(max(dsnu2_dn, 1e-30))) / k if dsnu > 0 else math.nan)
    s_dsnu = math.hypot(s_dsnu, dsnu * sk / k)

    # PRNU: the flat captures' spatial variance of the signal tap, less DSNU and the temporal part
    dark_mu = per[id(dark_st[0])]["mu"]
    pr, pr_var = [], []
    for s in lin:
        p = per[id(s)]
        n_fr = next(c.frames.shape[0] for c in flats if c.label == s.label)
        net = p["mu"] - dark_mu
        mean = float(net.mean())
        if not abs(mean) > 0:
            continue
        sp = net.var(ddof=1) - s.var_dn2 / n_fr - dark_st[0].var_dn2 / darks[0].frames.shape[0]
        n_pix = net.size
        sp_var = 2.0 * net.var(ddof=1) ** 2 / (n_pix - 1)
        pr.append(sp / mean ** 2)
        pr_var.append(sp_var / mean ** 4)
    w = 1.0 / np.asarray(pr_var)
    prnu2 = float(np.sum(w * np.asarray(pr)) / np.sum(w))
    prnu = math.sqrt(max(prnu2, 0.0))
    # as for DSNU: one pattern in every flat
    s_prnu2 = _pattern_and_noise(prnu2, per[id(lin[0])]["mu"].size, pr_var)
    s_prnu = s_prnu2 / (2 * prnu) if prnu > 0 else math.nan

    # linearity: the signal against exposure on the linear part (EMVA: 5-95 % of saturation)
    sig_lin = np.array([s.amplitude_dn if diff else s.mean_dn - np.polyval(dpar, s.integration_time_s) for s in lin])
    lpar = np.polyfit(t_f, sig_lin, 1)
    dev = 100.0 * (sig_lin - np.polyval(lpar, t_f)) / np.polyval(lpar, t_f)
    le = 0.5 * float(dev.max() - dev.min())
    # the deviations' own noise: the signal's standard error over pixels
    s_sig = np.array([math.sqrt(per[id(s)]["var"].mean() / per[id(s)]["var"].size / 1.0) for s in lin])
    s_le = float(np.sqrt(np.mean((100.0 * s_sig / np.abs(np.polyval(lpar, t_f))) ** 2)))

    # full well: the brighter gate of the most exposed flat clipped; read back per pixel
    fw, s_fw = math.nan, math.nan
    last = flat_st[-1]
    if diff and last not in lin and len(lin) >= 2:
        ref = lin[-1]
        pl, pr_ = per[id(last)], per[id(ref)]
        ratio = last.integration_time_s / ref.integration_time_s
        mu_ext = (pr_["mu"] - dark_mu) * ratio           # the signal tap had it not clipped
        amp_ext = pr_["amp"] * ratio
        observed = pl["mu"] - dark_mu
        sd = math.sqrt(max(last.var_dn2, ref.var_dn2 * ratio ** 2) / next(
            c.frames.shape[0] for c in flats if c.label == last.label))
        clipped = observed < mu_ext - 5.0 * sd
        share = float(clipped.mean())
        if share >= 0.99:
            other = amp_ext / m - mu_ext + k * dark * last.integration_time_s  # the other gate's charge
            fw_dn = 2.0 * observed + other
            fw = float(fw_dn[clipped].mean()) / k
            s_stat = float(fw_dn[clipped].std(ddof=1) / math.sqrt(clipped.sum())) / k
            # the gain's uncertainty moves every pixel's estimate together
            s_fw = math.hypot(s_stat, fw * sk / k)
        else:
            notes.append(f"the most exposed flat clipped only {100 * share:.0f} % of the pixels: full well not reached")
    elif not diff:
        # single-ended: saturation capacity = the mean at the photon-transfer peak (EMVA 1288)
        pk = flat_st[peak]
        x_pk = pk.mean_dn - np.polyval(dpar, pk.integration_time_s)
        fw = x_pk / k
        s_fw = fw * sk / k
    else:
        notes.append("no flat capture beyond the linear range: full well not reached")

    if len(per_tap) > 1:
        kk = np.array([t["conversion_gain_dn_per_e"] for t in per_tap])
        ss = np.array([t["sigma"] for t in per_tap])
        mean_k = float(np.sum(kk / ss ** 2) / np.sum(1 / ss ** 2))
        chi2_taps = float(np.sum(((kk - mean_k) / ss) ** 2))
        from scipy.stats import chi2 as _chi2

        p_taps = float(_chi2.sf(chi2_taps, len(kk) - 1))
        if p_taps < 0.01:
            notes.append("the taps' conversion gains differ beyond noise ("
                         + ", ".join(f"tap {t['tap']}: {t['conversion_gain_dn_per_e']:.4g} +- {t['sigma']:.2g}"
                                     for t in per_tap) + f"; p = {p_taps:.1e}): a tap calibration is needed")
    fit = {"alpha": alpha, "beta": beta, "gamma": gamma, "cov": cov.tolist(), "reduced_chi2": red, "per_tap": per_tap,
           "linear_fit": lpar.tolist(), "signal_tap": sig, "differential": diff}
    dark_offset = np.mean([_pixel_stats(c.frames, range(k_taps))[0] for c in darks], axis=0)
    return PhotonTransfer(
        dark_offset_dn=dark_offset,
        readout="differential" if diff else "single-ended",
        conversion_gain_dn_per_e=Estimate(float(k), float(sk), "DN/e"),
        read_noise_e=Estimate(rn, s_rn, "e"),
        dark_current_e_per_s=Estimate(float(dark), float(s_dark), "e/s"),
        dsnu_e=Estimate(dsnu, s_dsnu, "e"),
        prnu=Estimate(prnu, s_prnu, ""),
        full_well_e=Estimate(fw, s_fw, "e"),
        linearity_error_pct=Estimate(le, s_le, "%"),
        modulation_contrast=m, captures=stats, fit=fit, notes=notes)


def predicted_variance(sensor: Any, amplitude_dn: np.ndarray, integration_time_s: np.ndarray, *,
                       differential: bool = True) -> np.ndarray:
    """The twin's photon-transfer curve: temporal variance (DN^2) of a tap from a sensor block
    (``tofhil.sim.sensor.SensorConfig``) for a flat field of modulation amplitude
    ``amplitude_dn`` (0: dark) at ``integration_time_s``, below saturation."""
    k = sensor.conversion_gain_dn_per_e
    m = sensor.modulation_contrast
    a = np.asarray(amplitude_dn, dtype=np.float64)
    t = np.asarray(integration_time_s, dtype=np.float64)
    dark_dn = k * sensor.dark_current_e_per_s * t
    if differential:
        return k * (a / m + dark_dn) / 2.0 + k ** 2 * sensor.read_noise_e ** 2 / 2.0 + QUANT_VAR_DN2
    return k * (a / m + dark_dn) + k ** 2 * sensor.read_noise_e ** 2 + QUANT_VAR_DN2
