"""Averaging frames in the complex domain: the one mean of a raw session, and its noise.

Depth is a non-linear function of the signal (the phase of ``S``). Averaging depth frames
averages the noise *after* that non-linearity: on a dim pixel the phase of a noisy ``S``
is biased and wraps, and the mean depth keeps that error however many frames are taken.
Averaging the taps first -- equivalently the phasors, the estimator is linear in the taps --
and demodulating the mean leaves noise that shrinks as ``1 / sqrt(N)``. Every command that
averages frames of a raw session goes through :func:`mean_signal` (``compare --frames N``,
``correct --average``, the PSF calibration's captures, ``calibrate-taps``).

Order of the operations, per frame then over frames: the tap calibration (affine in the
taps, the same for every frame, so it commutes with the mean), the phasor, the mean. A
complex-domain correction is then applied to the mean. The complex corrections (uniform,
inverse filter, PSF deconvolution) are linear operators ``L`` on ``S``, so
``L(mean S_i) = mean L(S_i)``: correcting every frame and averaging gives the same signal,
N times slower. Correcting the mean is the right order for anything that is not exactly
linear too (the deconvolution's early stop is judged on the signal, not on one frame's
noise). The noise of the corrected mean is ``L`` applied to the frames' deviations from
the mean (:func:`mean_signal` with ``correct`` does this in batches).

Noise floor: the per-frame scatter of ``S`` perpendicular to the mean phasor gives the
phase noise of the mean, ``sigma_phi = sqrt(var_perp / N) / |S|`` (first order), and
through :func:`tofhil.demod.phase_to_distance` the distance noise; several frequencies
combine with the unwrapping's own weights ``(f A)^2`` (:mod:`tofhil.unwrap`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from itertools import chain
from typing import Any, Callable, Iterable

import numpy as np

from tofhil.demod import TapLimits, bad_tap_pixels, offset, phase_to_distance, phasor, taps_from_signal
from tofhil.frames import RawFrame

#: Frames corrected together when propagating the noise through a correction.
BATCH = 8


@dataclass
class MeanSignal:
    """The mean complex signal of ``n`` frames and the scatter of the frames around it."""

    s: np.ndarray            # [F, H, W] mean signal (tap-calibrated, corrected)
    offset_b: np.ndarray     # [F, H, W] mean offset B
    var_perp: np.ndarray     # [F, H, W] per-frame variance of S across the mean phasor's direction
    n: int
    template: RawFrame       # the first frame: camera, frequencies, tap phases, meta
    #: [H, W] pixels with a saturated or non-finite tap in any frame (the frames' declared
    #: limits, :func:`tofhil.demod.bad_tap_pixels`): the mean of clipped taps is no signal.
    bad: np.ndarray | None = None
    #: degrees of freedom of ``var_perp`` (None: ``n - 1``; more when other frames of the
    #: session joined the scatter, :func:`mean_signal`'s ``others``)
    dof: int | None = None

    def raw(self) -> RawFrame:
        """The mean as a raw frame (taps re-synthesised from ``s`` and ``B``), for
        :func:`tofhil.depth.depth_from_raw`. Pixels that clipped in a frame get non-finite
        taps (invalid by the one bad-tap rule); the declared saturation levels are not passed
        on, since re-synthesised taps of a pixel that came close to them can overshoot them
        without any tap having clipped."""
        t = self.template
        taps = taps_from_signal(np.abs(self.s), np.angle(self.s), self.offset_b, t.theta_rad)
        if self.bad is not None:
            taps[..., self.bad] = np.nan
        meta = {k: v for k, v in t.meta.items() if k not in ("saturation_dn", "saturation_low_dn")}
        return replace(t, taps=taps, meta=dict(meta, frames_averaged=self.n))

    def phase_noise_rad(self) -> np.ndarray:
        """``[F, H, W]`` standard deviation of the mean's phase (NaN where ``S = 0``)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.sqrt(self.var_perp / self.n) / np.abs(self.s)

    def distance_noise_m(self) -> np.ndarray:
        """``[H, W]`` standard deviation of the mean's radial distance, from the frames'
        scatter: per frequency ``phase_to_distance(sigma_phi, f)``, several frequencies
        combined with the unwrapping's weights ``w_f = (f A_f)^2``:
        ``sigma^2 = sum w_f^2 sigma_f^2 / (sum w_f)^2``. NaN without a scatter (one frame)."""
        if (self.n - 1 if self.dof is None else self.dof) < 1:
            return np.full(self.s.shape[-2:], np.nan)
        freq = self.template.freq_hz[:, None, None]
        sig = phase_to_distance(self.phase_noise_rad(), freq)
        if sig.shape[0] == 1:
            return sig[0]
        w = (freq * np.abs(self.s)) ** 2
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.sqrt((w * w * sig * sig).sum(axis=0)) / w.sum(axis=0)


