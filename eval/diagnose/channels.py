"""The held-out residual resolved by channel: what a ToF calibration is organised by.

A camera's calibration (the vendors' and the literature's) is per tap (offset, gain), per
modulation frequency (phase, gain), per frame (drift), then optics over the field. A cause
has a signature in those channels, so the residual is read channel by channel before any
cause is named. Each reading is an estimate with its standard error from the held-out
noise; its size against noise is ``z = estimate / standard error`` (|z| > :data:`Z_SIGNIFICANT`
is a part of the residual the noise cannot make).

- **per frequency**: the complex ratio measured / predicted of each frequency, as a phase
  (rad, and the path length it means) and a gain; with two or more frequencies, whether
  their phases agree (a phase on one frequency alone is a calibration error, not a surface);
- **per tap** (raw taps, 4 or more): the taps' part that alternates with the tap index, which
  no change of the light can make (a pose, a range, a phase): tap gains and offsets can;
- **offset**: the unmodulated part (the taps' mean), where the session has it;
- **per frame**: each frame's phase and gain against the mean of all frames, and its trend;
- **noise**: the measured frame-to-frame scatter against what the read + shot noise model
  predicts at those signal levels (a disturbance that changes from frame to frame shows here,
  where a per-pixel mean would hide it).

The field (smooth, radial, rows and columns, edges) and the dependence on amplitude and
distance are :mod:`tofhil.eval.diagnose.structure`'s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from tofhil.demod import radians_per_metre, tap_pattern
from tofhil.eval.diagnose.heldout import HeldOutData
from tofhil.sim.effects import OFFSET_CHANNEL

#: |estimate / standard error| beyond which one reading alone is not noise (about 6e-7
#: two-sided); a table of readings uses :func:`family_z` instead, so that the table as a whole
#: fires by chance with the diagnosis's one false-alarm rate.
Z_SIGNIFICANT = 5.0


def family_z(n_readings: int) -> float:
    """The |z| beyond which a reading among ``n_readings`` is significant: the two-sided
    Bonferroni threshold at which any of them fires by chance with probability
    :data:`tofhil.eval.diagnose.verdict.ALPHA` (1e-3 over 12 readings: z = 3.93; over 20: 4.06),
    computed for at least :data:`FAMILY_MIN_READINGS` readings so that a short table (a few
    readings of one prediction) is not judged more loosely than a whole one."""
    from scipy import stats

    from tofhil.eval.diagnose.verdict import ALPHA

    return float(stats.norm.isf(ALPHA / (2.0 * max(n_readings, FAMILY_MIN_READINGS))))


#: The smallest family a threshold is computed for (see :func:`family_z`).
FAMILY_MIN_READINGS = 12


@dataclass
class ChannelReading:
    """One channel's part of the residual: an estimate with its standard error."""

    channel: str          #: "frequency", "tap", "offset", "frame", "noise"
    name: str             #: e.g. "44 MHz phase", "tap 1 gain", "frame trend"
    value: float
    se: float
    unit: str
    text: str = ""
    #: The |z| it must exceed (set by the table it belongs to: :func:`family_z`).
    z_threshold: float = Z_SIGNIFICANT

    @property
    def z(self) -> float:
        return self.value / self.se if self.se > 0 else (0.0 if self.value == 0 else math.inf)

    @property
    def significant(self) -> bool:
        return abs(self.z) > self.z_threshold

    def to_json(self) -> dict[str, Any]:
        z = self.z
        return {"channel": self.channel, "name": self.name, "value": self.value, "se": self.se, "unit": self.unit,
                "z": z if math.isfinite(z) else None, "significant": self.significant, "text": self.text}


