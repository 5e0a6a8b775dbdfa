"""Session files: round trip, files from other tools, crash safety, malformed input, overwrite."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import h5py
import numpy as np
import pytest

from tests.core.killed_writer import write_until_killed
from tofhil.camera import CameraModel
from tofhil.demod import distance_to_phase, equally_spaced_phases, taps_from_signal
from tofhil.depth import depth_from_raw
from tofhil.errors import InputFileError
from tofhil.frames import RawFrame
from tofhil.session import SessionWriter, open_session

CAM = CameraModel(width=16, height=12, fx=14.0, fy=14.0, cx=7.5, cy=5.5, dist=(0.01, 0, 0, 0, 0), name="t")
FREQ = np.array([80e6, 100e6])
THETA = equally_spaced_phases(4)


def make_raw(seq: int, d: float = 2.0) -> RawFrame:
    dist = np.full(CAM.shape, d)
    phase = np.stack([distance_to_phase(dist, f) for f in FREQ])
    taps = taps_from_signal(np.full((2,) + CAM.shape, 80.0), phase, np.full((2,) + CAM.shape, 300.0), THETA)
    return RawFrame(taps=taps.astype(np.float32), freq_hz=FREQ, theta_rad=THETA, integration_time_s=250e-6,
                    camera=CAM, timestamp_s=10.0 + 0.033 * seq, sequence=seq,
                    temperature_c=35.5 if seq % 2 else float("nan"))


def test_round_trip_raw_and_depth(tmp_path):
    path = tmp_path / "s.h5"
    with SessionWriter(path, CAM, device={"model": "unit"}, scene_text="objects: []\n") as w:
        for i in range(3):
            raw = make_raw(i, d=1.0 + i)
            w.append(raw, depth_from_raw(raw))
    with open_session(path) as s:
        assert s.n_frames == 3 and s.has_raw and s.has_depth
        assert s.camera == CAM
        assert s.device == {"model": "unit"}
        assert s.scene_text == "objects: []\n"
        np.testing.assert_array_equal(s.freq_hz, FREQ)
        assert s.integration_time_s == pytest.approx(250e-6)
        for i in range(3):
            raw = s.raw_frame(i)
            np.testing.assert_array_equal(raw.taps, make_raw(i, 1.0 + i).taps)
            assert raw.sequence == i and raw.timestamp_s == pytest.approx(10.0 + 0.033 * i)
            dep = s.depth_frame(i)
            np.testing.assert_allclose(dep.distance_m, 1.0 + i, atol=1e-5)
        assert np.isnan(s.raw_frame(0).temperature_c) and s.raw_frame(1).temperature_c == pytest.approx(35.5)
    # The documented root attributes are there, with the documented types.
    with h5py.File(path, "r") as f:
        assert f.attrs["format"] == "tofhil.session" and int(f.attrs["format_version"]) == 1
        cam = json.loads(f.attrs["camera"])
        assert set(cam) >= {"width", "height", "fx", "fy", "cx", "cy", "dist"} and len(cam["dist"]) == 5
        assert f["raw/taps"].dtype == np.float32 and f["raw/taps"].shape == (3, 2, 4, 12, 16)
        assert f["depth/valid"].dtype == np.bool_  # booleans, as documented


def test_file_written_by_plain_h5py_reads(tmp_path):
    """A file another tool wrote following docs/session-format.md, with nothing of ours."""
    path = tmp_path / "other.h5"
    n = 2
    d_true = 1.7
    phase = distance_to_phase(np.full((12, 16), d_true), 44e6)
    taps = np.stack([500 + 100 * np.cos(phase - t) for t in THETA])[None]  # [F=1, K, H, W]
    with h5py.File(path, "w") as f:
        f.attrs["format"] = "tofhil.session"
        f.attrs["format_version"] = 1
        f.attrs["created_utc"] = "2026-01-01T00:00:00+00:00"
        f.attrs["software_version"] = "matlab-writer 0.1"
        f.attrs["device"] = json.dumps({"model": "other"})
        f.attrs["camera"] = json.dumps({"width": 16, "height": 12, "fx": 14, "fy": 14, "cx": 7.5,
                                        "cy": 5.5, "dist": [0, 0, 0, 0, 0]})
        f.attrs["scene"] = ""
        f["raw/taps"] = np.repeat(taps[None], n, axis=0).astype(np.float32)
        f["raw/freq_hz"] = np.array([44e6])
        f["raw/theta_rad"] = THETA
        f["raw"].attrs["integration_time_s"] = 1e-3
        f["frames/timestamp_s"] = np.arange(n, dtype=float)
        f["frames/sequence"] = np.arange(n, dtype=np.int64)
        f["frames/temperature_c"] = np.full(n, np.nan, dtype=np.float32)
    with open_session(path) as s:
        assert s.n_frames == n
        dep = depth_from_raw(s.raw_frame(1))
        np.testing.assert_allclose(dep.distance_m, d_true, atol=1e-4)


WRITER = textwrap.dedent("""
    import sys, numpy as np
    sys.path.insert(0, {tests!r})
    from test_session import make_raw, CAM
    from tofhil.session import SessionWriter
    with SessionWriter({path!r}, CAM, device={{"model": "kill-test"}}) as w:
        i = 0
        while True:
            w.append(make_raw(i))
            print(i, flush=True)  # frame i is complete
            i += 1
