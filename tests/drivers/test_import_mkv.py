"""The Matroska reader (PyAV, FFmpeg's demuxer) on the real Azure Kinect recording and on
files damaged or written from it: what it lists, what it refuses, what it never returns."""

from __future__ import annotations

import fractions
import json
from pathlib import Path

import av
import numpy as np
import pytest

from tofhil.drivers.importers import mkv as M
from tofhil.drivers.importers.k4a import read_k4a_recording
from tofhil.errors import InputFileError, TofhilError

from tests.real_data import AZURE_KINECT_MKV, need


@pytest.fixture(scope="module")
def mkv_path() -> Path:
    return need(AZURE_KINECT_MKV)


@pytest.fixture(scope="module")
def intact(mkv_path) -> dict[tuple[str, int | None], bytes]:
    """Every packet of the intact recording by (track name, pts), read once."""
    with M.open_mkv(mkv_path) as m:
        assert not m.truncated
        return {(m.tracks[b.track].name, b.pts): m.payload(b) for b in m.blocks}


def test_lists_the_k4a_tracks_tags_and_calibration_attachment(mkv_path):
    with M.open_mkv(mkv_path) as m:
        t = {tr.name: tr for tr in m.tracks.values()}
        assert {"COLOR", "DEPTH", "IR", "IMU"} <= set(t)
        assert (t["COLOR"].codec_id, t["COLOR"].width, t["COLOR"].height) == ("mjpeg", 1280, 720)
        for name in ("DEPTH", "IR"):
            assert (t[name].codec_id, t[name].fourcc, t[name].width, t[name].height) == ("rawvideo", "b16g", 640, 576)
            assert t[name].pix_fmt == "gray16be"   # FFmpeg agrees: b16g is 16-bit big-endian grey
        assert m.track_tags[t["DEPTH"].index]["K4A_DEPTH_MODE"] == "NFOV_UNBINNED"
        assert m.track_tags[t["IR"].index]["K4A_IR_MODE"] == "ACTIVE"
        assert m.tags["K4A_DEVICE_SERIAL_NUMBER"] and int(m.tags["K4A_START_OFFSET_NS"]) >= 0
        assert "title" not in m.tags  # Info's title is a header field, not a tag
        calib = json.loads(m.attachments["calibration.json"])
        assert "CalibrationInformation" in calib
        # One capture: a colour, a depth and an IR frame, all stamped with the capture's time.
        frames = {name: m.frames(t[name]) for name in ("COLOR", "DEPTH", "IR")}
        assert [len(f) for f in frames.values()] == [1, 1, 1]
        times = {f[0].time_s for f in frames.values()}
        assert len(times) == 1 and 0 <= times.pop() < 10
        depth = frames["DEPTH"][0]
        assert len(m.payload(depth)) == depth.size == 640 * 576 * 2


def _write_depth_ir(path: Path, src: Path, pts_ms: list[int]) -> None:
    """A recording written by FFmpeg's Matroska muxer: the real depth and IR frames repeated at
    the given times, pixel (0, 0) set to the frame number so that each frame is recognisable."""
    with av.open(str(src)) as inp:
        first = {p.stream.metadata.get("title"): bytes(p) for p in inp.demux() if p.size}
        templates = {s.metadata.get("title"): s for s in inp.streams.video}
        with av.open(str(path), "w", format="matroska", options={"allow_raw_vfw": "1"}) as out:
            streams = {}
            for name in ("DEPTH", "IR"):
                streams[name] = out.add_stream_from_template(templates[name])
                streams[name].metadata["title"] = name
            for k, t in enumerate(pts_ms):
                for name, s in streams.items():
                    img = np.frombuffer(first[name], ">u2").copy()
                    img[0] = k
                    pkt = av.Packet(img.tobytes())
                    pkt.stream, pkt.pts, pkt.dts, pkt.time_base = s, t, t, fractions.Fraction(1, 1000)
                    out.mux(pkt)


@pytest.mark.parametrize("hold_bytes", [M.HOLD_BYTES, 0])
def test_block_times_frame_count_and_random_access(mkv_path, tmp_path, monkeypatch, hold_bytes):
    """Times are the muxed ones, in order; every frame is found again in any order, whether
    its payload was kept from the index pass or is demuxed again (hold_bytes=0: seeks)."""
    monkeypatch.setattr(M, "HOLD_BYTES", hold_bytes)
    pts_ms = [100, 133, 167, 200, 233, 267]
    p = tmp_path / "multi.mkv"
    _write_depth_ir(p, mkv_path, pts_ms)
    with M.open_mkv(p) as m:
        assert not m.truncated
        depth, ir = m.track_by_name("DEPTH"), m.track_by_name("IR")
        for tr in (depth, ir):
            blocks = m.frames(tr)
            assert len(blocks) == len(pts_ms)
            assert [b.time_s for b in blocks] == pytest.approx([t / 1000 for t in pts_ms])
        for k in (5, 0, 3, 3, 1, 4, 2):
            for tr in (depth, ir):
                data = m.payload(m.frames(tr)[k])
                assert len(data) == 640 * 576 * 2 and np.frombuffer(data, ">u2")[0] == k


