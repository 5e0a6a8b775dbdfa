"""The DepthAI driver reads the factory lens as the model that holds it (no terms dropped)."""

from __future__ import annotations

import pytest

dai = pytest.importorskip("depthai")

from tofhil.drivers.depthai.driver import factory_lens  # noqa: E402

SOCKET = dai.CameraBoardSocket.CAM_A


def calibration(coeffs: list[float], fisheye: bool = False):
    c = dai.CalibrationHandler()
    c.setCameraIntrinsics(SOCKET, [[300.0, 0.0, 320.0], [0.0, 300.0, 240.0], [0.0, 0.0, 1.0]], 640, 480)
    c.setDistortionCoefficients(SOCKET, coeffs)
    if fisheye:
        c.setCameraType(SOCKET, dai.CameraModel.Fisheye)
    return c


def test_perspective_coefficients_become_the_shortest_opencv_model():
    five = [0.1, -0.02, 0.001, -0.002, 0.003]
    model, dist, dropped = factory_lens(calibration(five + [0.0] * 9), SOCKET)
    assert model == "plumb_bob" and dist == pytest.approx(five, abs=1e-7) and not dropped
    rational = five + [0.5, 0.04, -0.01]
    model, dist, _ = factory_lens(calibration(rational + [0.0] * 6), SOCKET)
    assert model == "rational" and dist == pytest.approx(rational, abs=1e-7)
    prism = rational + [1e-3, -2e-4, 3e-4, -1e-4]
    model, dist, dropped = factory_lens(calibration(prism + [0.01, 0.0]), SOCKET)
    assert model == "rational" and dist == pytest.approx(prism, abs=1e-7)
    assert set(dropped) == {"tau_x"}          # the sensor tilt has no place: said so


def test_fisheye_calibration_is_a_fisheye():
    model, dist, _ = factory_lens(calibration([-0.01, 0.03, -0.02, 0.005] + [0.0] * 10, fisheye=True), SOCKET)
    assert model == "fisheye" and dist == pytest.approx([-0.01, 0.03, -0.02, 0.005], abs=1e-7)
