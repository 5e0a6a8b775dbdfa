"""Camera model geometry: rays, distortion, radial <-> z, planar point clouds, presets."""

from __future__ import annotations

import numpy as np
import pytest

from tofhil.camera import CameraModel, list_camera_presets, load_camera_preset
from tofhil.errors import InputFileError

DISTORTED = CameraModel(width=64, height=48, fx=50.0, fy=52.0, cx=31.7, cy=24.2,
                        dist=(-0.25, 0.08, 0.001, -0.0015, -0.01))


def test_rays_are_unit_and_centre_ray_is_optical_axis():
    cam = CameraModel(width=5, height=5, fx=10.0, fy=10.0, cx=2.0, cy=2.0)
    r = cam.rays
    np.testing.assert_allclose(np.linalg.norm(r, axis=-1), 1.0, atol=1e-12)
    np.testing.assert_allclose(r[2, 2], [0, 0, 1], atol=1e-15)
    # pixel (u=4, v=2) is 2 px right of centre: direction (0.2, 0, 1) normalised
    np.testing.assert_allclose(r[2, 4], np.array([0.2, 0, 1]) / np.sqrt(1.04), atol=1e-12)


def test_projection_inverts_rays_with_distortion():
    v, u = np.mgrid[0:48, 0:64].astype(float)
    pts = DISTORTED.rays * 2.5
    uv = DISTORTED.project(pts)
    np.testing.assert_allclose(uv[..., 0], u, atol=1e-6)
    np.testing.assert_allclose(uv[..., 1], v, atol=1e-6)


def test_undistortion_agrees_with_opencv():
    import cv2

    v, u = np.mgrid[0:48:5, 0:64:5].astype(np.float64)
    pts = np.stack([u.ravel(), v.ravel()], axis=-1)[:, None, :]
    ref = cv2.undistortPoints(pts, DISTORTED.K, np.array(DISTORTED.dist),
                              criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14))[:, 0, :]
    x, y = DISTORTED.undistort_normalized(u.ravel(), v.ravel())
    np.testing.assert_allclose(x, ref[:, 0], atol=1e-7)
    np.testing.assert_allclose(y, ref[:, 1], atol=1e-7)


def test_compiled_undistortion_is_the_numpy_iteration(monkeypatch: pytest.MonkeyPatch):
    """Many points run through the compiled kernel: bit-identical to the numpy iteration, and
    OpenCV's inverse too (a kernel that iterated wrongly would miss it)."""
    import cv2

    import tofhil.camera as camera_module

    rng = np.random.default_rng(1)
    u = rng.uniform(-0.5, 63.5, (70, 90))          # 6300 subpixel points, >= the threshold
    v = rng.uniform(-0.5, 47.5, (70, 90))
    compiled = DISTORTED.undistort_normalized(u, v)
    monkeypatch.setattr(camera_module, "_COMPILED_UNDISTORT_MIN", 10**12)
    plain = DISTORTED.undistort_normalized(u, v)
    assert compiled[0].shape == u.shape
    np.testing.assert_array_equal(compiled[0], plain[0])
    np.testing.assert_array_equal(compiled[1], plain[1])
    pts = np.stack([u.ravel(), v.ravel()], axis=-1)[:, None, :]
    ref = cv2.undistortPoints(pts, DISTORTED.K, np.array(DISTORTED.dist),
                              criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14))[:, 0, :]
    np.testing.assert_allclose(compiled[0].ravel(), ref[:, 0], atol=1e-7)
    np.testing.assert_allclose(compiled[1].ravel(), ref[:, 1], atol=1e-7)


def test_radial_z_round_trip_and_closed_form():
    cam = CameraModel.from_fov(40, 30, 70.0)
    rng = np.random.default_rng(0)
    d = rng.uniform(0.2, 8.0, cam.shape)
    np.testing.assert_allclose(cam.z_to_radial(cam.radial_to_z(d)), d, rtol=1e-12)
    # closed form for a pinhole: z = d / sqrt(1 + x^2 + y^2), x = (u - cx)/fx
    v, u = np.mgrid[0:30, 0:40]
    x, y = (u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy
    np.testing.assert_allclose(cam.radial_to_z(d), d / np.sqrt(1 + x**2 + y**2), rtol=1e-12)


@pytest.mark.parametrize("cam", [CameraModel.from_fov(80, 60, 60.0), DISTORTED])
def test_point_cloud_of_plane_is_planar(cam):
    # A plane n.p = h seen by the camera: radial distance along each ray is h / (n . ray).
    n = np.array([0.2, -0.1, 1.0])
    n /= np.linalg.norm(n)
    h = 1.5
    radial = h / (cam.rays @ n)
    pts = cam.points(radial, "radial")
    assert pts.shape == (cam.width * cam.height, 3)
    np.testing.assert_allclose(pts @ n, h, atol=1e-9)
    # the same plane as z-depth
    pts_z = cam.points(cam.radial_to_z(radial), "z")
    np.testing.assert_allclose(pts_z, pts, atol=1e-9)
    # and through Open3D, with a plane fit independent of our maths
    cloud = cam.point_cloud(radial, amplitude=np.ones(cam.shape))
    model, inliers = cloud.segment_plane(distance_threshold=1e-6, ransac_n=3, num_iterations=50)
    assert len(inliers) == len(pts)
    assert abs(abs(np.dot(model[:3], n)) - 1) < 1e-6


def test_invalid_pixels_are_dropped():
    cam = CameraModel.from_fov(4, 3, 60.0)
    d = np.ones(cam.shape)
    d[0, 0] = 0
    d[1, 1] = np.nan
    valid = np.ones(cam.shape, bool)
    valid[2, 3] = False
    assert cam.points(d, valid=valid).shape == (9, 3)


def test_presets_load_with_their_stated_fields_of_view():
    assert {"holmlund_thesis", "sr4000", "oak_tof_33d", "epc635"} <= set(list_camera_presets())
    sr = load_camera_preset("sr4000")
    assert (sr.width, sr.height) == (176, 144)
    hfov = 2 * np.degrees(np.arctan(sr.width / 2 / sr.fx))
    vfov = 2 * np.degrees(np.arctan(sr.height / 2 / sr.fy))
    assert hfov == pytest.approx(43.6, abs=0.05) and vfov == pytest.approx(36.4, abs=0.05)
    oak = load_camera_preset("oak_tof_33d")
    assert 2 * np.degrees(np.arctan(320 / oak.fx)) == pytest.approx(70.0, abs=0.05)
    assert 2 * np.degrees(np.arctan(240 / oak.fy)) == pytest.approx(54.7, abs=0.05)
    assert oak.extra["freq_hz"] == [80e6, 100e6]
    th = load_camera_preset("holmlund_thesis")
    assert (th.width, th.height, th.pixel_pitch_m, th.extra["freq_hz"]) == (160, 120, 24e-6, [44e6])
    epc = load_camera_preset("epc635")
    assert (epc.width, epc.height) == (160, 60)


def test_camera_errors_name_field():
    with pytest.raises(InputFileError, match="field 'fx'"):
        CameraModel.from_dict({"width": 4, "height": 3, "fy": 1, "cx": 1, "cy": 1}, source="x.yaml")
    with pytest.raises(InputFileError, match="dist"):
        CameraModel.from_dict({"width": 4, "height": 3, "fx": 1, "fy": 1, "cx": 1, "cy": 1, "dist": [1, 2]})
    with pytest.raises(InputFileError, match="no such camera preset"):
        load_camera_preset("nonexistent_camera")


def test_json_round_trip():
    assert CameraModel.from_json(DISTORTED.to_json()) == DISTORTED
