"""A small Matroska (EBML) reader: tracks, tags, attachments and the frames of video tracks.

Enough of Matroska to read recordings written by the Azure Kinect recorder (k4arecord,
libmatroska) and similar raw-video files; it is not a general demuxer. Elements are
walked with offsets into a memory map of the file, so a multi-gigabyte recording is not
read into memory; a frame's payload is sliced out only when it is asked for.

Why our own reader: OpenCV's VideoCapture cannot decode 16-bit ``b16g`` tracks, and the
pure-Python EBML packages on PyPI either parse metadata only (``enzyme``) or need schema
files and do not split Matroska blocks (``ebmlite``). Matroska's block layout is small
(https://www.matroska.org/technical/basics.html), so we read it directly.

Errors name the file, the element (field) and what was expected.
"""

from __future__ import annotations

import mmap
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

from tofhil.errors import InputFileError

# Element ids (Matroska specification, ids include their length-marker bits).
EBML = 0x1A45DFA3
DOC_TYPE = 0x4282
SEGMENT = 0x18538067
INFO = 0x1549A966
TIMECODE_SCALE = 0x2AD7B1
TRACKS = 0x1654AE6B
TRACK_ENTRY = 0xAE
TRACK_NUMBER = 0xD7
TRACK_UID = 0x73C5
TRACK_TYPE = 0x83
CODEC_ID = 0x86
CODEC_PRIVATE = 0x63A2
TRACK_NAME = 0x536E
VIDEO = 0xE0
PIXEL_WIDTH = 0xB0
PIXEL_HEIGHT = 0xBA
ATTACHMENTS = 0x1941A469
ATTACHED_FILE = 0x61A7
FILE_NAME = 0x466E
FILE_MIME = 0x4660
FILE_DATA = 0x465C
TAGS = 0x1254C367
TAG = 0x7373
TARGETS = 0x63C0
TAG_TRACK_UID = 0x63C5
SIMPLE_TAG = 0x67C8
TAG_NAME = 0x45A3
TAG_STRING = 0x4487
CLUSTER = 0x1F43B675
CLUSTER_TIMECODE = 0xE7
SIMPLE_BLOCK = 0xA3
BLOCK_GROUP = 0xA0
BLOCK = 0xA1

#: Elements whose size may be "unknown" (live recordings): they extend to their parent's end
#: or to the next top-level element.
_TOP_LEVEL = {SEGMENT, CLUSTER}


@dataclass(frozen=True)
class Element:
    id: int
    offset: int       #: where the element's id starts
    data_start: int   #: where its payload starts
    size: int         #: payload size in bytes

    @property
    def end(self) -> int:
        return self.data_start + self.size


@dataclass
class Track:
    number: int
    uid: int
    type: int
    codec_id: str
    name: str = ""
    codec_private: bytes = b""
    width: int = 0
    height: int = 0

    @property
    def fourcc(self) -> str:
        """For ``V_MS/VFW/FOURCC`` tracks: the compression code of the BITMAPINFOHEADER."""
        if self.codec_id == "V_MS/VFW/FOURCC" and len(self.codec_private) >= 20:
            return self.codec_private[16:20].decode("latin-1")
        return ""


@dataclass(frozen=True)
class BlockRef:
    """Where one frame of a track lives in the file (payload not read yet)."""

    track: int
    timecode: int          #: absolute, in TimecodeScale units
    data_start: int
    size: int
    laced: bool


