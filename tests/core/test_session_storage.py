"""Compact raw-tap storage: the device's integer type, shuffle + gzip per frame chunk, exact
float values back, older layouts read as before, and a SIGKILL still keeps every frame."""

from __future__ import annotations

import textwrap
from pathlib import Path

import h5py
import numpy as np
import pytest

from tests.core.killed_writer import write_until_killed
from tofhil.camera import CameraModel
from tofhil.frames import RawFrame
from tofhil.session import SessionWriter, open_session

CAM = CameraModel(width=16, height=12, fx=14.0, fy=14.0, cx=7.5, cy=5.5, name="t")
THETA = np.radians([0.0, 90.0, 180.0, 270.0])


def int_taps(seq: int, dtype: str = "int16") -> np.ndarray:
    """12-bit differential taps (-2048..2047) as a TOFcam635 delivers them."""
    rng = np.random.default_rng(seq)
    return rng.integers(-2048, 2048, (1, 4) + CAM.shape).astype(dtype)


def frame(taps: np.ndarray, seq: int = 0) -> RawFrame:
    return RawFrame(taps=taps, freq_hz=[20e6], theta_rad=THETA, integration_time_s=3e-4, camera=CAM,
                    timestamp_s=0.1 * seq, sequence=seq)


def test_integer_taps_are_stored_in_their_type_compressed_per_frame(tmp_path):
    path = tmp_path / "s.h5"
    taps = [int_taps(i) for i in range(4)]
    with SessionWriter(path, CAM) as w:
        for i, t in enumerate(taps):
            w.append(frame(t, i))
    with h5py.File(path, "r") as f:
        ds = f["raw/taps"]
        assert ds.dtype == np.int16 and ds.chunks == (1, 1, 4) + CAM.shape
        assert ds.compression == "gzip" and ds.shuffle and ds.maxshape[0] is None
        # only filters every HDF5 library has built in (MATLAB, h5py, HDFView): deflate, shuffle
        assert set(ds._filters) == {"gzip", "shuffle"}
        # uniform 12-bit noise has 12 bits of entropy in 16: the filters win back part of the 4
        # unused bits (real taps, far from uniform, shrink ~3.7x: benchmarks/bench_session_storage.py)
        assert ds.id.get_storage_size() < 0.95 * 4 * ds[0].nbytes
    with open_session(path) as s:
        assert s.stored_tap_dtype == np.int16
        for i, t in enumerate(taps):
            back = s.raw_frame(i).taps
            assert back.dtype == np.float32                             # readers: floats, as before
            np.testing.assert_array_equal(back, t.astype(np.float32))   # exactly the device's values