@dataclass
class ChannelTable:
    readings: list[ChannelReading] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    def by_channel(self, channel: str) -> list[ChannelReading]:
        return [r for r in self.readings if r.channel == channel]

    def significant_channels(self) -> list[str]:
        """The channels with a part of the residual beyond noise, in table order."""
        seen: list[str] = []
        for r in self.readings:
            if r.significant and r.channel not in seen:
                seen.append(r.channel)
        return seen

    def to_json(self) -> dict[str, Any]:
        return {"readings": [r.to_json() for r in self.readings], "significant": self.significant_channels(),
                "notes": list(self.notes), "z_significant": family_z(len(self.readings))}

    def set_family(self) -> "ChannelTable":
        """Every reading judged at the table's family threshold (:func:`family_z`)."""
        z = family_z(len(self.readings))
        for r in self.readings:
            r.z_threshold = z
        return self


def _ratio_fit(meas: np.ndarray, pred: np.ndarray, var: np.ndarray) -> tuple[complex, float]:
    """The complex factor ``q`` with ``meas ~ q pred`` (weighted least squares over pixels,
    each complex residual of variance ``2 var``), and the standard error of each of its real
    and imaginary parts."""
    w = 1.0 / np.maximum(var, 1e-300)
    den = float(np.sum(w * np.abs(pred) ** 2))
    if den <= 0:
        return complex(1.0), math.inf
    q = complex(np.sum(w * meas * np.conj(pred)) / den)
    return q, math.sqrt(1.0 / den)


def frequency_readings(data: HeldOutData, prediction: np.ndarray) -> list[ChannelReading]:
    """Phase and gain of each frequency's held-out signal against the prediction."""
    out = []
    m = data.test_pixels
    phases = []
    for f in range(data.n_freq):
        q, se = _ratio_fit(data.s_test[f][m], prediction[f][m], data.var_test[f][m])
        a = abs(q)
        phase = math.atan2(q.imag, q.real)
        se_phase = se / max(a, 1e-30)
        label = f"{data.freq_hz[f] / 1e6:g} MHz"
        path_mm = 1e3 * phase / float(radians_per_metre(data.freq_hz[f]))
        out.append(ChannelReading("frequency", f"{label} phase", phase, se_phase, "rad",
                                  f"{label}: phase {phase:+.4f} rad ({path_mm:+.2f} mm of range) against the twin"))
        out.append(ChannelReading("frequency", f"{label} gain", a - 1.0, se, "",
                                  f"{label}: signal {100 * (a - 1):+.2f} % of the twin's"))
        phases.append((phase, se_phase, path_mm))
    if len(phases) >= 2:
        # One range error moves every frequency's phase in proportion to it; a phase that
        # does not follow is a per-frequency calibration error (or a harmonic of one).
        k = np.array([float(radians_per_metre(f)) for f in data.freq_hz])
        ph = np.array([p for p, _, _ in phases])
        se = np.array([s for _, s, _ in phases])
        w = 1.0 / se ** 2
        d_common = float(np.sum(w * k * ph) / np.sum(w * k * k))
        resid = ph - k * d_common
        worst = int(np.argmax(np.abs(resid) / se))
        out.append(ChannelReading("frequency", "phase inconsistency", float(resid[worst]), float(se[worst]), "rad",
                                  f"the phases of the {len(phases)} frequencies do not follow one range offset "
                                  f"({1e3 * d_common:+.2f} mm): {data.freq_hz[worst] / 1e6:g} MHz is off by "
                                  f"{resid[worst]:+.4f} rad"))
    return out


def offset_readings(data: HeldOutData, prediction: np.ndarray) -> list[ChannelReading]:
    if not data.offset_channel:
        return []
    m = data.test_pixels
    c = data.n_freq
    r = (data.s_test[c].real - prediction[c].real)[m]
    var = data.var_test[c].real[m]
    level = float(np.mean(np.abs(prediction[c].real[m]))) or 1.0
    mean = float(np.mean(r))
    se = float(math.sqrt(np.sum(var)) / max(r.size, 1))
    return [ChannelReading(OFFSET_CHANNEL, OFFSET_CHANNEL, mean / level, se / level, "",
                           f"unmodulated offset {mean:+.3g} DN ({100 * mean / level:+.2f} % of the twin's)")]