@dataclass
class MatroskaFile:
    """An opened Matroska file: use as a context manager, or call :meth:`close`."""

    path: Path
    doc_type: str = ""
    timecode_scale_ns: int = 1_000_000
    tracks: dict[int, Track] = field(default_factory=dict)
    attachments: dict[str, bytes] = field(default_factory=dict)
    #: Global tags (no track target) by name; per-track tags under ``track_tags[uid]``.
    tags: dict[str, str] = field(default_factory=dict)
    track_tags: dict[int, dict[str, str]] = field(default_factory=dict)
    blocks: list[BlockRef] = field(default_factory=list)
    #: True when the file ends inside an element (a recording cut short); ``truncation`` says where.
    truncated: bool = False
    truncation: str = ""

    def __post_init__(self) -> None:
        self._fh = open(self.path, "rb")
        size = os.fstat(self._fh.fileno()).st_size
        if size == 0:
            self._fh.close()
            raise InputFileError("is empty", file=self.path, expected="a Matroska (.mkv) file")
        self._mm = mmap.mmap(self._fh.fileno(), 0, access=mmap.ACCESS_READ)
        self._size = size
        try:
            self._parse()
        except Exception:
            self.close()
            raise

    # ------------------------------------------------------------------ low level
    def _fail(self, message: str, field_: str, expected: str) -> None:
        raise InputFileError(message, file=self.path, field=field_, expected=expected)

    def _vint(self, pos: int, keep_marker: bool) -> tuple[int, int, bool]:
        """Read a variable-length integer at ``pos``: (value, length, all-ones 'unknown')."""
        if pos >= self._size:
            self._fail(f"ends at byte {self._size} inside an element header", "EBML header",
                       "a complete element id and size")
        first = self._mm[pos]
        if first == 0:
            self._fail(f"invalid variable-length integer at byte {pos}", "EBML vint",
                       "a leading byte with a length marker")
        length = 9 - first.bit_length()
        if pos + length > self._size:
            self._fail(f"ends at byte {self._size} inside an element header", "EBML header",
                       "a complete element id and size")
        value = first if keep_marker else first & ((0x80 >> (length - 1)) - 1)
        for b in self._mm[pos + 1:pos + length]:
            value = (value << 8) | b
        unknown = not keep_marker and value == (1 << (7 * length)) - 1
        return value, length, unknown

    def _children(self, start: int, end: int, lenient: bool = False) -> Iterator[Element]:
        """Elements between ``start`` and ``end``. ``lenient`` (inside Segment and Cluster):
        an element cut off by the end of the file ends the walk and marks the file truncated."""
        pos = start
        while pos < end:
            if lenient and self._incomplete_header(pos, end):
                self._mark_truncated(pos, "an element header")
                return
            eid, n_id, _ = self._vint(pos, keep_marker=True)
            size, n_size, unknown = self._vint(pos + n_id, keep_marker=False)
            data_start = pos + n_id + n_size
            if unknown:
                if eid not in _TOP_LEVEL:
                    self._fail(f"element 0x{eid:X} at byte {pos} has unknown size", f"0x{eid:X}",
                               "a known size (only Segment and Cluster may be open-ended)")
                size = self._open_ended_size(eid, data_start, end)
            if data_start + size > end:
                if eid in (CLUSTER, SEGMENT):
                    # A recording cut short: walk what is there; incomplete children stop it.
                    self._mark_truncated(pos, f"element 0x{eid:X} ({size} bytes declared)")
                    size = end - data_start
                elif lenient:
                    self._mark_truncated(pos, f"element 0x{eid:X} ({size} bytes declared)")
                    return
                else:
                    self._fail(f"element 0x{eid:X} at byte {pos} declares {size} bytes but only "
                               f"{max(0, end - data_start)} remain", f"0x{eid:X}",
                               "a complete file (it looks truncated)")
            yield Element(eid, pos, data_start, size)
            pos = data_start + size

    def _incomplete_header(self, pos: int, end: int) -> bool:
        first = self._mm[pos]
        if first == 0:
            return False  # not a truncation: _vint reports the corruption
        n_id = 9 - first.bit_length()
        if pos + n_id >= end:
            return True
        n_size = 9 - self._mm[pos + n_id].bit_length() if self._mm[pos + n_id] else 1
        return pos + n_id + n_size > end

    def _mark_truncated(self, pos: int, what: str) -> None:
        if not self.truncated:
            self.truncated = True
            self.truncation = f"the file ends at byte {self._size} inside {what} starting at byte {pos}"

    def _open_ended_size(self, eid: int, data_start: int, end: int) -> int:
        if eid == SEGMENT:
            return end - data_start
        # An open-ended cluster runs to the next cluster (or the end of the parent).
        nxt = self._mm.find(CLUSTER.to_bytes(4, "big"), data_start, end)
        return (nxt if nxt >= 0 else end) - data_start

    def _uint(self, el: Element) -> int:
        return int.from_bytes(self._mm[el.data_start:el.end], "big")

    def _str(self, el: Element) -> str:
        return bytes(self._mm[el.data_start:el.end]).rstrip(b"\0").decode("utf-8", "replace")

    def _bytes(self, el: Element) -> bytes:
        return bytes(self._mm[el.data_start:el.end])

    # ------------------------------------------------------------------ structure
    def _parse(self) -> None:
        if self._mm[:4] != EBML.to_bytes(4, "big"):
            self._fail(f"does not start with an EBML header (starts {self._mm[:4].hex()})", "EBML",
                       "a Matroska (.mkv) file, magic 1a45dfa3")
        top = list(self._children(0, self._size))
        if not top or top[0].id != EBML:
            self._fail("does not start with an EBML header", "EBML", "a Matroska (.mkv) file")
        for el in self._children(top[0].data_start, top[0].end):
            if el.id == DOC_TYPE:
                self.doc_type = self._str(el)
        if self.doc_type not in ("matroska", "webm"):
            self._fail(f"DocType is {self.doc_type!r}", "EBML.DocType", "'matroska'")
        segments = [el for el in top if el.id == SEGMENT]
        if not segments:
            self._fail("has no Segment", "Segment", "one Matroska segment")
        seg = segments[0]
        for el in self._children(seg.data_start, seg.end, lenient=True):
            if el.id == INFO:
                for c in self._children(el.data_start, el.end):
                    if c.id == TIMECODE_SCALE:
                        self.timecode_scale_ns = self._uint(c)
            elif el.id == TRACKS:
                for t in self._children(el.data_start, el.end):
                    if t.id == TRACK_ENTRY:
                        track = self._track(t)
                        self.tracks[track.number] = track
            elif el.id == ATTACHMENTS:
                for a in self._children(el.data_start, el.end):
                    if a.id == ATTACHED_FILE:
                        name, data = "", b""
                        for c in self._children(a.data_start, a.end):
                            if c.id == FILE_NAME:
                                name = self._str(c)
                            elif c.id == FILE_DATA:
                                data = self._bytes(c)
                        self.attachments[name] = data
            elif el.id == TAGS:
                self._tags(el)
            elif el.id == CLUSTER:
                self._cluster(el)

    def _track(self, el: Element) -> Track:
        vals: dict[int, Element] = {}
        width = height = 0
        for c in self._children(el.data_start, el.end):
            vals[c.id] = c
            if c.id == VIDEO:
                for v in self._children(c.data_start, c.end):
                    if v.id == PIXEL_WIDTH:
                        width = self._uint(v)
                    elif v.id == PIXEL_HEIGHT:
                        height = self._uint(v)
        if TRACK_NUMBER not in vals:
            self._fail(f"TrackEntry at byte {el.offset} has no TrackNumber", "TrackEntry.TrackNumber",
                       "an unsigned integer")
        return Track(number=self._uint(vals[TRACK_NUMBER]),
                     uid=self._uint(vals[TRACK_UID]) if TRACK_UID in vals else 0,
                     type=self._uint(vals[TRACK_TYPE]) if TRACK_TYPE in vals else 0,
                     codec_id=self._str(vals[CODEC_ID]) if CODEC_ID in vals else "",
                     name=self._str(vals[TRACK_NAME]) if TRACK_NAME in vals else "",
                     codec_private=self._bytes(vals[CODEC_PRIVATE]) if CODEC_PRIVATE in vals else b"",
                     width=width, height=height)

    def _tags(self, el: Element) -> None:
        for tag in self._children(el.data_start, el.end):
            if tag.id != TAG:
                continue
            target_uid = 0
            pairs: dict[str, str] = {}
            for c in self._children(tag.data_start, tag.end):
                if c.id == TARGETS:
                    for t in self._children(c.data_start, c.end):
                        if t.id == TAG_TRACK_UID:
                            target_uid = self._uint(t)
                elif c.id == SIMPLE_TAG:
                    name = value = ""
                    for s in self._children(c.data_start, c.end):
                        if s.id == TAG_NAME:
                            name = self._str(s)
                        elif s.id == TAG_STRING:
                            value = self._str(s)
                    if name:
                        pairs[name] = value
            if target_uid:
                self.track_tags.setdefault(target_uid, {}).update(pairs)
            else:
                self.tags.update(pairs)

    def _cluster(self, el: Element) -> None:
        base = 0
        for c in self._children(el.data_start, el.end, lenient=True):
            if c.id == CLUSTER_TIMECODE:
                base = self._uint(c)
            elif c.id == SIMPLE_BLOCK:
                self._block(c, base)
            elif c.id == BLOCK_GROUP:
                for b in self._children(c.data_start, c.end):
                    if b.id == BLOCK:
                        self._block(b, base)

    def _block(self, el: Element, base: int) -> None:
        # Block header: track number (vint), int16 relative timecode, flags byte.
        track, n, _ = self._vint(el.data_start, keep_marker=False)
        head = el.data_start + n
        if head + 3 > el.end:
            self._fail(f"block at byte {el.offset} is shorter than its header", "SimpleBlock",
                       "track number, 16-bit timecode and flags")
        rel = int.from_bytes(self._mm[head:head + 2], "big", signed=True)
        flags = self._mm[head + 2]
        self.blocks.append(BlockRef(track=track, timecode=base + rel, data_start=head + 3,
                                    size=el.end - head - 3, laced=bool(flags & 0x06)))

    # ------------------------------------------------------------------ access
    def track_by_name(self, name: str) -> Track | None:
        for t in self.tracks.values():
            if t.name == name:
                return t
        return None

    def frames(self, track: Track) -> list[BlockRef]:
        """The blocks of ``track`` in file order."""
        return [b for b in self.blocks if b.track == track.number]

    def payload(self, block: BlockRef) -> bytes:
        if block.laced:
            raise InputFileError(f"block at byte {block.data_start} is laced", file=self.path,
                                 field=f"track {block.track}", expected="one frame per block (no lacing)")
        return self._mm[block.data_start:block.data_start + block.size]

    def time_s(self, block: BlockRef) -> float:
        return block.timecode * self.timecode_scale_ns * 1e-9

    def close(self) -> None:
        mm = getattr(self, "_mm", None)
        if mm is not None and not mm.closed:
            mm.close()
        if not self._fh.closed:
            self._fh.close()

    def __enter__(self) -> "MatroskaFile":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_mkv(path: str | Path) -> MatroskaFile:
    """Open and index a Matroska file; raises :class:`InputFileError` for malformed input."""
    p = Path(path)
    if not p.is_file():
        raise InputFileError("no such file", file=p, expected="a Matroska (.mkv) recording")
    return MatroskaFile(p)
