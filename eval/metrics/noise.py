"""Noise figures every part of evaluation shares: the robust spread, the pooled local variance
of a frame-to-frame scatter, and a phasor's scatter as a distance.

One home for each, so that a report's noise, diagnosis's noise threshold and a fit's weights
are the same number computed the same way.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import uniform_filter

from tofhil.demod import radians_per_metre

#: The median absolute deviation of Gaussian noise is sigma / 1.4826.
MAD_TO_SIGMA = 1.4826

#: Side of the square of pixels over which a pixel's frame-to-frame noise variance is pooled:
#: a handful of frames gives each pixel a variance too noisy to weight a fit with alone.
NOISE_POOL_PX = 5


def robust_sigma(x: np.ndarray) -> float:
    """The standard deviation of Gaussian noise from its median absolute deviation: outliers
    (edges, texture, bad pixels) do not inflate it."""
    x = np.asarray(x)
    return float(MAD_TO_SIGMA * np.median(np.abs(x - np.median(x))))


def pooled_variance(var: np.ndarray, exclude: np.ndarray | None = None) -> np.ndarray:
    """Per-pixel variance maps ``[C, H, W]`` averaged over the ``NOISE_POOL_PX`` square around
    each pixel (edges repeat the nearest pixel), channel by channel. ``exclude`` (bool
    ``[H, W]``): pixels whose scatter is not noise (defects) are left out of every average."""
    if exclude is None or not exclude.any():
        return np.stack([uniform_filter(v, size=NOISE_POOL_PX, mode="nearest") for v in var])
    keep = (~exclude).astype(np.float64)
    count = np.maximum(uniform_filter(keep, size=NOISE_POOL_PX, mode="nearest"), 1e-12)
    return np.stack([uniform_filter(v * keep, size=NOISE_POOL_PX, mode="nearest") / count for v in var])


def phasor_depth_sigma(variance: np.ndarray, amplitude: np.ndarray, freq_hz: np.ndarray | float) -> np.ndarray:
    """The radial-distance noise (m) of a phasor of ``amplitude`` whose scatter across it
    (tangential, one real component) has ``variance``: ``sqrt(var) / A`` radians of phase,
    divided by the phase per metre ``4 pi f / c``."""
    k = radians_per_metre(freq_hz)
    return np.sqrt(variance / amplitude ** 2 / k ** 2)
