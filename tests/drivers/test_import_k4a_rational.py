"""The Azure Kinect importer keeps the factory lens exactly: OpenCV's rational model, no refit."""

from __future__ import annotations

import numpy as np
import pytest

from tofhil.drivers.importers.dispatch import import_file
from tofhil.drivers.importers.k4a import K4AIntrinsics, factory_camera, read_k4a_recording
from tofhil.session import open_session

from tests.real_data import AZURE_KINECT_MKV, need


@pytest.fixture(scope="module")
def rec():
    with read_k4a_recording(need(AZURE_KINECT_MKV)) as r:
        yield r


def test_session_camera_is_the_factory_rational_model(rec, tmp_path):
    intr = rec.intrinsics
    cam = rec.camera
    k1, k2, k3, k4, k5, k6 = intr.k
    assert cam.distortion_model == "rational"
    assert cam.dist == (k1, k2, intr.p1, intr.p2, k3, k4, k5, k6)
    # every pixel's ray is the SDK model's (its own Gauss-Newton inverse), not a refit's
    v, u = np.mgrid[0:intr.height, 0:intr.width].astype(np.float64)
    x, y, ok = intr.undistort(u, v)
    r = cam.pixel_rays(u[ok], v[ok])
    np.testing.assert_allclose(r[:, 0] / r[:, 2], x[ok], rtol=0, atol=1e-9)
    np.testing.assert_allclose(r[:, 1] / r[:, 2], y[ok], rtol=0, atol=1e-9)
    assert rec.fit.max_residual_px < 1e-6 and "exactly" in rec.fit.method
    res = import_file(need(AZURE_KINECT_MKV), tmp_path / "k.h5")
    _, z_mm, _ = rec.frame(0)
    with open_session(res.out) as s:
        assert s.camera == cam
        d = s.depth_frame(0)
        assert "exactly" in s.device["camera_fit"]["method"]
    valid = d.valid
    # z back from the stored radial distance along the stored camera's rays: float32 storage only
    np.testing.assert_allclose(d.z_m[valid], z_mm[valid] * 1e-3, rtol=2e-7, atol=0)


def test_centre_of_distortion_off_axis_is_refitted():
    """A calibration whose centre of distortion is not the principal point has no OpenCV
    model: the 5-parameter refit, said so."""
    intr = K4AIntrinsics(width=64, height=48, fx=40.0, fy=40.0, cx=31.5, cy=23.5,
                         k=(0.3, -0.02, 0.0, 0.5, 0.05, 0.0), p1=0.0, p2=0.0, codx=0.01, cody=0.0)
    assert intr.camera_model() is None
    fit = factory_camera(intr, step=1)
    assert fit.camera.distortion_model == "plumb_bob" and "refit" in fit.method
