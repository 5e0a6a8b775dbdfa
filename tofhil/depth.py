"""Raw taps -> depth frame: demodulate every frequency, unwrap, flag invalid pixels."""

from __future__ import annotations

import numpy as np

from tofhil.demod import TapLimits, bad_tap_pixels, iq, phase_from_iq
from tofhil.fastdepth import fused_depth, fused_supported
from tofhil.frames import DepthFrame, RawFrame
from tofhil.unwrap import unwrap

#: Rows processed together: small enough that a block's intermediates stay in the CPU cache.
_BLOCK_PIXELS = 32768


def depth_from_raw(frame: RawFrame, *, min_amplitude: float = 0.0,
                   tap_limits: TapLimits | None = None, margin: float = 0.5, fused: bool = True) -> DepthFrame:
    """Demodulate and unwrap a raw frame into radial distance.

    A pixel is invalid where its amplitude (the mean over frequencies) is below
    ``min_amplitude``, where any tap is saturated or not finite (``tap_limits``, by default
    the limits the frame declares in its ``meta``: :meth:`TapLimits.from_meta`), where the
    frequencies disagree during unwrapping, or where the result is not finite. The amplitude returned is the mean over
    frequencies; the intensity is the mean offset B. Float32 taps (any K >= 3) at one to three
    frequencies take the fused path (:mod:`tofhil.fastdepth`); ``fused=False`` forces the
    general numpy path (any K >= 3, any number of frequencies).
    """
    taps = frame.taps
    f, k, h, w = taps.shape
    limits = TapLimits.from_meta(frame.meta) if tap_limits is None else tap_limits
    if fused and fused_supported(taps, frame.theta_rad):
        distance, amplitude, intensity, conflict, rng, valid = fused_depth(taps, frame.theta_rad, frame.freq_hz,
                                                                           margin, limits)
        return _depth_frame(frame, distance, amplitude, intensity, conflict, rng, min_amplitude, None, valid)
    dtype = np.float32 if taps.dtype == np.float32 else np.float64
    distance = np.empty((h, w), dtype)
    amplitude = np.empty((h, w), dtype)
    intensity = np.empty((h, w), dtype)
    conflict = np.empty((h, w), bool)
    bad = np.empty((h, w), bool)
    rows = max(1, _BLOCK_PIXELS // w)
    for r0 in range(0, h, rows):
        block = taps[:, :, r0:r0 + rows]
        bad[r0:r0 + rows] = bad_tap_pixels(block, limits)
        i, q = iq(block, frame.theta_rad)
        amp = np.sqrt(i * i + q * q)
        res = unwrap(phase_from_iq(i, q), frame.freq_hz, amplitude=amp, margin=margin)
        distance[r0:r0 + rows] = res.distance_m
        conflict[r0:r0 + rows] = res.conflict
        np.mean(amp, axis=0, out=amplitude[r0:r0 + rows])
        np.mean(block.reshape((f * k,) + block.shape[2:]), axis=0, out=intensity[r0:r0 + rows])
    return _depth_frame(frame, distance, amplitude, intensity, conflict, float(res.unambiguous_range_m),
                        min_amplitude, bad)


def _depth_frame(frame: RawFrame, distance: np.ndarray, amplitude: np.ndarray, intensity: np.ndarray,
                 conflict: np.ndarray, unambiguous_range_m: float, min_amplitude: float,
                 bad_taps: np.ndarray | None, valid: np.ndarray | None = None) -> DepthFrame:
    # A saturated or NaN tap is no measurement, whatever arithmetic made of it; nor is a
    # finite tap so large that the amplitude overflowed. (The fused kernel applies this
    # same rule in its pass and hands ``valid`` in.)
    if valid is None:
        valid = ~(conflict | bad_taps) & np.isfinite(distance) & np.isfinite(amplitude)
    if min_amplitude > 0:
        valid &= amplitude >= min_amplitude
    return DepthFrame(distance_m=distance, kind="radial", camera=frame.camera,
                      amplitude=amplitude, intensity=intensity,
                      valid=valid, timestamp_s=frame.timestamp_s, sequence=frame.sequence,
                      temperature_c=frame.temperature_c, unwrap_conflict=conflict,
                      meta={"unambiguous_range_m": float(unambiguous_range_m)})


def saturated_amplitude(amplitude: np.ndarray, valid: np.ndarray, *, min_pixels: int = 5) -> np.ndarray:
    """Pixels of a device's amplitude image pinned at its largest value: a clipped sensor.

    Several pixels (``min_pixels`` or more) at exactly the image's maximum, but fewer than half
    of the valid ones (an evenly lit synthetic image is not saturated), are taken as clipped;
    their depth and amplitude say nothing about the scene."""
    amplitude = np.asarray(amplitude)
    vals = amplitude[valid & np.isfinite(amplitude)]
    if vals.size == 0:
        return np.zeros(amplitude.shape, bool)
    pinned = valid & (amplitude >= vals.max())
    n = int(pinned.sum())
    return pinned if min_pixels <= n < 0.5 * vals.size else np.zeros(amplitude.shape, bool)


def relative_depth_noise(depth_m: np.ndarray, valid: np.ndarray) -> float:
    """A depth image's noise relative to depth, from the image itself: the robust spread
    (1.4826 MAD) of each valid pixel's relative difference from the median of its 3 x 3 valid
    neighbours (corrected for the median's own noise). Surfaces' shape and their edges lie in
    the tail the MAD ignores. ToF noise grows with distance, so ``sigma(z) ~ result * z``;
    0 without a pixel that has neighbours."""
    import warnings

    z = np.where(valid, np.asarray(depth_m, np.float64), np.nan)
    h, w = z.shape
    p = np.pad(z, 1, constant_values=np.nan)
    stack = np.stack([p[i:i + h, j:j + w] for i in range(3) for j in range(3) if (i, j) != (1, 1)])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # pixels without valid neighbours
        rel = (z - np.nanmedian(stack, axis=0)) / z
    rel = rel[np.isfinite(rel)]
    if rel.size == 0:
        return 0.0
    # a difference from a median of ~8 noisy neighbours is sqrt(1 + 1/8) wider than one pixel's noise
    return 1.4826 * float(np.median(np.abs(rel - np.median(rel)))) / np.sqrt(1.0 + 1.0 / 8.0)
