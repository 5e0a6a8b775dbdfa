"""Held-out data made from a known complex signal, for the selection, form and verdict tests
that use a small forward model of their own instead of the renderer: two noisy frames (one
training, one held out), split on a checkerboard of 4 x 4 pixel blocks."""

from __future__ import annotations

import numpy as np

from tofhil.camera import CameraModel
from tofhil.eval.diagnose.heldout import HeldOutData


def heldout_from_signal(s_true: np.ndarray, sigma: float, seed: int = 0,
                        freq_hz: tuple[float, ...] = (20e6,)) -> HeldOutData:
    """``s_true`` ``[F, H, W]`` (one plane per frequency of ``freq_hz``) plus complex Gaussian
    noise of ``sigma`` per component."""
    rng = np.random.default_rng(seed)
    noisy = [s_true + sigma * (rng.standard_normal(s_true.shape) + 1j * rng.standard_normal(s_true.shape))
             for _ in range(2)]
    h, w = s_true.shape[-2:]
    v, u = np.mgrid[0:h, 0:w]
    train = ((v // 4 + u // 4) % 2) == 0
    var = np.full(s_true.shape, sigma ** 2)
    return HeldOutData(camera=CameraModel(w, h, 20.0, 20.0, w / 2, h / 2), freq_hz=np.asarray(freq_hz, dtype=float),
                       theta_rad=np.arange(4) * np.pi / 2, integration_time_s=1e-3, s_train=noisy[0],
                       s_test=noisy[1], var_train=var, var_test=var, usable=np.ones((h, w), bool),
                       train_pixels=train, test_pixels=~train, n_train_frames=1, n_test_frames=1)