# Offsets in the real recording (1 699 264 bytes): EBML header, track headers, the colour
# block, the depth block (224 671..961 959), the IR block (..1 699 239), the trailing Cues.
CUTS = [3, 60, 2_000, 7_000, 100_000, 500_000, 961_000, 1_200_000, 1_699_250]


@pytest.mark.parametrize("cut", CUTS)
def test_truncated_copy_is_an_error_naming_the_file_and_never_garbage(mkv_path, tmp_path, intact, cut):
    p = tmp_path / f"cut{cut}.mkv"
    p.write_bytes(mkv_path.read_bytes()[:cut])
    try:
        m = M.open_mkv(p)
    except InputFileError as exc:
        assert str(p) in str(exc) and "Matroska" in str(exc)
    else:
        with m:
            assert m.truncated and str(m.truncation)
            # FFmpeg returns complete blocks only: each one is byte-identical to the intact file's.
            for b in m.blocks:
                assert m.payload(b) == intact[(m.tracks[b.track].name, b.pts)]
    with pytest.raises(InputFileError) as err:  # the importer refuses it (unless salvaging)
        read_k4a_recording(p)
    assert str(p) in str(err.value)


def test_salvage_keeps_the_complete_depth_frame_identical(mkv_path, tmp_path, intact):
    p = tmp_path / "cut.mkv"
    p.write_bytes(mkv_path.read_bytes()[:1_200_000])    # inside the IR block
    with read_k4a_recording(p, salvage=True) as rec:
        assert len(rec) == 1 and "prematurely" in rec.truncated
        _, z, ir = rec.frame(0)
        assert ir is None
        np.testing.assert_array_equal(z, np.frombuffer(intact[("DEPTH", rec.refs[0][1].pts)], ">u2").reshape(z.shape))


@pytest.mark.parametrize("blob", [b"RIFF\x00\x00\x00\x00AVI LIST", b"\x89HDF\r\n\x1a\n" + bytes(64),
                                  bytes(range(256)) * 8, b"\x1a\x45\xdf\xa3"])
def test_non_matroska_is_refused_with_the_file_and_what_was_expected(tmp_path, blob):
    p = tmp_path / "x.mkv"
    p.write_bytes(blob)
    with pytest.raises(InputFileError, match="Matroska") as err:
        M.open_mkv(p)
    assert str(p) in str(err.value) and "\n" not in str(err.value)


def test_empty_missing_and_directory(tmp_path):
    (tmp_path / "e.mkv").write_bytes(b"")
    with pytest.raises(InputFileError, match="empty"):
        M.open_mkv(tmp_path / "e.mkv")
    with pytest.raises(InputFileError, match="no such file"):
        M.open_mkv(tmp_path / "nope.mkv")
    with pytest.raises(InputFileError, match="not a file"):
        M.open_mkv(tmp_path)


def test_unknown_doctype_is_refused(mkv_path, tmp_path):
    data = mkv_path.read_bytes()
    assert data.count(b"\x42\x82\x88matroska") == 1
    p = tmp_path / "d.mkv"
    p.write_bytes(data.replace(b"\x42\x82\x88matroska", b"\x42\x82\x88notmkv!!", 1))
    with pytest.raises(InputFileError, match="DocType"):
        M.open_mkv(p)


def _renamed(mkv_path: Path, tmp_path: Path, old: bytes, new: bytes) -> Path:
    """The real recording with one TrackEntry Name (element 0x536E) changed, same length."""
    data = mkv_path.read_bytes()
    head = b"\x53\x6e" + bytes([0x80 | len(old)])
    assert len(old) == len(new) and data.count(head + old) == 1
    p = tmp_path / f"no_{old.decode()}.mkv"
    p.write_bytes(data.replace(head + old, head + new, 1))
    return p


def test_recording_without_depth_track_is_refused_naming_the_track(mkv_path, tmp_path):
    p = _renamed(mkv_path, tmp_path, b"DEPTH", b"DEPTX")
    with pytest.raises(TofhilError, match="DEPTH") as err:
        read_k4a_recording(p)
    assert str(p) in str(err.value)


def test_recording_without_ir_track_imports_depth_alone(mkv_path, tmp_path, intact):
    p = _renamed(mkv_path, tmp_path, b"IR", b"XX")
    with read_k4a_recording(p) as rec:
        t, z, ir = rec.frame(0)
        assert ir is None and z.shape == (576, 640)
        np.testing.assert_array_equal(z, np.frombuffer(intact[("DEPTH", rec.refs[0][1].pts)], ">u2").reshape(576, 640))
