"""The Matroska reader on small hand-built files: open-ended clusters, lacing, block times."""

from __future__ import annotations

import numpy as np
import pytest

from tofhil.drivers.importers import mkv as M
from tofhil.errors import InputFileError


def vint_size(n: int) -> bytes:
    """EBML size: the shortest length whose all-ones value is not n."""
    for length in range(1, 9):
        if n < (1 << (7 * length)) - 1:
            return ((1 << (7 * length)) | n).to_bytes(length, "big") if length > 1 else bytes([0x80 | n])
    raise ValueError(n)


def el(eid: int, payload: bytes, unknown_size: bool = False) -> bytes:
    ident = eid.to_bytes((eid.bit_length() + 7) // 8, "big")
    size = b"\x01\xff\xff\xff\xff\xff\xff\xff" if unknown_size else vint_size(len(payload))
    return ident + size + payload


def uint(eid: int, v: int) -> bytes:
    return el(eid, v.to_bytes(max(1, (v.bit_length() + 7) // 8), "big"))


def block(eid: int, track: int, rel: int, payload: bytes, flags: int = 0x80) -> bytes:
    return el(eid, bytes([0x80 | track]) + rel.to_bytes(2, "big", signed=True) + bytes([flags]) + payload)


def make_file(clusters: list[bytes], open_ended_last: bool = False, scale: int = 1_000_000) -> bytes:
    header = el(M.EBML, el(M.DOC_TYPE, b"matroska"))
    bih = (40).to_bytes(4, "little") + (3).to_bytes(4, "little") + (2).to_bytes(4, "little") + b"\0" * 4 + b"b16g"
    bih += b"\0" * (40 - len(bih))
    track = el(M.TRACK_ENTRY, uint(M.TRACK_NUMBER, 1) + uint(M.TRACK_UID, 7) + uint(M.TRACK_TYPE, 1)
               + el(M.CODEC_ID, b"V_MS/VFW/FOURCC") + el(M.TRACK_NAME, b"DEPTH") + el(M.CODEC_PRIVATE, bih)
               + el(M.VIDEO, uint(M.PIXEL_WIDTH, 3) + uint(M.PIXEL_HEIGHT, 2)))
    tags = el(M.TAGS, el(M.TAG, el(M.TARGETS, uint(M.TAG_TRACK_UID, 7))
                         + el(M.SIMPLE_TAG, el(M.TAG_NAME, b"K4A_DEPTH_MODE") + el(M.TAG_STRING, b"X"))))
    body = el(M.INFO, uint(M.TIMECODE_SCALE, scale)) + el(M.TRACKS, track) + tags
    for i, c in enumerate(clusters):
        body += el(M.CLUSTER, c, unknown_size=open_ended_last and i == len(clusters) - 1)
    return header + el(M.SEGMENT, body)


def image(v: int) -> bytes:
    return np.full((2, 3), v, dtype=">u2").tobytes()


def test_blocks_times_tags_and_open_ended_cluster(tmp_path):
    c1 = uint(M.CLUSTER_TIMECODE, 1000) + block(M.SIMPLE_BLOCK, 1, 0, image(1)) + block(M.SIMPLE_BLOCK, 1, 33, image(2))
    c2 = uint(M.CLUSTER_TIMECODE, 2000) + el(M.BLOCK_GROUP, block(M.BLOCK, 1, -5, image(3)))
    p = tmp_path / "t.mkv"
    p.write_bytes(make_file([c1, c2], open_ended_last=True, scale=1_000_000))
    with M.open_mkv(p) as f:
        t = f.track_by_name("DEPTH")
        assert (t.width, t.height, t.fourcc) == (3, 2, "b16g")
        assert f.track_tags[7]["K4A_DEPTH_MODE"] == "X" and not f.truncated
        blocks = f.frames(t)
        # block time = (cluster timecode + signed relative timecode) x TimecodeScale (1 ms here)
        assert [f.time_s(b) for b in blocks] == pytest.approx([1.0, 1.033, 1.995])
        values = [int(np.frombuffer(f.payload(b), ">u2")[0]) for b in blocks]
        assert values == [1, 2, 3]


def test_laced_blocks_are_refused_with_the_track(tmp_path):
    c = uint(M.CLUSTER_TIMECODE, 0) + block(M.SIMPLE_BLOCK, 1, 0, b"\x01" + image(1), flags=0x82)
    p = tmp_path / "laced.mkv"
    p.write_bytes(make_file([c]))
    with M.open_mkv(p) as f:
        b = f.frames(f.track_by_name("DEPTH"))[0]
        assert b.laced
        with pytest.raises(InputFileError, match="laced.*track 1.*no lacing"):
            f.payload(b)


def test_truncation_inside_a_cluster_keeps_the_complete_blocks(tmp_path):
    c = uint(M.CLUSTER_TIMECODE, 0) + block(M.SIMPLE_BLOCK, 1, 0, image(1)) + block(M.SIMPLE_BLOCK, 1, 10, image(2))
    data = make_file([c])
    p = tmp_path / "cut.mkv"
    p.write_bytes(data[:-4])  # the second block loses its last bytes
    with M.open_mkv(p) as f:
        assert f.truncated and "ends at byte" in f.truncation
        assert len(f.frames(f.track_by_name("DEPTH"))) == 1


def test_not_matroska(tmp_path):
    p = tmp_path / "x.mkv"
    p.write_bytes(b"RIFF0000AVI ")
    with pytest.raises(InputFileError, match="EBML"):
        M.open_mkv(p)
    p.write_bytes(b"")
    with pytest.raises(InputFileError, match="empty"):
        M.open_mkv(p)
