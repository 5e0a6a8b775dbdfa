"""``tofhil import`` on the command line, session copy, and the replay driver."""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tofhil.drivers.base import DeviceError, open_device
from tofhil.drivers.importers.dispatch import import_file
from tofhil.errors import InputFileError
from tofhil.session import open_session

from tests.real_data import REAL, need


def cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "tofhil.cli", *map(str, args)], capture_output=True,
                          text=True, timeout=120)


def digest(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


def test_cli_imports_and_refuses_to_overwrite(tmp_path):
    src = need(REAL / "adi_tof" / "near_plane_ir.bin")  # the IR half: its depth partner is found
    out = tmp_path / "near.h5"
    r = cli("import", src, "--out", out)
    assert r.returncode == 0, r.stderr
    assert "adi-pair" in r.stdout and "assumed preset" in r.stdout
    before = digest(out)
    r = cli("import", src, "--out", out)
    assert r.returncode == 2 and "already exists" in r.stderr and "--force" in r.stderr
    assert "Traceback" not in r.stderr and digest(out) == before
    r = cli("import", src, "--out", out, "--force", "--camera", "oak_tof_33d")
    assert r.returncode == 2 and "--camera" in r.stderr and "512x512" in r.stderr
    assert digest(out) == before  # a failed --force import leaves the old file alone
    r = cli("import", tmp_path / "missing.bin", "--out", tmp_path / "x.h5")
    assert r.returncode == 2 and "no such file" in r.stderr


def test_cli_unknown_content_is_a_clear_error(tmp_path):
    junk = tmp_path / "junk.dat"
    junk.write_bytes(os.urandom(1000))
    r = cli("import", junk, "--out", tmp_path / "j.h5")
    assert r.returncode == 2 and "format not recognised" in r.stderr and "expected" in r.stderr
    assert not (tmp_path / "j.h5").exists()
    assert not list(tmp_path.glob("*.partial"))


def test_session_import_copies_every_complete_frame(tmp_path):
    src = need(REAL / "adi_tof" / "frame_mode2.bin")
    first = import_file(src, tmp_path / "a.h5").out
    copy = import_file(first, tmp_path / "b.h5")
    assert copy.format == "session"
    with open_session(first) as a, open_session(copy.out) as b:
        assert b.n_frames == a.n_frames and b.camera == a.camera
        assert b.device["imported_from"]["format"] == "session"
        np.testing.assert_array_equal(a.depth_frame(0).radial_m, b.depth_frame(0).radial_m)
        np.testing.assert_array_equal(a.depth_frame(0).valid, b.depth_frame(0).valid)
    with pytest.raises(InputFileError, match="must differ"):
        import_file(first, first, force=True)


def test_replay_streams_the_recorded_frames_with_their_timestamps(tmp_path):
    src = need(REAL / "azure_kinect" / "recording.mkv")
    sess = import_file(src, tmp_path / "k.h5").out
    with open_session(sess) as s:
        recorded = s.depth_frame(0)
    with open_device(f"replay:{sess}") as dev:
        dev.configure(mode="distance")
        frames = list(dev.stream(1))
        assert dev.info().model == "Azure Kinect DK"
        with pytest.raises(DeviceError, match="end of session"):
            dev.read_frame()
    f = frames[0]
    assert f.timestamp_s == recorded.timestamp_s and f.sequence == recorded.sequence
    np.testing.assert_array_equal(f.depth.radial_m, recorded.radial_m)
    with open_device(f"replay:{sess}?loop=1") as dev:
        looped = list(dev.stream(3))
    assert [x.sequence for x in looped] == [0, 1, 2]
    assert all(b.timestamp_s > a.timestamp_s for a, b in zip(looped, looped[1:]))
    with pytest.raises(InputFileError, match="no such file"):
        open_device(f"replay:{tmp_path / 'nope.h5'}")
    with pytest.raises(DeviceError, match="no raw taps"):
        with open_device(f"replay:{sess}") as dev:
            dev.configure(mode="dcs")


def _raw_plane_session(path: Path, d0: float = 0.8) -> Path:
    """Raw taps of a fronto-parallel plane at d0 (closed-form phase), as another tool would write."""
    from tofhil.camera import load_camera_preset
    from tofhil.demod import distance_to_phase, equally_spaced_phases, taps_from_signal
    from tofhil.frames import RawFrame
    from tofhil.session import SessionWriter

    cam = load_camera_preset("epc635")
    theta = equally_spaced_phases(4)
    radial = d0 / cam.ray_z
    with SessionWriter(path, cam, device={"model": "test"}, scene_text="name: plane\n") as w:
        for i in range(3):
            taps = taps_from_signal(np.full(cam.shape, 500.0), distance_to_phase(radial, 20e6),
                                    np.full(cam.shape, 1000.0), theta)[None]
            w.append(raw=RawFrame(taps=taps, freq_hz=[20e6], theta_rad=theta, integration_time_s=1e-3,
                                  camera=cam, timestamp_s=5.0 + 0.1 * i, sequence=10 + i))
    return path


def test_raw_sessions_copy_and_replay_as_taps_or_demodulated_depth(tmp_path):
    src = _raw_plane_session(tmp_path / "raw.h5")
    copy = import_file(src, tmp_path / "copy.h5")
    with open_session(src) as a, open_session(copy.out) as b:
        assert b.has_raw and b.n_frames == 3 and b.scene_text == a.scene_text
        np.testing.assert_array_equal(a.raw_frame(2).taps, b.raw_frame(2).taps)
    with open_device(f"replay:{src}") as dev:
        dev.configure(mode="dcs")
        raw = [f.raw for f in dev.stream(3)]
    assert [r.sequence for r in raw] == [10, 11, 12] and raw[1].timestamp_s == pytest.approx(5.1)
    with open_device(f"replay:{src}") as dev:
        dev.configure(mode="distance")
        depth = next(iter(dev.stream(1))).depth
    # Demodulated from the taps: the plane's closed-form radial distance.
    np.testing.assert_allclose(depth.radial_m, 0.8 / depth.camera.ray_z, atol=1e-4)


def test_a_session_cut_short_is_repaired_by_import(tmp_path):
    import h5py

    src = _raw_plane_session(tmp_path / "raw.h5")
    with h5py.File(src, "r+") as f:  # as if the writer died after frame 2's data, before its count
        f.attrs["n_frames"] = 2
    res = import_file(src, tmp_path / "fixed.h5")
    assert res.n_frames == 2 and any("partly written" in n for n in res.notes)
    with open_session(res.out) as s:
        assert s.n_frames == 2 and s.dataset_lengths["raw/taps"] == 2
