"""Azure Kinect recording: Matroska reading, byte order, lens model, z -> radial, bad files."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from tofhil.drivers.importers.k4a import read_k4a_recording
from tofhil.drivers.importers.dispatch import detect_format, import_file
from tofhil.drivers.importers.mkv import open_mkv
from tofhil.errors import InputFileError
from tofhil.session import open_session

from tests.real_data import AZURE_KINECT_MKV, need


@pytest.fixture(scope="module")
def mkv_path() -> Path:
    return need(AZURE_KINECT_MKV)


@pytest.fixture(scope="module")
def rec(mkv_path):
    return read_k4a_recording(mkv_path)


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(np.dot(a, b), -1.0, 1.0))))


def test_tracks_and_attachment_are_found(mkv_path):
    with open_mkv(mkv_path) as m:
        names = {t.name: t for t in m.tracks.values()}
        assert {"DEPTH", "IR", "COLOR"} <= set(names)
        assert (names["DEPTH"].width, names["DEPTH"].height, names["DEPTH"].fourcc) == (640, 576, "b16g")
        assert "calibration.json" in m.attachments and not m.truncated


def test_depth_and_ir_are_big_endian(rec):
    _, z_mm, ir = rec.frames[0]
    a = z_mm.astype(float)
    both = (z_mm[:, 1:] > 0) & (z_mm[:, :-1] > 0)
    step = np.median(np.abs(np.diff(a, axis=1))[both])
    swapped = z_mm.byteswap().astype(float)
    step_swapped = np.median(np.abs(np.diff(swapped, axis=1))[both])
    # Surfaces are smooth: neighbours differ by millimetres, not by multiples of 256 mm.
    assert step <= 5 and step_swapped >= 100
    assert 0.3 < np.median(a[z_mm > 0]) / 1000 < 4.0   # a table-top scene, NFOV range 0.5-3.86 m
    assert ir.max() == 65535                            # README: the mug saturates the IR


def test_camera_field_of_view_matches_the_nfov_specification(rec):
    cam = rec.camera
    left = cam.pixel_rays(np.array(-0.5), np.array(cam.cy))
    right = cam.pixel_rays(np.array(cam.width - 0.5), np.array(cam.cy))
    top = cam.pixel_rays(np.array(cam.cx), np.array(-0.5))
    bottom = cam.pixel_rays(np.array(cam.cx), np.array(cam.height - 0.5))
    # Azure Kinect DK hardware specification: NFOV unbinned 640x576, 75 x 65 deg.
    assert abs(angle_deg(left, right) - 75.0) < 3.0
    assert abs(angle_deg(top, bottom) - 65.0) < 3.0


def test_refit_lens_model_reprojects_onto_the_factory_model(rec):
    """The 5-parameter model's rays (inverted by the core) land on the same pixel under the
    factory rational model, over the pixels that see anything."""
    cam, intr = rec.camera, rec.intrinsics
    _, z_mm, _ = rec.frames[0]
    v, u = np.nonzero(z_mm > 0)
    sel = slice(None, None, 7)
    u, v = u[sel].astype(float), v[sel].astype(float)
    r = cam.pixel_rays(u, v)
    xd, yd = intr.distort(r[:, 0] / r[:, 2], r[:, 1] / r[:, 2])
    err = np.hypot(xd * intr.fx + intr.cx - u, yd * intr.fy + intr.cy - v)
    assert err.max() < 1.0 and np.sqrt(np.mean(err ** 2)) < 0.1
    assert rec.fit.max_residual_px < 1.0


def test_session_stores_radial_distance_that_projects_back_to_the_recorded_z(rec, tmp_path, mkv_path):
    res = import_file(mkv_path, tmp_path / "k4a.h5")
    assert res.format == "k4a-mkv"
    _, z_mm, ir = rec.frames[0]
    with open_session(res.out) as s:
        d = s.depth_frame(0)
        assert s.device["depth_kind_in_file"] == "z" and s.device["serial"]
        assert s.camera.shape == (576, 640)
        np.testing.assert_array_equal(d.amplitude, ir.astype(np.float32))
        np.testing.assert_array_equal(d.valid, z_mm > 0)
    valid = d.valid
    # radial >= z everywhere (a ray is never shorter than its z component) ...
    assert np.all(d.radial_m[valid] >= z_mm[valid] / 1000.0 - 1e-6)
    # ... and the point along the stored camera's ray has the recorded z (within the lens refit).
    z_back = d.z_m[valid]
    assert np.max(np.abs(z_back - z_mm[valid] / 1000.0)) < 0.003
    # At the principal point radial and z agree.
    r0, c0 = int(round(s.camera.cy)), int(round(s.camera.cx))
    if valid[r0, c0]:
        assert abs(d.radial_m[r0, c0] - z_mm[r0, c0] / 1000.0) < 1e-4


def test_original_calibration_is_kept_verbatim(rec, tmp_path, mkv_path):
    # Find the attachment without the EBML reader: it is the JSON object in the file.
    blob = mkv_path.read_bytes()
    start = blob.index(b'{\n    "CalibrationInformation"') if b'{\n    "CalibrationInformation"' in blob \
        else blob.index(b'"CalibrationInformation"') - 1
    calib, _ = json.JSONDecoder().raw_decode(blob[start:].decode("latin-1"))
    res = import_file(mkv_path, tmp_path / "k.h5")
    with open_session(res.out) as s:
        assert s.device["k4a_calibration"] == calib
        assert s.device["camera_fit"]["max_residual_px"] < 1.0


def test_truncated_recording_is_refused_unless_salvaged(mkv_path, tmp_path):
    data = mkv_path.read_bytes()
    cut = tmp_path / "cut.mkv"
    cut.write_bytes(data[:1_200_000])          # inside the IR block, after the depth block
    assert detect_format(cut) == "k4a-mkv"
    with pytest.raises(InputFileError, match="truncated.*--salvage"):
        import_file(cut, tmp_path / "a.h5")
    assert not (tmp_path / "a.h5").exists()
    res = import_file(cut, tmp_path / "a.h5", salvage=True)
    with open_session(res.out) as s:
        assert s.n_frames == 1 and np.all(np.isnan(s.depth_frame(0).amplitude))
    cut.write_bytes(data[:500_000])            # inside the depth block: nothing complete
    with pytest.raises(InputFileError, match="no complete depth frame"):
        read_k4a_recording(cut, salvage=True)


def test_bad_calibration_names_the_field(mkv_path, tmp_path):
    data = mkv_path.read_bytes()
    bad = data.replace(b"CALIBRATION_LensDistortionModelBrownConrady",
                       b"CALIBRATION_LensDistortionModelXXXXXXXXXXXX", 1)
    p = tmp_path / "bad.mkv"
    p.write_bytes(bad)
    with pytest.raises(InputFileError, match="ModelType.*BrownConrady"):
        read_k4a_recording(p)
    p.write_bytes(b"\x1a\x45\xdf\xa3" + b"\x84" + b"\x42\x82\x81x")  # EBML header, DocType "x"
    with pytest.raises(InputFileError, match="DocType"):
        read_k4a_recording(p)


@settings(max_examples=int(os.environ.get("TOFHIL_FUZZ_EXAMPLES", "40")), deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(cut=st.integers(min_value=0, max_value=8000), flip=st.integers(min_value=0, max_value=7999),
       bit=st.integers(min_value=0, max_value=7))
def test_damaged_headers_give_input_errors_not_crashes(mkv_path, tmp_path, cut, flip, bit):
    data = bytearray(mkv_path.read_bytes()[:1_000_000])
    data[flip] ^= 1 << bit
    p = tmp_path / "f.mkv"
    for blob in (bytes(data[:cut]), bytes(data)):
        p.write_bytes(blob)
        try:
            read_k4a_recording(p, salvage=True)
        except InputFileError:
            pass


def test_camera_override_converts_z_with_that_cameras_rays(rec, tmp_path, mkv_path):
    yaml_cam = tmp_path / "k.yaml"
    yaml_cam.write_text("name: flat\nwidth: 640\nheight: 576\nhfov_deg: 75\nvfov_deg: 65\n")
    res = import_file(mkv_path, tmp_path / "o.h5", camera=str(yaml_cam))
    _, z_mm, _ = rec.frames[0]
    with open_session(res.out) as s:
        assert s.camera.name == "flat" and s.device["camera_source"].startswith("--camera")
        d = s.depth_frame(0)
        # Pinhole without distortion: radial = z * sqrt(1 + ((u-cx)/fx)^2 + ((v-cy)/fy)^2).
        v, u = np.mgrid[0:576, 0:640]
        cam = s.camera
        norm = np.sqrt(1 + ((u - cam.cx) / cam.fx) ** 2 + ((v - cam.cy) / cam.fy) ** 2)
        ok = z_mm > 0
        np.testing.assert_allclose(d.radial_m[ok], (z_mm * 1e-3 * norm)[ok], rtol=1e-6)


def _largest_plane(points: np.ndarray, thr: float = 0.01, iters: int = 200) -> tuple[int, float]:
    """RANSAC: inlier count of the largest plane and the RMS of its refitted inliers."""
    rng = np.random.default_rng(0)
    best = np.zeros(len(points), bool)
    for _ in range(iters):
        s = points[rng.choice(len(points), 3, replace=False)]
        n = np.cross(s[1] - s[0], s[2] - s[0])
        if np.linalg.norm(n) < 1e-9:
            continue
        inl = np.abs((points - s[0]) @ (n / np.linalg.norm(n))) < thr
        if inl.sum() > best.sum():
            best = inl
    q = points[best]
    c = q.mean(axis=0)
    n = np.linalg.svd(q - c, full_matrices=False)[2][2]
    return int(best.sum()), float(np.sqrt(np.mean(((q - c) @ n) ** 2)))


def test_walls_are_flatter_with_z_converted_to_radial_than_with_z_read_as_radial(rec):
    """The room's largest plane holds more points, more tightly, when the recorded z-depth is
    converted to radial; reading it as radial already bends planes (depth / cos(angle) missing)."""
    _, z_mm, _ = rec.frames[0]
    radial, valid = rec.radial_m(z_mm)
    right = rec.camera.points(radial, "radial", valid)[::5]
    wrong = rec.camera.points(z_mm / 1000.0, "radial", valid)[::5]
    n_right, rms_right = _largest_plane(right)
    n_wrong, rms_wrong = _largest_plane(wrong)
    assert n_right > 1.2 * n_wrong and rms_right < rms_wrong
