"""Raw taps -> depth frame: demodulate every frequency, unwrap, flag invalid pixels."""

from __future__ import annotations

import numpy as np

from tofhil.demod import offset, phasor, wrapped_phase
from tofhil.frames import DepthFrame, RawFrame
from tofhil.unwrap import unwrap


def depth_from_raw(frame: RawFrame, *, min_amplitude: float = 0.0,
                   saturation_level: float | None = None, margin: float = 0.5) -> DepthFrame:
    """Demodulate and unwrap a raw frame into radial distance.

    A pixel is invalid where its amplitude (the mean over frequencies) is below
    ``min_amplitude``, where any tap reaches ``saturation_level`` (if given), or where the
    frequencies disagree during unwrapping. The amplitude returned is the mean over
    frequencies; the intensity is the mean offset B.
    """
    s = phasor(frame.taps, frame.theta_rad)  # [F, H, W]
    amp = np.abs(s)
    phase = wrapped_phase(s)
    res = unwrap(phase, frame.freq_hz, amplitude=amp, margin=margin)
    amplitude = amp.mean(axis=0)
    valid = ~res.conflict & (amplitude >= min_amplitude)
    if saturation_level is not None:
        valid &= ~(frame.taps >= saturation_level).any(axis=(0, 1))
    return DepthFrame(distance_m=res.distance_m, kind="radial", camera=frame.camera,
                      amplitude=amplitude, intensity=offset(frame.taps).mean(axis=0),
                      valid=valid, timestamp_s=frame.timestamp_s, sequence=frame.sequence,
                      temperature_c=frame.temperature_c, unwrap_conflict=res.conflict,
                      meta={"unambiguous_range_m": res.unambiguous_range_m})