def frame_readings(data: HeldOutData) -> list[ChannelReading]:
    """Each frame's phase and gain against the mean of all frames (what changes over time)."""
    if data.s_frames is None or data.s_frames.shape[0] < 3:
        return []
    frames = data.s_frames[:, :data.n_freq]
    n = frames.shape[0]
    m = data.usable
    mean = frames.mean(axis=0)
    var1 = data.var_frame[:data.n_freq]
    f = int(np.argmax(data.freq_hz))  # the finest range resolution
    k = float(radians_per_metre(data.freq_hz[f]))
    ranges, gains, ses = [], [], []
    for i in range(n):
        q, se = _ratio_fit(frames[i, f][m], mean[f][m], var1[f][m])
        ranges.append(math.atan2(q.imag, q.real) / k)
        gains.append(abs(q) - 1.0)
        ses.append(se)
    t = np.arange(n) - (n - 1) / 2.0
    se_r = float(np.median(ses)) / k
    slope = float(np.sum(t * np.asarray(ranges)) / np.sum(t * t))
    se_slope = se_r / math.sqrt(float(np.sum(t * t)))
    g_slope = float(np.sum(t * np.asarray(gains)) / np.sum(t * t))
    se_g = float(np.median(ses)) / math.sqrt(float(np.sum(t * t)))
    spread = 1e3 * float(np.ptp(ranges))
    return [ChannelReading("frame", "range trend", slope, se_slope, "m/frame",
                           f"per frame: the range moves {1e3 * slope:+.3f} mm per frame ({spread:.2f} mm first to last "
                           f"extreme over {n} frames)"),
            ChannelReading("frame", "signal trend", g_slope, se_g, "1/frame",
                           f"per frame: the modulated light changes {100 * g_slope:+.3f} % per frame")]


def noise_readings(data: HeldOutData, model_variance: np.ndarray | None) -> list[ChannelReading]:
    """The measured frame-to-frame scatter of S against the sensor noise model's prediction."""
    if model_variance is None:
        return []
    m = data.usable
    measured = data.var_frame[:data.n_freq][:, m]
    predicted = np.asarray(model_variance)[:, m]
    ratio = float(np.median(measured / np.maximum(predicted, 1e-300)))
    # the median of a variance ratio from N - 1 degrees of freedom, pooled over 25 pixels
    dof = max((data.n_train_frames + data.n_test_frames - 1) * 25, 1)
    se = math.sqrt(2.0 / dof)
    return [ChannelReading("noise", "scatter / noise model", ratio - 1.0, se, "",
                           f"the frame-to-frame scatter is {ratio:.2f} x the sensor noise model's at these signal levels")]


def tap_readings(theta_rad: np.ndarray, measured: np.ndarray, predicted: np.ndarray, pixels: np.ndarray,
                 noise_var: np.ndarray, *, with_offset: bool = True) -> list[ChannelReading]:
    """The part of the residual that follows the tap index: the taps' alternating part
    (:func:`tap_pattern`), measured minus predicted, as a constant (a tap offset pattern) and
    in proportion to the pixel's offset level (a tap gain pattern, where the readout has an
    offset of its own). ``noise_var``: a tap's variance of the mean ``[H, W]``."""
    k = measured.shape[1]
    if k < 4 or k % 2:
        return []
    d = (tap_pattern(measured) - tap_pattern(predicted))[:, pixels].ravel()
    level = np.broadcast_to(measured.mean(axis=1)[:, pixels], (measured.shape[0], int(pixels.sum()))).ravel()
    var = np.broadcast_to(noise_var[pixels] / k, (measured.shape[0], int(pixels.sum()))).ravel()
    w = 1.0 / np.maximum(var, 1e-300)
    mean_level = float(np.mean(np.abs(level))) or 1.0
    out = []
    if with_offset and float(np.std(level)) > 1e-6 * mean_level:
        # d = o + g * level: a tap offset pattern o and a tap gain pattern g (weighted least squares)
        sw, sx, sy = w.sum(), (w * level).sum(), (w * d).sum()
        sxx, sxy = (w * level * level).sum(), (w * level * d).sum()
        det = sw * sxx - sx * sx
        if det > 0:
            g = (sw * sxy - sx * sy) / det
            o = (sxx * sy - sx * sxy) / det
            out.append(ChannelReading("tap", "tap gain pattern", float(g), float(math.sqrt(sw / det)), "",
                                      f"per tap: the odd taps' gain {-200 * g:+.3f} % against the even taps' (the "
                                      "alternating part grows with the offset level)"))
            out.append(ChannelReading("tap", "tap offset pattern", float(o) / mean_level,
                                      float(math.sqrt(sxx / det)) / mean_level, "",
                                      f"per tap: the odd taps' offset {-2 * o:+.3g} DN against the even taps'"))
            return out
    o = float(np.sum(w * d) / np.sum(w))
    out.append(ChannelReading("tap", "tap pattern", o / mean_level, float(math.sqrt(1.0 / np.sum(w))) / mean_level, "",
                              f"per tap: the odd taps read {-2 * o:+.3g} DN against the even taps"))
    return out


