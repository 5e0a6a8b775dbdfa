"""The colour/depth misalignment at depth silhouettes: on a synthetic card in front of a wall the
truth is known (the colour image is rendered in closed form from the card's geometry), on the real
Azure Kinect recording the measure must pass its own self-check."""

from __future__ import annotations

import numpy as np
import pytest

from tofhil.camera import CameraModel
from tofhil.eval.rgb.edge_alignment import SLOPE_RANGE, edge_alignment
from tests.real_data import AZURE_KINECT_MKV, need

DEPTH_CAM = CameraModel(width=160, height=120, fx=100.0, fy=100.0, cx=79.5, cy=59.5)
COLOR_CAM = CameraModel(width=320, height=240, fx=220.0, fy=220.0, cx=159.5, cy=119.5)
BASELINE_M = 0.03   # the colour camera 30 mm to the depth camera's right (x_color = x_depth - 0.03)
CARD = (0.1, 0.08, 0.5)   # half width, half height, depth: its sides at depth columns 59.5 and 99.5


def _to_color(dx: float = 0.0) -> np.ndarray:
    t = np.eye(4)
    t[0, 3] = -BASELINE_M + dx
    return t


def synthetic() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Depth z of the card (0.5 m) on a wall (1.5 m) and the colour camera's image of both, the
    card white (220) on a grey wall (90), 4 x 4 samples a pixel (the card's edges anti-aliased)."""
    v, u = np.mgrid[0:DEPTH_CAM.height, 0:DEPTH_CAM.width].astype(np.float64)
    x, y = (u - DEPTH_CAM.cx) / DEPTH_CAM.fx, (v - DEPTH_CAM.cy) / DEPTH_CAM.fy
    hw, hh, zc = CARD
    z = np.where((np.abs(x * zc) < hw) & (np.abs(y * zc) < hh), zc, 1.5)
    s = (np.arange(4) + 0.5) / 4 - 0.5
    vc, uc = np.mgrid[0:COLOR_CAM.height, 0:COLOR_CAM.width].astype(np.float64)
    acc = np.zeros(vc.shape)
    for du in s:
        for dv in s:
            xc = (uc + du - COLOR_CAM.cx) / COLOR_CAM.fx
            yc = (vc + dv - COLOR_CAM.cy) / COLOR_CAM.fy
            # the ray meets the card's plane z = zc at colour-frame x = xc zc, depth-frame x = that + baseline
            on = (np.abs(xc * zc + BASELINE_M) < hw) & (np.abs(yc * zc) < hh)
            acc += np.where(on, 220.0, 90.0)
    grey = np.round(acc / 16).astype(np.uint8)
    return z, np.ones(z.shape, bool), np.repeat(grey[..., None], 3, axis=2)


def _rays(u: np.ndarray, v: np.ndarray):
    return (u - DEPTH_CAM.cx) / DEPTH_CAM.fx, (v - DEPTH_CAM.cy) / DEPTH_CAM.fy, np.ones(np.shape(u), bool)


def test_true_extrinsics_measure_no_misalignment_and_the_self_check_passes():
    z, valid, rgb = synthetic()
    r = edge_alignment(z, valid, _rays, _to_color(), COLOR_CAM, rgb)
    assert r.left.n == r.right.n == 32             # every row of the card
    assert abs(r.shift_px) < 0.2 and abs(r.spread_px) < 0.2, (r.shift_px, r.spread_px)
    assert r.passed and 0.9 < r.slope < 1.1


def test_a_wrong_baseline_shows_as_the_predicted_shift():
    """4 mm of baseline error moves the card's edges by fx * 4 mm / 0.5 m = 1.76 colour px."""
    z, valid, rgb = synthetic()
    r = edge_alignment(z, valid, _rays, _to_color(0.004), COLOR_CAM, rgb)
    assert r.shift_px == pytest.approx(-COLOR_CAM.fx * 0.004 / CARD[2], abs=0.2)
    assert abs(r.spread_px) < 0.2


def test_kinect_mug_edges_are_measured_and_the_measure_checks_itself():
    from tofhil.drivers.importers.k4a import read_k4a_recording
    from tofhil.drivers.importers.k4a_color import read_color_frame

    path = need(AZURE_KINECT_MKV)
    rgb, ccam, t = read_color_frame(path, 0)
    with read_k4a_recording(path) as rec:
        _, z_mm, _ = rec.frame(0)
        intr = rec.intrinsics
    v, u = np.mgrid[0:intr.height, 0:intr.width].astype(np.float64)
    ok = intr.undistort(u, v)[2]
    r = edge_alignment(z_mm * 1e-3, (z_mm > 0) & ok, intr.undistort, t, ccam, rgb)
    assert r.left.n > 100 and r.right.n > 50          # the mug's two sides (and its handle)
    assert SLOPE_RANGE[0] <= r.slope <= SLOPE_RANGE[1], r.probes
    assert abs(r.shift_px) < 3.0
