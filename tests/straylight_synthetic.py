"""Synthetic raw sessions for the compare/report/CLI tests, built independently of eval.

A 80 x 60 camera looks at a wall at 2 m (reflectance 1) with a dark square, and
optionally a white card at 0.3 m; the signal per pixel is ``A exp(i 4 pi f d / c)`` with
``A = rho / d^2`` (inverse-square law, cos factors ignored: the same for A and B). Stray
light is a Gaussian lobe plus a veil, convolved with scipy's FFT convolution.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.signal import fftconvolve
from scipy.stats import norm

from tofhil import C_M_PER_S
from tofhil.camera import CameraModel
from tofhil.demod import equally_spaced_phases, taps_from_signal
from tofhil.frames import RawFrame
from tofhil.session import SessionWriter

H, W = 60, 80
FREQ = np.array([20e6])
THETA = equally_spaced_phases(4)
CAMERA = CameraModel.from_fov(W, H, 60.0, name="synthetic")
SQUARE = (slice(22, 36), slice(46, 62))  # rows, cols of the dark square
CARD = (slice(10, 26), slice(8, 24))


def wall_distance() -> np.ndarray:
    """Radial distance to a fronto-parallel wall at z = 2 m."""
    return 2.0 / CAMERA.ray_z


def scene_signal(square_rho: float | None = 0.05, card: bool = True, wall: bool = True) -> tuple[np.ndarray, np.ndarray]:
    dist = wall_distance().copy()
    rho = np.full((H, W), 1.0 if wall else 0.0)
    if square_rho is not None and wall:
        rho[SQUARE] = square_rho
    if card:
        dist[CARD] = 0.3 / CAMERA.ray_z[CARD]
        rho[CARD] = 1.0
    amp = rho / dist ** 2
    return amp * np.exp(1j * 4 * np.pi * FREQ[0] * dist / C_M_PER_S), dist


def psf_kernel(weight: float = 0.08, sigma: float = 9.0, veil: float = 0.03) -> np.ndarray:
    y = np.arange(-(H - 1), H)[:, None]
    x = np.arange(-(W - 1), W)[None, :]
    g = (norm.cdf(y + 0.5, scale=sigma) - norm.cdf(y - 0.5, scale=sigma)) * \
        (norm.cdf(x + 0.5, scale=sigma) - norm.cdf(x - 0.5, scale=sigma))
    return weight * g / g.sum() + veil / (H * W)


def with_stray_light(s: np.ndarray, kernel: np.ndarray | None = None) -> np.ndarray:
    k = psf_kernel() if kernel is None else kernel
    return s + fftconvolve(s, k, mode="full")[H - 1:2 * H - 1, W - 1:2 * W - 1]


def write_session(path: Path, s: np.ndarray, n_frames: int = 2, noise: float = 0.0, seed: int = 0,
                  offset: float = 5.0) -> Path:
    rng = np.random.default_rng(seed)
    with SessionWriter(path, CAMERA, device={"model": "synthetic"}) as w:
        for i in range(n_frames):
            taps = taps_from_signal(np.abs(s)[None], np.angle(s)[None], np.full((1, H, W), offset), THETA)
            if noise:
                taps = taps + rng.normal(0, noise, taps.shape)
            w.append(RawFrame(taps=taps.astype(np.float32), freq_hz=FREQ, theta_rad=THETA,
                              integration_time_s=1e-3, camera=CAMERA, sequence=i, timestamp_s=0.01 * i))
    return path
