"""Occlusion that knows the depth noise (issue 34's walkthrough: a simulated board session with
noise had 3508 of 17960 points 'occluded', 288 without noise): a noisy flat wall hides nothing."""

from __future__ import annotations

import numpy as np

from tofhil.camera import CameraModel
from tofhil.eval.rgb.colorize import colorize_points, depth_noise


def test_a_noisy_wall_is_not_occluded_by_its_own_noise() -> None:
    tof = CameraModel(width=160, height=120, fx=140.0, fy=140.0, cx=79.5, cy=59.5)
    rng = np.random.default_rng(3)
    sigma = 0.012                                   # 12 mm at 1 m: a ToF camera at low amplitude
    z = 1.0 + rng.normal(0.0, sigma, tof.shape)
    z[40:80, 60:100] = 0.6 + rng.normal(0.0, sigma, (40, 40))   # a card in front: real occlusion
    valid = np.ones(tof.shape, bool)
    v, u = np.mgrid[0:120, 0:160].astype(np.float64)
    rays = tof.pixel_rays(u, v)
    pts = (rays / rays[..., 2:3] * z[..., None])[valid]
    noise = depth_noise(z, valid)
    assert 0.6 * sigma < np.median(noise[z > 0.9]) < 1.5 * sigma   # the estimate finds the noise
    t = np.eye(4)
    t[0, 3] = -0.05                                 # colour camera 5 cm to the right
    color = CameraModel(width=320, height=240, fx=280.0, fy=280.0, cx=159.5, cy=119.5)
    rgb = np.full((240, 320, 3), 128, np.uint8)
    naive = colorize_points(pts, t, color, rgb)
    aware = colorize_points(pts, t, color, rgb, noise_m=noise[valid])
    # the strip of wall beside the card that the colour camera, 5 cm to the right, sees through
    # the card (the card spans x/z in (-0.14, 0.15) at z = 0.6; seen from x = +0.05 it covers
    # the wall's x in (-0.17, 0.11))
    x = pts[:, 0] / pts[:, 2]
    hidden = (np.abs(pts[:, 2] - 1.0) < 0.1) & (np.abs(pts[:, 1] / pts[:, 2]) < 0.12) & (x > -0.165) & (x < -0.145)
    assert hidden.sum() > 50
    assert aware.occluded[hidden].mean() > 0.9
    free_wall = (np.abs(pts[:, 2] - 1.0) < 0.1) & ~hidden & (np.abs(x) > 0.25)
    assert naive.occluded[free_wall].mean() > 0.05  # what the test without the noise did
    assert aware.occluded[free_wall].mean() < 0.005
