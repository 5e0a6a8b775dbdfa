"""The TOFcam635 as tofhil sees it: its device profile and the tap conversion at the edge.

Tap convention: the vendor computes the phase as ``atan2(DCS3 - DCS1, DCS2 - DCS0) + pi``
after removing the 2048 mid-scale offset, i.e. ``phi = atan2(DCS1 - DCS3, DCS0 - DCS2)``.
That is exactly the canonical estimator for ``DCS_k = A cos(phi - theta_k)`` with
``theta_k = 0, 90, 180, 270 deg`` and sign +1, so the profile declares those phases; the
driver subtracts the offset and applies the :class:`tofhil.demod.TapConvention` at the edge.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from tofhil.demod import TapConvention
from tofhil.drivers.tofcam635 import protocol as P

@dataclass(frozen=True)
class DeviceProfile:
    """What tofhil needs to know about a device model to convert its data at the edge."""

    model: str
    camera_preset: str
    taps: TapConvention
    dcs_offset: int
    mod_freqs_hz: tuple[float, ...]
    #: Default integration time when the user gives none (vendor initialize(): 125 us).
    default_integration_time_s: float = 125e-6
    max_integration_time_s: float = 65535e-6


TOFCAM635 = DeviceProfile(
    model="TOFcam635",
    camera_preset="epc635",
    taps=TapConvention(theta_rad=(0.0, 0.5 * math.pi, math.pi, 1.5 * math.pi), order=None, sign=1.0),
    dcs_offset=P.DCS_OFFSET,
    mod_freqs_hz=(10.0e6, 20.0e6),
)


def dcs_to_canonical(dcs: np.ndarray, profile: DeviceProfile = TOFCAM635) -> tuple[np.ndarray, np.ndarray]:
    """Device DCS ``[4, H, W]`` (12-bit around 2048) -> canonical taps (DN, offset removed) and
    phases. The taps stay integers in the device's own type (int16: -2048..2047), so a session
    stores them as the device delivered them (docs/session-format.md)."""
    d = np.asarray(dcs)
    wide = d.astype(np.int32) - np.int32(profile.dcs_offset)   # (no int16 wrap on a corrupt value)
    taps = wide.astype(np.int16) if wide.size == 0 or (wide.min() >= -32768 and wide.max() <= 32767) else wide
    return profile.taps.to_canonical(taps)


def canonical_phases(profile: DeviceProfile = TOFCAM635) -> np.ndarray:
    """Phases of the canonical taps the driver delivers (what an emulator must render)."""
    _, theta = profile.taps.to_canonical(np.zeros((len(profile.taps.theta_rad), 1, 1)))
    return theta


def canonical_to_dcs(taps: np.ndarray, profile: DeviceProfile = TOFCAM635) -> np.ndarray:
    """Inverse of :func:`dcs_to_canonical` (for the emulator): taps at :func:`canonical_phases`
    -> device stack order, plus the mid-scale offset. Not quantised or clipped."""
    t = np.asarray(taps)
    if profile.taps.order is not None:
        t = np.take(t, np.argsort(np.asarray(profile.taps.order)), axis=-3)
    return t + profile.dcs_offset