""")


@pytest.mark.parametrize("attempt", range(3))
def test_sigkill_mid_session_keeps_every_completed_frame(tmp_path, attempt):
    path = tmp_path / "killed.h5"
    code = WRITER.format(tests=str(Path(__file__).parent), path=str(path))
    completed = write_until_killed(code, attempt)
    with open_session(path) as s:
        assert s.n_frames >= completed + 1
        for i in range(s.n_frames):
            raw = s.raw_frame(i)
            assert raw.sequence == i
            np.testing.assert_array_equal(raw.taps, make_raw(i).taps)


def test_refuses_to_overwrite(tmp_path):
    path = tmp_path / "s.h5"
    path.write_bytes(b"precious recording")
    with pytest.raises(InputFileError, match="refusing to overwrite"):
        SessionWriter(path, CAM)
    assert path.read_bytes() == b"precious recording"
    with SessionWriter(path, CAM, force=True) as w:
        w.append(make_raw(0))
    assert open_session(path).n_frames == 1


def _write_minimal(path: Path, drop: str | None = None, **changes) -> None:
    with SessionWriter(path, CAM, force=True) as w:
        w.append(make_raw(0))
    with h5py.File(path, "a") as f:
        if drop:
            if drop in f:
                del f[drop]
            else:
                del f.attrs[drop]
        for k, v in changes.items():
            f.attrs[k] = v


@pytest.mark.parametrize("drop,changes,field", [
    ("camera", {}, "camera"),
    (None, {"camera": '{"width": 16, "height": 12, "fx": 14}'}, "fy"),
    (None, {"camera": "not json"}, "camera"),
    (None, {"format": "something.else"}, "format"),
    ("format_version", {}, "format_version"),
    ("raw/theta_rad", {}, "raw/theta_rad"),
    ("frames/sequence", {}, "frames/sequence"),
    (None, {"camera": json.dumps({"width": 20, "height": 12, "fx": 14, "fy": 14, "cx": 7.5, "cy": 5.5,
                                  "dist": [0, 0, 0, 0, 0]})}, "raw/taps"),
])
def test_malformed_file_names_file_and_field(tmp_path, drop, changes, field):
    path = tmp_path / "bad.h5"
    _write_minimal(path, drop, **changes)
    with pytest.raises(InputFileError) as exc:
        open_session(path)
    msg = str(exc.value)
    assert str(path) in msg and field in msg and "expected" in msg


def test_not_hdf5_and_missing(tmp_path):
    p = tmp_path / "x.h5"
    p.write_text("hello")
    with pytest.raises(InputFileError, match="HDF5"):
        open_session(p)
    with pytest.raises(InputFileError, match="no such file"):
        open_session(tmp_path / "missing.h5")


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "tofhil.cli", *args], capture_output=True, text=True, timeout=120)


def test_cli_info_and_depth(tmp_path):
    src = tmp_path / "raw.h5"
    with SessionWriter(src, CAM, device={"model": "unit"}) as w:
        for i in range(2):
            w.append(make_raw(i, d=5.5))
    r = _cli("info", str(src))
    assert r.returncode == 0, r.stderr
    assert "80000000.0" in r.stdout and "raw/taps" in r.stdout
    out = tmp_path / "depth.h5"
    r = _cli("depth", str(src), "--out", str(out))
    assert r.returncode == 0, r.stderr
    with open_session(out) as s:
        assert s.has_depth and s.n_frames == 2
        # 5.5 m is beyond both wrap ranges (1.87 m, 1.50 m): only unwrapping gets it right.
        np.testing.assert_allclose(s.depth_frame(1).distance_m, 5.5, atol=1e-4)
    # refusing to overwrite: exit 2, one message, no traceback
    r = _cli("depth", str(src), "--out", str(out))
    assert r.returncode == 2
    assert "refusing to overwrite" in r.stderr and "Traceback" not in r.stderr
    r = _cli("info", str(tmp_path / "nope.h5"))
    assert r.returncode == 2 and "no such file" in r.stderr and "Traceback" not in r.stderr
    r = _cli("--version")
    assert r.returncode == 0 and "tofhil" in r.stdout