def prediction_readings(data: HeldOutData, prediction: np.ndarray) -> dict[str, ChannelReading]:
    """The readings that depend on the prediction and need no taps (each frequency's phase and
    gain, their agreement, the offset), by name."""
    readings = frequency_readings(data, prediction) + offset_readings(data, prediction)
    z = family_z(len(readings))
    for r in readings:
        r.z_threshold = z
    return {r.name: r for r in readings}


def sensor_noise_variance(data: HeldOutData) -> np.ndarray | None:
    """The noise variance of one frame's S per real component ``[F, H, W]`` that the session's
    recorded sensor predicts (read noise and shot noise at the measured tap levels, plus the
    ADC's quantisation); None without a recorded sensor or raw taps."""
    cfg = data.sensor_config
    if not cfg or data.taps_test is None:
        return None
    try:
        g = float(cfg["conversion_gain_dn_per_e"])
        read_dn = float(cfg["read_noise_e"]) * g
        black = float(cfg.get("black_level_dn", 0.0))
    except (KeyError, TypeError, ValueError):
        return None
    k = data.taps_test.shape[1]
    var_tap = g * np.maximum(data.taps_test - black, 0.0) + read_dn ** 2 + 1.0 / 12.0   # [F, K, H, W]
    # a binned pixel is the mean of bin_px^2 pixels with independent noise
    return (2.0 / k ** 2) * var_tap.sum(axis=1) / data.bin_px ** 2


def residual_by_channel(data: HeldOutData, prediction: np.ndarray, *, taps_measured: np.ndarray | None = None,
                        taps_predicted: np.ndarray | None = None,
                        model_variance: np.ndarray | None = None) -> ChannelTable:
    """The table of the held-out residual ``measured - prediction`` by channel."""
    table = ChannelTable()
    table.readings += frequency_readings(data, prediction)
    if taps_measured is not None and taps_predicted is not None:
        k = taps_measured.shape[1]
        # a tap's noise variance of the mean from S's: var(S) per real part = 2 sigma^2 / K
        tap_var = data.var_test[:data.n_freq].real.mean(axis=0) * k / 2.0
        table.readings += tap_readings(data.theta_rad, taps_measured, taps_predicted, data.test_pixels, tap_var,
                                       with_offset=data.offset_channel)
        if not data.offset_channel:
            table.notes.append("per tap: the readout reports no offset of its own (or it does not vary): tap gains "
                               "only, read on the taps' modulated part")
    else:
        table.notes.append("per tap: the session has no raw taps (depth + amplitude): the tap channel cannot be read")
    table.readings += offset_readings(data, prediction)
    table.readings += frame_readings(data)
    if data.s_frames is None or data.s_frames.shape[0] < 3:
        table.notes.append("per frame: fewer than 3 frames: what changes over time cannot be told from noise")
    table.readings += noise_readings(data, model_variance)
    if model_variance is None:
        table.notes.append("noise: no sensor noise model recorded with the session: the frame-to-frame scatter is "
                           "taken as the noise (a disturbance that changes between frames would read as noise)")
    return table.set_family()