def frame_signal(raw: RawFrame, flat: Any = None) -> tuple[np.ndarray, np.ndarray]:
    """One frame's ``(S, B)`` after the tap calibration ``flat`` (a TapCalibration or None)."""
    taps = raw.taps.astype(np.float64)
    if flat is not None:
        taps = flat.apply(taps)
    return phasor(taps, raw.theta_rad), offset(taps)


def mean_signal(frame: Callable[[int], RawFrame], n: int, *, flat: Any = None,
                correct: Callable[[np.ndarray], np.ndarray] | None = None, scatter: bool = True,
                progress: Callable[[Any, int, str], Any] | None = None,
                others: tuple[Callable[[int], RawFrame], int] | None = None) -> MeanSignal:
    """Average ``n`` raw frames (``frame(i)``) in the complex domain, then apply ``correct``
    (``S[..., H, W] -> S``, a complex-domain correction) to the mean.

    With ``scatter`` the frames are read twice: the second pass gives the scatter of
    ``correct(S_i - mean)`` across the mean's phase (for linear corrections, the scatter of
    the corrected frames), in batches of :data:`BATCH` frames. ``others`` = ``(frame, m)``:
    ``m`` more frames of the same session (held out from this mean: a fit's frames) whose
    scatter about their own mean joins the per-frame noise estimate (pooled, ``n + m - 2``
    degrees of freedom): the noise is the sensor's, whichever frames are averaged, and a
    mean of one scored frame gets a noise floor.
    """
    if n < 1:
        raise ValueError("need at least one frame")
    wrap = progress or (lambda it, k, desc: it)
    first = frame(0)
    limits = TapLimits.from_meta(first.meta)
    bad = np.zeros(first.taps.shape[-2:], bool)

    def checked(frames: Iterable[RawFrame]) -> Iterable[RawFrame]:
        for f in frames:
            bad[...] |= bad_tap_pixels(f.taps, limits)
            yield f

    # The tap calibration is affine and the phasor linear: both commute with the mean.
    taps = mean_taps_of(checked(chain([first], (frame(i) for i in wrap(range(1, n), n, "averaging frames")))))
    mean, mean_b = frame_signal(replace(first, taps=taps), flat)
    s_out = mean if correct is None else np.asarray(correct(mean))
    var = np.zeros(mean.shape)
    groups = [(frame, n, mean)]
    if scatter and others is not None and others[1] > 1:
        o_frame, m = others
        o_mean = frame_signal(replace(first, taps=mean_taps_of(o_frame(i) for i in range(m))), flat)[0]
        groups.append((o_frame, m, o_mean))
    dof = sum(k - 1 for _, k, _ in groups)
    if scatter and dof > 0:
        # Across the (corrected) mean phasor: the component that moves the phase.
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.where(np.abs(s_out) > 0, np.conj(s_out) / np.abs(s_out), 0)
        for get, k, centre in groups:
            for i0 in range(0, k, BATCH):
                dev = np.stack([frame_signal(get(i), flat)[0] - centre for i in range(i0, min(k, i0 + BATCH))])
                if correct is not None:
                    dev = np.asarray(correct(dev))
                var += ((dev * u).imag ** 2).sum(axis=0)
        var /= dof
    return MeanSignal(s_out, mean_b, var, n, first, bad, dof if scatter else None)


def session_mean_signal(session: Any, n: int | None = None, **kwargs: Any) -> MeanSignal:
    """:func:`mean_signal` of the first ``n`` frames (default all) of an open raw session."""
    k = session.n_frames if n is None else min(n, session.n_frames)
    return mean_signal(session.raw_frame, k, **kwargs)


def mean_taps_of(frames: Iterable[RawFrame]) -> np.ndarray:
    """Mean raw taps ``[F, K, H, W]`` of frames (float64), e.g. a calibration capture."""
    acc, k = None, 0
    for raw in frames:
        acc = raw.taps.astype(np.float64) if acc is None else acc + raw.taps
        k += 1
    if acc is None:
        raise ValueError("no frames")
    return acc / k
