"""ADI ToF SDK captures: decoding, units, depth kind and camera, checked against physics."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from tofhil.camera import CameraModel, load_camera_preset
from tofhil.drivers.importers.adi import read_adi_interleaved, read_adi_pair
from tofhil.drivers.importers.dispatch import detect_format, import_file
from tofhil.errors import InputFileError
from tofhil.session import open_session

from tests.real_data import ADI, need


def robust_plane_rms(points: np.ndarray, keep: float = 80.0, rounds: int = 5) -> float:
    """RMS distance to a plane fitted to the best ``keep`` % of the points (cable excluded)."""
    points = points[::4]  # every 4th point: ~65k points fit the same plane, 4x faster
    mask = np.ones(len(points), bool)
    for _ in range(rounds):
        c = points[mask].mean(axis=0)
        n = np.linalg.svd(points[mask] - c, full_matrices=False)[2][2]
        r = (points - c) @ n
        mask = np.abs(r) <= np.percentile(np.abs(r), keep)
    return float(np.sqrt(np.mean(r[mask] ** 2)))


def test_interleaved_decoder_matches_the_documented_byte_layout():
    path = need(ADI / "frame_mode2.bin")
    frame = read_adi_interleaved(path)[0]
    assert frame.depth_mm.shape == frame.amplitude.shape == frame.confidence.shape == (512, 512)
    raw = path.read_bytes()
    rng = np.random.default_rng(0)
    for idx in rng.integers(0, 512 * 512, 200):
        # ADI visualize_interleaved: depth uint16 LE, confidence uint8, AB uint16 LE per pixel.
        d, c, ab = struct.unpack("<HBH", raw[5 * idx:5 * idx + 5])
        r, col = divmod(int(idx), 512)
        assert (frame.depth_mm[r, col], frame.confidence[r, col], frame.amplitude[r, col]) == (d, c, ab)


def test_mode_frames_have_office_scale_depths():
    mode2 = read_adi_interleaved(need(ADI / "frame_mode2.bin"))[0]
    mode3 = read_adi_interleaved(need(ADI / "frame_mode3.bin"))[0]
    med2 = np.median(mode2.depth_mm[mode2.depth_mm > 0]) / 1000
    med3 = np.median(mode3.depth_mm[mode3.depth_mm > 0]) / 1000
    assert 1.72 < med2 < 1.82  # README: depth median about 1.77 m
    assert 0.4 < med3 < 4.0    # ADTF3175 operating range 0.4 to 4 m
    # An office seen by a lit sensor: most pixels measure something.
    assert (mode2.depth_mm > 0).mean() > 0.8 and (mode3.depth_mm > 0).mean() > 0.8


def test_near_plane_depth_range_matches_the_readme():
    f = read_adi_pair(need(ADI / "near_plane_depth.bin"), need(ADI / "near_plane_ir.bin"))
    d = f.depth_mm[f.depth_mm > 0] / 1000
    lo, hi = np.percentile(d, [5, 95])
    assert 0.29 < lo < 0.33 and 0.40 < hi < 0.44  # README: about 0.31 to 0.42 m


def test_near_plane_is_flat_only_as_radial_depth_with_the_assumed_field_of_view():
    f = read_adi_pair(need(ADI / "near_plane_depth.bin"), need(ADI / "near_plane_ir.bin"))
    d = f.depth_mm / 1000.0
    valid = f.depth_mm > 0
    cam = load_camera_preset("adi_adtf3175_qmp")
    radial = robust_plane_rms(cam.points(d, "radial", valid))
    as_z = robust_plane_rms(cam.points(d, "z", valid))
    assert radial < 0.004          # a real plane: a few mm of noise
    assert as_z > 3 * radial       # read as z-depth the plane bends (depth / cos(angle) is missing)
    for hfov in (55.0, 95.0):      # a wrong field of view bends it too
        other = CameraModel.from_fov(512, 512, hfov)
        assert robust_plane_rms(other.points(d, "radial", valid)) > 1.5 * radial


def test_import_writes_radial_metres_amplitude_and_validity(tmp_path):
    src = need(ADI / "frame_mode3.bin")
    assert detect_format(src) == "adi-interleaved"
    res = import_file(src, tmp_path / "s.h5")
    frame = read_adi_interleaved(src)[0]
    with open_session(res.out) as s:
        assert s.n_frames == 1 and s.has_depth and not s.has_raw
        assert s.camera.name == "adi_adtf3175_qmp"
        assert s.device["depth_kind_in_file"] == "radial" and len(s.device["source_sha256"]) == 64
        d = s.depth_frame(0)
    valid = frame.depth_mm > 0
    np.testing.assert_array_equal(d.valid, valid)
    np.testing.assert_allclose(d.radial_m[valid], frame.depth_mm[valid] / 1000.0, rtol=1e-6)
    np.testing.assert_array_equal(d.amplitude, frame.amplitude.astype(np.float32))


def test_pair_import_finds_the_ir_partner_and_honours_camera_override(tmp_path):
    src = need(ADI / "near_plane_depth.bin")
    assert detect_format(src) == "adi-pair"
    yaml_cam = tmp_path / "cam.yaml"
    yaml_cam.write_text("name: mine\nwidth: 512\nheight: 512\nhfov_deg: 70\n")
    res = import_file(src, tmp_path / "s.h5", camera=str(yaml_cam))
    with open_session(res.out) as s:
        assert s.camera.name == "mine" and s.device["source_ir_file"].endswith("near_plane_ir.bin")
        ir = np.fromfile(ADI / "near_plane_ir.bin", "<u2").reshape(512, 512)
        np.testing.assert_array_equal(s.depth_frame(0).amplitude, ir.astype(np.float32))
    with pytest.raises(InputFileError, match="image size 512x512"):
        import_file(src, tmp_path / "t.h5", camera="epc635")


def test_bad_adi_files_are_named_with_what_was_expected(tmp_path):
    bad = tmp_path / "frame.bin"
    bad.write_bytes(b"\0" * (512 * 512 * 5 - 7))
    with pytest.raises(InputFileError, match="format not recognised"):
        detect_format(bad)
    with pytest.raises(InputFileError) as e:
        read_adi_interleaved(bad)
    assert str(bad) in str(e.value) and "multiple of 1310720" in str(e.value)
    depth = tmp_path / "x_depth_0.bin"
    depth.write_bytes(b"\0" * 512 * 512 * 2)
    with pytest.raises(InputFileError, match="no matching IR image"):
        import_file(depth, tmp_path / "o.h5")
    (tmp_path / "x_ir_0.bin").write_bytes(b"\0" * 100)
    with pytest.raises(InputFileError, match="IR image.*524288"):
        import_file(depth, tmp_path / "o.h5")
    assert not (tmp_path / "o.h5").exists()


def test_multi_frame_interleaved_files_import_frame_by_frame(tmp_path):
    a, b = need(ADI / "frame_mode2.bin"), need(ADI / "frame_mode3.bin")
    both = tmp_path / "two_frames.bin"
    both.write_bytes(a.read_bytes() + b.read_bytes())
    res = import_file(both, tmp_path / "two.h5")
    assert res.n_frames == 2
    with open_session(res.out) as s:
        for i, src in enumerate((a, b)):
            ref = read_adi_interleaved(src)[0]
            d = s.depth_frame(i)
            assert d.sequence == i
            np.testing.assert_array_equal(d.amplitude, ref.amplitude.astype(np.float32))
            np.testing.assert_array_equal(d.valid, ref.depth_mm > 0)


def test_confidence_threshold_is_opt_in(tmp_path):
    src = need(ADI / "frame_mode2.bin")
    frame = read_adi_interleaved(src)[0]
    res = import_file(src, tmp_path / "c.h5", adi_max_confidence=5)
    with open_session(res.out) as s:
        assert s.device["adi_max_confidence"] == 5
        valid = s.depth_frame(0).valid
    np.testing.assert_array_equal(valid, (frame.depth_mm > 0) & (frame.confidence <= 5))
    assert valid.sum() < (frame.depth_mm > 0).sum()


def test_import_keeps_the_confidence_byte_and_stores_validity_as_booleans(tmp_path):
    """What the device gives is kept: the interleaved frame's confidence byte becomes
    depth/confidence (byte for byte), depth/valid is a boolean dataset; a pair (no
    confidence in the format) has no depth/confidence."""
    import h5py

    src = need(ADI / "frame_mode2.bin")
    frame = read_adi_interleaved(src)[0]
    res = import_file(src, tmp_path / "c.h5")
    with h5py.File(res.out, "r") as f:
        assert f["depth/valid"].dtype == np.bool_
        assert "depth/confidence" in f
    with open_session(res.out) as s:
        conf = s.depth_frame(0).confidence
    np.testing.assert_array_equal(conf, frame.confidence.astype(np.float32))
    assert conf.max() > conf.min()  # the real byte varies over the office frame
    pair = import_file(need(ADI / "near_plane_depth.bin"), tmp_path / "p.h5")
    with open_session(pair.out) as s:
        assert s.depth_frame(0).confidence is None
