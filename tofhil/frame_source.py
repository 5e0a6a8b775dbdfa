"""What an emulated camera sees: the interface of the frame sources emulators are given.

An emulator (``tofhil.drivers``) speaks a device's protocol; the images it sends come from a
frame source its caller injects. The simulator twin provides the real ones
(``tofhil.sim.sources``); the drivers never import it. This module is the contract between
the two, in the core so that neither depends on the other.
"""

from __future__ import annotations

import threading
from abc import ABC, abstractmethod
from typing import Protocol

import numpy as np

from tofhil.camera import CameraModel
from tofhil.demod import taps_from_signal

#: Integration time every source's amplitudes are quoted at (the TOFcam635 vendor client's
#: initialize() value); signal, offset and ambient scale linearly with the exposure.
REFERENCE_INTEGRATION_TIME_S = 125e-6


class TapNoise(Protocol):
    """Per-frame noise of an emulated sensor: noisy taps (DN) from noise-free ones."""

    def apply(self, taps: np.ndarray, rng: np.random.Generator) -> np.ndarray: ...


class ImageSource(ABC):
    """Noise-free canonical taps (DN) of a correlation (raw-tap) sensor.

    Sources render at :data:`REFERENCE_INTEGRATION_TIME_S`, once per modulation frequency
    (cached); other integration times are a scale factor, not a new render.
    """

    camera: CameraModel
    description: str = ""

    def __init__(self) -> None:
        self._cache: dict[float, np.ndarray] = {}
        self._lock = threading.Lock()

    def taps(self, freq_hz: float, integration_time_s: float, theta_rad: np.ndarray) -> np.ndarray:
        """``[K, H, W]`` float32 taps ``B + A cos(phi - theta_k)`` for this exposure."""
        key = float(freq_hz)
        with self._lock:
            ref = self._cache.get(key)
            if ref is None:
                a, phi, b = self.signal(freq_hz)
                ref = taps_from_signal(a, phi, b, theta_rad).astype(np.float32)
                ref.setflags(write=False)
                self._cache[key] = ref
        return ref * np.float32(integration_time_s / REFERENCE_INTEGRATION_TIME_S)

    @abstractmethod
    def signal(self, freq_hz: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Amplitude (DN), phase (rad) and offset (DN) images ``[H, W]`` at the reference exposure."""

    @abstractmethod
    def noise_model(self) -> TapNoise:
        """The per-frame noise the emulator adds to these taps."""

    def scene_text(self) -> str:
        """The scene this source renders, as text (stored in a capture's session), or ``""``."""
        return ""


class DepthScene(Protocol):
    """What a depth camera's host-side emulation sends (the DepthAI host pipeline): per
    frame, images ``radial_m``, ``z_m``, ``amplitude``, ``intensity`` and ``phase``."""

    fps: float
    drop_amplitude_of: tuple[int, ...]
    n_frames: int | None

    def camera_model(self) -> CameraModel: ...

    def render_frames(self, camera: CameraModel) -> list[dict[str, np.ndarray]]: ...


__all__ = ["REFERENCE_INTEGRATION_TIME_S", "ImageSource", "TapNoise", "DepthScene"]