@pytest.mark.parametrize("dtype", ["uint16", "uint8", "int32"])
def test_other_integer_types_keep_their_type_and_read_exactly(tmp_path, dtype):
    path = tmp_path / "u.h5"
    t = int_taps(1, "int32") + (2048 if dtype.startswith("u") else 0)
    t = (t // 16 if dtype == "uint8" else t * 1000 if dtype == "int32" else t).astype(dtype)
    with SessionWriter(path, CAM) as w:
        w.append(frame(t))
    with open_session(path) as s:
        assert s.stored_tap_dtype == np.dtype(dtype)
        back = s.raw_frame(0).taps
        np.testing.assert_array_equal(back, t.astype(np.float64))
        assert back.dtype == (np.float64 if dtype == "int32" else np.float32)   # each value exact


def test_float_taps_stay_float32_and_the_old_layout_is_still_written_on_request(tmp_path):
    rng = np.random.default_rng(0)
    t = (rng.normal(0, 300, (1, 4) + CAM.shape)).astype(np.float32)
    with SessionWriter(tmp_path / "f.h5", CAM) as w:
        w.append(frame(t))
    with SessionWriter(tmp_path / "old.h5", CAM, tap_storage="float32") as w:
        w.append(frame(int_taps(0)))
    with h5py.File(tmp_path / "f.h5", "r") as f:
        assert f["raw/taps"].dtype == np.float32 and f["raw/taps"].compression == "gzip"
    with h5py.File(tmp_path / "old.h5", "r") as f:
        assert f["raw/taps"].dtype == np.float32 and f["raw/taps"].compression is None
    with open_session(tmp_path / "f.h5") as s:
        np.testing.assert_array_equal(s.raw_frame(0).taps, t)
    with open_session(tmp_path / "old.h5") as s:
        np.testing.assert_array_equal(s.raw_frame(0).taps, int_taps(0).astype(np.float32))


def test_files_written_before_read_as_before(tmp_path):
    """float32 taps, contiguous (unchunked) and chunked without filters, as older tofhil and
    other tools write them: the same float32 values back."""
    t = np.stack([int_taps(i).astype(np.float32) for i in range(3)])
    for layout in ("contiguous", "chunked"):
        path = tmp_path / f"{layout}.h5"
        with SessionWriter(path, CAM, tap_storage="float32") as w:
            for i in range(3):
                w.append(frame(t[i], i))
        with h5py.File(path, "r+") as f:
            del f["raw/taps"]
            if layout == "contiguous":
                f["raw/taps"] = t
            else:
                f.create_dataset("raw/taps", data=t, chunks=(1,) + t.shape[1:], maxshape=(None,) + t.shape[1:])
        with open_session(path) as s:
            assert s.n_frames == 3
            for i in range(3):
                got = s.raw_frame(i).taps
                assert got.dtype == np.float32
                np.testing.assert_array_equal(got, t[i])


def test_an_integer_store_refuses_taps_it_would_round(tmp_path):
    with SessionWriter(tmp_path / "a.h5", CAM, tap_dtype="int16") as w:
        w.append(frame(int_taps(0).astype(np.float32)))        # exact integers as floats: fine
        with pytest.raises(ValueError, match=r"frame 1: raw taps are not int16 integers"):
            w.append(frame(int_taps(1).astype(np.float32) + 0.5, 1))
        with pytest.raises(ValueError, match=r"frame 1: raw taps are not int16"):
            w.append(frame(int_taps(1).astype(np.int32) * 100, 1))
        assert w.n_frames == 1
    with open_session(tmp_path / "a.h5") as s:
        assert s.n_frames == 1 and s.stored_tap_dtype == np.int16
    with pytest.raises(ValueError, match="tap_storage"):
        SessionWriter(tmp_path / "b.h5", CAM, tap_storage="lzf")


def test_copies_keep_an_integer_store(tmp_path, tofhil_cli):
    """`tofhil depth` and `tofhil import` of a session copy its taps as stored (int16), not as
    the reader's floats."""
    src = tmp_path / "src.h5"
    with SessionWriter(src, CAM) as w:
        for i in range(2):
            w.append(frame(int_taps(i), i))
    r = tofhil_cli("depth", src, "--out", tmp_path / "d.h5")
    assert r.returncode == 0, r.stderr
    r = tofhil_cli("import", src, "--out", tmp_path / "i.h5")
    assert r.returncode == 0, r.stderr
    for name in ("d.h5", "i.h5"):
        with open_session(tmp_path / name) as s:
            assert s.stored_tap_dtype == np.int16
            np.testing.assert_array_equal(s.raw_frame(1).taps, int_taps(1).astype(np.float32))


WRITER = textwrap.dedent("""
    import sys, numpy as np
    sys.path.insert(0, {tests!r})
    from test_session_storage import frame, int_taps, CAM
    from tofhil.session import SessionWriter
    with SessionWriter({path!r}, CAM, device={{"model": "kill-test"}}) as w:
        i = 0
        while True:
            w.append(frame(int_taps(i), i))
            print(i, flush=True)  # frame i is complete
            i += 1
""")


@pytest.mark.parametrize("attempt", range(3))
def test_sigkill_mid_compact_session_keeps_every_completed_frame(tmp_path, attempt):
    path = tmp_path / "killed.h5"
    code = WRITER.format(tests=str(Path(__file__).parent), path=str(path))
    completed = write_until_killed(code, attempt)
    with open_session(path) as s:
        assert s.n_frames >= completed + 1 and s.stored_tap_dtype == np.int16
        for i in range(s.n_frames):
            raw = s.raw_frame(i)
            assert raw.sequence == i
            np.testing.assert_array_equal(raw.taps, int_taps(i).astype(np.float32))
