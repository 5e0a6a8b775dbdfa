"""Measured complex signal split into training and held-out data, with its noise.

Diagnosis fits on one part of a session and scores on another. The data are channels of
complex images ``[C, H, W]``: the signal ``S`` of each modulation frequency, and (when the
device reports a physical tap offset) the offset ``B`` as a last, real-valued channel: the
only place unmodulated light such as ambient shows. The split is two-fold:
frames (even frames train, odd frames test: independent noise) and pixels (a checkerboard
of square blocks: a fit cannot memorise the pixels it is scored on). Both parts are
averaged over their frames; the noise of each average comes from the frame-to-frame
scatter of the session itself, pooled over a small neighbourhood so that a handful of
frames is enough.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from tofhil.binning import bin_factor, bin_mean, binned_camera, one_object
from tofhil.eval.diagnose.defects import binned_defects, raw_defects
from tofhil.eval.metrics.noise import pooled_variance
from tofhil.camera import CameraModel
from tofhil.demod import TapLimits, bad_extremes, clip_limits, phasor, wrapped_phase
from tofhil.errors import TofhilError
from tofhil.session import Session
from tofhil.unwrap import frequency_plan, unwrap


@dataclass
class HeldOutData:
    """Mean complex signal of the training and the held-out frames, and their variances."""

    camera: CameraModel
    freq_hz: np.ndarray
    theta_rad: np.ndarray
    integration_time_s: float
    s_train: np.ndarray  # complex [C, H, W]: mean over training frames (C = F, or F + 1 with the offset)
    s_test: np.ndarray  # complex [C, H, W]: mean over held-out frames
    var_train: np.ndarray  # float [C, H, W]: noise variance of s_train per real component
    var_test: np.ndarray
    usable: np.ndarray  # bool [H, W]: pixels with signal and no saturation
    train_pixels: np.ndarray  # bool [H, W]: usable pixels of the training blocks
    test_pixels: np.ndarray  # bool [H, W]: usable pixels of the held-out blocks
    n_train_frames: int
    n_test_frames: int
    offset_channel: bool = False
    #: The session's recorded sensor configuration (twin sessions), None for a device capture.
    sensor_config: dict | None = None
    source: str = "<session>"
    #: The clip levels applied to the measured taps; a prediction reaching them would have clipped too.
    tap_limits: TapLimits = field(default_factory=TapLimits)
    #: What the channels are made of and where the noise comes from (stated in the report).
    channels: str = "raw taps: the complex signal S per frequency"
    noise: str = "frame-to-frame scatter of S (pooled over 5 x 5 pixels)"
    #: Depth sessions: the noise differs along the measured phasor (amplitude) and across it
    #: (phase, i.e. depth). ``phase_ref`` is the measured unit phasor [C, H, W] and
    #: ``radial_var_scale`` the radial variance over the tangential one (``var_*``); None:
    #: isotropic noise (raw taps).
    phase_ref: np.ndarray | None = None
    radial_var_scale: np.ndarray | None = None
    #: Depth sessions from a scene built from the capture: how well the scene knows the
    #: amplitude at all (relative: one reflectance per object leaves this scatter of the log
    #: amplitude). The amplitude residual is then the log ratio measured / predicted over
    #: ``sqrt(instrument^2 + error^2)`` (:meth:`whitened`); None: no such error.
    amplitude_model_error: float | None = None
    #: False when the training and the held-out data are the same frame (a one-frame depth
    #: session): then nothing fitted per pixel can be scored.
    frames_held_out: bool = True
    #: Every frame's signal ``[N, C, H, W]`` (even frames train, odd frames test), for forms
    #: that change from frame to frame (drift); None when not kept.
    s_frames: np.ndarray | None = field(default=None, repr=False)
    #: The defective pixels found before any fit (:mod:`tofhil.eval.diagnose.defects`): not
    #: in ``usable``, so neither fitted nor scored; None when not searched.
    defects: Any = None
    #: Raw sessions: the measured taps ``[F, K, H, W]`` (DN) averaged over the held-out frames,
    #: for the residual per tap (:mod:`tofhil.eval.diagnose.channels`).
    taps_test: np.ndarray | None = field(default=None, repr=False)
    #: The pixels each frame set is compared on, chosen on the *other* frame set's amplitude
    #: (raw sessions): a pixel kept because its own noise lifted it over the amplitude
    #: threshold has a residual biased outward, along its signal (0.5 sigma at 3-5 sigma of
    #: signal), which a gain or a tap calibration then "explains". None: ``usable`` for both.
    usable_train_frames: np.ndarray | None = field(default=None, repr=False)
    usable_test_frames: np.ndarray | None = field(default=None, repr=False)
    #: The training frames on the held-out blocks (chosen on the held-out frames); None: ``test_pixels``.
    tune_pixels: np.ndarray | None = field(default=None, repr=False)
    #: Raw taps: the data are the means of ``bin_px x bin_px`` blocks of the sensor's pixels
    #: (:mod:`tofhil.binning`), and the twin is binned alike (samples, fixed pattern, its own
    #: sampling variance). ``camera`` is the binned camera, ``sensor_shape`` the sensor's.
    bin_px: int = 1
    sensor_shape: tuple[int, int] | None = None
    _fit_pixels: np.ndarray | None = field(default=None, repr=False, compare=False)
    _screen_pixels: np.ndarray | None = field(default=None, repr=False, compare=False)
    #: Per part, the measured side of its whitened residual (a fit evaluates it thousands of
    #: times): (s, var, mask) as given, the flat pixel indices, s and sigma there.
    _gathered: dict = field(default_factory=dict, repr=False, compare=False)

    @property
    def binned_by(self) -> int:
        """How many sensor pixels a pixel of the data spans along each axis (raw taps binned
        by ``bin_px``, a depth session by its own binning; 1: the sensor's pixels)."""
        if self.sensor_shape is None:
            return self.bin_px
        return max(self.bin_px, self.sensor_shape[1] // self.camera.width)

    @property
    def var_frame(self) -> np.ndarray:
        """Noise variance of one frame per real component ``[C, H, W]``."""
        return self.var_train * self.n_train_frames

    @property
    def differential_taps(self) -> bool:
        """The device's taps are signed differences (its ADC clips below zero, as the TOFcam635's
        DCS about their mid-scale): no common-mode offset is in them."""
        return self.tap_limits.low_dn is not None and self.tap_limits.low_dn < 0

    @property
    def n_freq(self) -> int:
        return int(self.freq_hz.size)

    @property
    def values_per_pixel(self) -> int:
        """Real values a pixel holds: 2 per frequency's S, 1 for the offset."""
        return 2 * self.n_freq + (1 if self.offset_channel else 0)

    @property
    def unambiguous_range_m(self) -> float:
        return frequency_plan(self.freq_hz).unambiguous_range_m

    def chi2(self, prediction: np.ndarray, part: str = "test") -> float:
        """Robust misfit: sum over one part's pixels and channels of Huber's rho of each
        whitened residual component (``r^2`` up to ``HUBER_SIGMA``, linear beyond).

        About one per real value when the model is right. The linear tail keeps a few pixels
        that a finite number of render samples places on the wrong side of a bright edge from
        outweighing the whole image.
        """
        r = self.whitened(prediction, part)
        return float(huber(r.real).sum() + huber(r.imag).sum())

    @property
    def fit_pixels(self) -> np.ndarray:
        """The training pixels a fit evaluates: all of them up to :attr:`max_fit_pixels`,
        else every n-th in raster order (evenly spread over the image, the same set every
        evaluation). A few parameters are fitted; tens of thousands of pixels pin them down
        as well as a whole camera's worth, at a fraction of the cost per evaluation."""
        if self._fit_pixels is None:
            self._fit_pixels = subsample(self.train_pixels, self.max_fit_pixels)
        return self._fit_pixels

    @property
    def max_fit_pixels(self) -> int:
        """:data:`MAX_FIT_PIXELS` sensor pixels: a bin holds ``bin_px^2`` of them, with as much
        information (its noise is ``bin_px`` times lower) and as many render samples."""
        return max(MAX_FIT_PIXELS // self.bin_px ** 2, 256)

    @property
    def screen_pixels(self) -> np.ndarray:
        """The held-out pixels a signature's test reads (:mod:`tofhil.eval.diagnose.signature`):
        all of them up to :attr:`max_fit_pixels`, else every n-th in raster order."""
        if self._screen_pixels is None:
            self._screen_pixels = subsample(self.test_pixels, self.max_fit_pixels)
        return self._screen_pixels

    def whitened(self, prediction: np.ndarray, part: str = "test") -> np.ndarray:
        """Complex (measured - predicted) / sigma ``[C, N]`` over a part's pixels ("test",
        "train", or "fit": :attr:`fit_pixels`); for depth
        sessions the real part is the amplitude residual along the measured phasor, the
        imaginary the phase residual times the measured amplitude, each over its own noise."""
        s, var, mask = self.part(part)
        if self.phase_ref is None or self.radial_var_scale is None:
            idx, s_at, sigma_at = self._measured_at(part, s, var, mask)
            return (s_at - prediction.reshape(prediction.shape[0], -1)[:, idx]) / sigma_at
        # Polar residuals: along the measured phasor, the amplitude difference; across it, the
        # phase difference times the *measured* amplitude (the depth residual in the units of
        # S). Scaling the prediction's amplitude down must not make a depth misfit cheaper.
        u = self.phase_ref[:, mask]
        p = prediction[:, mask]
        a_meas = np.abs(s[:, mask])
        across = a_meas * ((p / np.maximum(np.abs(p), 1e-30)) * np.conj(u)).imag
        v = var[:, mask]
        if self.amplitude_model_error:
            # A multiplicative model error (texture the scene's one reflectance per object
            # cannot follow) is symmetric in the log amplitude: a difference over an error
            # relative to the *measured* amplitude weighs the pixels the twin over-predicts
            # most and pulls every fitted level low (a reflectance x0.55 on the ADI office).
            # For small residuals this is the instrument's difference over its own noise.
            a_pred = np.maximum((p * np.conj(u)).real, 1e-3 * a_meas)
            rel2 = v * self.radial_var_scale[:, mask] / np.maximum(a_meas, 1e-30) ** 2 + self.amplitude_model_error ** 2
            return np.log(np.maximum(a_meas, 1e-30) / a_pred) / np.sqrt(rel2) + 1j * (across / np.sqrt(v))
        radial = a_meas - (p * np.conj(u)).real
        return radial / np.sqrt(v * self.radial_var_scale[:, mask]) + 1j * (across / np.sqrt(v))

    def _measured_at(self, part: str, s: np.ndarray, var: np.ndarray,
                     mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """A part's pixels as flat indices, its measured signal and noise sigma there (kept
        while the part's arrays are the same objects)."""
        kept = self._gathered.get(part)
        if kept is None or kept[0] is not s or kept[1] is not var or kept[2] is not mask:
            idx = np.flatnonzero(mask.ravel())
            c = s.shape[0]
            kept = (s, var, mask, idx, s.reshape(c, -1)[:, idx], np.sqrt(var.reshape(c, -1)[:, idx]))
            self._gathered[part] = kept
        return kept[3], kept[4], kept[5]

    def part(self, part: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(mean signal, variance, pixels) of a part: ``test`` / ``train`` (the held-out or
        training frames on their own pixel blocks), ``fit`` (the training part's
        :attr:`fit_pixels`), ``screen`` (the held-out part's :attr:`screen_pixels`), ``test_frames`` / ``train_frames`` (those frames on every usable
        pixel: for forms fitted per pixel, scored on other frames) or ``tune`` (the training
        frames on the held-out blocks: where a prior's strength is chosen, the held-out frames
        unseen)."""
        if part == "fit":
            return self.s_train, self.var_train, self.fit_pixels
        if part == "screen":
            return self.s_test, self.var_test, self.screen_pixels
        if part == "tune":
            return self.s_train, self.var_train, self.test_pixels if self.tune_pixels is None else self.tune_pixels
        if part == "test":
            return self.s_test, self.var_test, self.test_pixels
        if part == "test_frames":
            return self.s_test, self.var_test, self.usable if self.usable_test_frames is None else self.usable_test_frames
        if part == "train":
            return self.s_train, self.var_train, self.train_pixels
        if part == "train_frames":
            return self.s_train, self.var_train, self.usable if self.usable_train_frames is None else self.usable_train_frames
        raise ValueError(f"unknown part {part!r}")

    def n_values(self, part: str = "test") -> int:
        """Real-valued data points in one part (2 per complex signal value, 1 per offset)."""
        mask = self.part(part)[2]
        return int(mask.sum() * self.values_per_pixel)

    def whitened_residual(self, prediction: np.ndarray, part: str = "train") -> np.ndarray:
        """Real vector of (measured - predicted) / sigma over a part: what least squares minimises."""
        r = self.whitened(prediction, part)
        return np.concatenate([r.real.ravel(), r.imag.ravel()])


def predict_fit(model: Any, data: HeldOutData, values: Any) -> np.ndarray:
    """A prediction that is read only on the fit pixels (:attr:`HeldOutData.fit_pixels`):
    a model that can (``predicts_pixels``) predicts only them, exact there (the rest of
    its frame is then not the model's)."""
    if getattr(model, "predicts_pixels", False):
        return model.predict(values, pixels=data.fit_pixels)
    return model.predict(values)


def depth_from_signal(s: np.ndarray, freq_hz: np.ndarray) -> np.ndarray:
    """Radial distance from the complex signal of each frequency ``[F, H, W]``."""
    return unwrap(wrapped_phase(s), freq_hz, amplitude=np.abs(s)).distance_m


#: Most training pixels a fit evaluates (:attr:`HeldOutData.fit_pixels`); a 160 x 120 camera
#: (9600 training pixels) is fitted on all of them.
MAX_FIT_PIXELS = 16384


def subsample(mask: np.ndarray, most: int) -> np.ndarray:
    """``mask`` thinned to at most ``most`` pixels: every n-th true pixel in raster order."""
    idx = np.flatnonzero(mask)
    if len(idx) <= most:
        return mask
    out = np.zeros(mask.size, bool)
    out[idx[::-(-len(idx) // most)]] = True
    return out.reshape(mask.shape)


#: Whitened residual (noise standard deviations) beyond which the misfit grows linearly.
HUBER_SIGMA = 5.0


def huber(r: np.ndarray, c: float = HUBER_SIGMA) -> np.ndarray:
    """Huber's rho: ``r^2`` for ``|r| <= c``, ``2 c |r| - c^2`` beyond."""
    a = np.abs(r)
    return np.where(a <= c, a * a, 2.0 * c * a - c * c)


def block_checkerboard(shape: tuple[int, int], block: int) -> np.ndarray:
    """True on the 'training' squares of a checkerboard of ``block`` x ``block`` pixels."""
    v, u = np.mgrid[0:shape[0], 0:shape[1]]
    return ((v // block + u // block) % 2) == 0


def frame_deviations(s: np.ndarray, mean: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """Each frame's deviation from the pixels' mean with the frame's common mode taken out: per
    frame and channel, the one complex factor (a gain and a phase: the emitter's power, a range
    offset) that brings the mean closest to the frame over ``pixels``. A change common to every
    pixel of a frame (a warm-up, a flicker) is not a pixel's noise: left in the scatter it would
    inflate the noise of every pixel and hide itself and every smaller effect; taken out, it
    stays in the frames for the drift form to find. Costs two of each frame's thousands of
    degrees of freedom (no visible bias)."""
    if s.shape[0] < 3 or not pixels.any():
        return s - mean[None]
    m = mean[:, pixels]                                         # [C, P]
    denom = np.sum(np.abs(m) ** 2, axis=1)                      # [C]
    g = np.einsum("cp,ncp->nc", np.conj(m), s[:, :, pixels]) / np.where(denom > 0, denom, 1.0)
    g = np.where(denom[None] > 0, g, 1.0)
    # the factors average to one (the mean stays the mean)
    g = g / g.mean(axis=0, keepdims=True)
    return s - g[:, :, None, None] * mean[None]


#: Pixels of raw taps a diagnosis renders at most: larger images are binned to this. A
#: 160 x 120 or 176 x 132 sensor is diagnosed pixel for pixel; 512 x 512 is binned 3 x 3 and
#: 1024 x 1024 6 x 6 (both to 170 x 170), so the search costs the same at any resolution and
#: finds the same causes. What binning hides: a pattern finer than a bin (a single pixel's
#: defect is found before binning, on the full image).
MAX_RAW_DIAGNOSIS_PIXELS = 32_768


def bin_taps(taps: np.ndarray, clipped: np.ndarray, defects: Any, b: int,
             object_id: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, Any, np.ndarray]:
    """Taps ``[N, F, K, H, W]`` averaged over ``b x b`` blocks of good pixels, with the clipped,
    defect and edge maps of the blocks: a block holding a clipped pixel is clipped (the mean
    of the others is not the block's light); a block is the mean of its good pixels where
    they are at least :data:`~tofhil.eval.diagnose.defects.BIN_USABLE_SHARE` of it, else a
    defect; a block across an object's outline in ``object_id`` (the scene's object of each
    pixel) is an edge (:func:`tofhil.binning.one_object`).

    (A test of each block's pixels against a plane within their frame-to-frame noise would find
    edges the scene lacks, but every pixel's fixed pattern fails it too.)"""
    good = ~clipped & ~defects.mask
    share = bin_mean(good.astype(float), b)
    binned = bin_mean(np.where(good, taps, 0.0), b) / np.maximum(share, 1e-12)
    edges = np.zeros(share.shape, bool) if object_id is None else ~one_object(object_id, b)
    # (a block short of good pixels has a clipped one, or is a defect of the binned grid)
    return np.where(share > 0, binned, 0.0), bin_mean(clipped.astype(float), b) > 0, binned_defects(defects, b), edges


def split_session(session: Session, *, block_px: int = 8, min_amplitude_sigma: float = 3.0,
                  saturation_dn: float | None = None, max_frames: int | None = None,
                  offset_channel: bool | None = None, max_pixels: int = MAX_RAW_DIAGNOSIS_PIXELS,
                  objects_on_sensor: Callable[[CameraModel], np.ndarray | None] | None = None) -> HeldOutData:
    """Average a session's frames into training and held-out signals.

    Needs at least 2 frames with raw taps (4 or more recommended). Pixels whose amplitude is
    below ``min_amplitude_sigma`` noise standard deviations, or whose taps reach
    ``saturation_dn`` (default: the largest tap value in the session, if several pixels sit
    there), are left out of both parts. ``offset_channel=None`` adds the tap offset as a
    channel when it carries information: it varies over the image by more than its noise
    (differential devices such as the epc635 report a constant offset).

    An image of more than ``max_pixels`` is binned (:func:`bin_taps`): saturation and defects
    are found on the full image, then the taps of each ``b x b`` block are averaged and the
    rest of the diagnosis sees the binned camera; blocks across an object's outline are left
    out (``objects_on_sensor(camera)``: the scene's object of each sensor pixel, asked for only
    when the image is binned).
    """
    if not session.has_raw:
        raise TofhilError("diagnosis needs raw taps (the complex signal); this session has depth only",
                          file=session.path, field="raw/taps")
    n = session.n_frames if max_frames is None else min(session.n_frames, max_frames)
    if n < 2:
        raise TofhilError(f"has {n} frame(s)", file=session.path, field="raw/taps",
                          expected="at least 2 frames (training and held-out), 4 or more recommended")
    frames = [session.raw_frame(i) for i in range(n)]
    taps = np.stack([f.taps.astype(np.float64) for f in frames])  # [N, F, K, H, W]
    taps_max = np.stack([f.taps.max(axis=(0, 1)) for f in frames]).max(axis=0)
    taps_min = np.stack([f.taps.min(axis=(0, 1)) for f in frames]).min(axis=0)
    # Saturated taps: the one definition of the core (tofhil.demod). Limits given or declared
    # by the session win; otherwise several pixels pinned at one extreme value over all
    # frames are a clipped ADC or full well (a signed differential readout clips at both ends).
    limits = clip_limits(taps_max, taps_min, TapLimits.from_meta(frames[0].meta), saturation_dn)
    clipped = bad_extremes(taps_max, taps_min, limits)
    defects = raw_defects(taps, frames[0].theta_rad, clipped=clipped)
    camera, bin_px = session.camera, bin_factor(session.camera.shape, max_pixels)
    edges = np.zeros(camera.shape, bool)
    if bin_px > 1:
        oid = None if objects_on_sensor is None else objects_on_sensor(camera)
        oid = None if oid is None or oid.shape != camera.shape else oid
        taps, clipped, defects, edges = bin_taps(taps, clipped, defects, bin_px, oid)
        camera = binned_camera(camera, bin_px)
    s = np.stack([phasor(t, f.theta_rad) for t, f in zip(taps, frames)])  # [N, F, H, W]
    b = np.stack([t.mean(axis=(0, 1)) for t in taps])  # [N, H, W]
    offset_mean = b.mean(axis=0)
    if offset_channel is None:
        noise_b = float(np.median(b.std(axis=0, ddof=1))) if n > 1 else 0.0
        spread = float(np.std(offset_mean))
        # a differential readout reports a fixed (zero) offset: no frame-to-frame noise at all
        offset_channel = noise_b > 0 and spread > 3.0 * noise_b
    if offset_channel:
        s = np.concatenate([s, b[:, None].astype(np.complex128)], axis=1)
    train_idx = np.arange(0, n, 2)
    test_idx = np.arange(1, n, 2)

    # Per-pixel noise from the frame-to-frame scatter about each pixel's mean, pooled over
    # a 5 x 5 neighbourhood (E|noise|^2 of one frame); the mean of m frames has 1/m of it.
    mean_all = s.mean(axis=0)
    dev2 = np.abs(frame_deviations(s, mean_all, ~clipped & ~defects.mask)) ** 2
    var_frame = dev2.sum(axis=0) / max(n - 1, 1)
    var_frame = pooled_variance(var_frame, exclude=defects.mask)
    floor = max(float(np.median(var_frame)) * 1e-3, 1e-12)
    var_frame = np.maximum(var_frame, floor)
    # Per real component: a complex channel's E|noise|^2 splits evenly into its real and
    # imaginary parts, so chi2 counts one unit per real value (what the BIC penalty assumes).
    nf = frames[0].freq_hz.size
    var_frame[:nf] /= 2.0

    # Pixels with signal: amplitude above min_amplitude_sigma of one frame's noise. Each frame
    # set is compared on pixels chosen on the other set's amplitude (independent noise): chosen
    # on its own, a pixel near the threshold is kept when its noise raised its amplitude, and
    # its residual is biased along its signal.
    threshold = min_amplitude_sigma * np.sqrt(var_frame[:nf].max(axis=0))
    # a defect is a finding of its own, never evidence against the scene; a bin across an edge
    # is a mixture the binned twin cannot resolve
    good = ~clipped & ~defects.mask & ~edges

    def above(frames_idx: np.ndarray) -> np.ndarray:
        return (np.abs(s[frames_idx, :nf].mean(axis=0)).min(axis=0) > threshold) & good

    by_train, by_test = above(train_idx), above(test_idx)
    usable = by_train | by_test
    board = block_checkerboard(usable.shape, block_px)
    f0 = frames[0]
    return HeldOutData(camera=camera, freq_hz=f0.freq_hz, theta_rad=f0.theta_rad,
                       integration_time_s=f0.integration_time_s,
                       s_train=s[train_idx].mean(axis=0), s_test=s[test_idx].mean(axis=0),
                       var_train=var_frame / len(train_idx), var_test=var_frame / len(test_idx),
                       usable=usable,
                       train_pixels=by_test & board, test_pixels=by_train & ~board,
                       usable_train_frames=by_test, usable_test_frames=by_train, tune_pixels=by_test & ~board,
                       n_train_frames=len(train_idx), n_test_frames=len(test_idx),
                       offset_channel=bool(offset_channel),
                       sensor_config=getattr(session, "sensor_config", None), source=str(session.path),
                       tap_limits=limits, s_frames=s, defects=defects, taps_test=taps[test_idx].mean(axis=0),
                       bin_px=bin_px, sensor_shape=session.camera.shape,
                       **({"channels": f"raw taps: the complex signal S per frequency; binned {bin_px} x {bin_px} "
                                       f"pixels (the {session.camera.width} x {session.camera.height} image to "
                                       f"{camera.width} x {camera.height}: a diagnosis renders at most "
                                       f"{max_pixels} pixels of raw taps; {int(edges.sum())} bins across the scene's "
                                       "object's outline left out)"} if bin_px > 1 else {}))
