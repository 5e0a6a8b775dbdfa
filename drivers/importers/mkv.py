"""Matroska (.mkv) files through PyAV (FFmpeg's demuxer): tracks, tags, attachments, packets.

FFmpeg parses the container (EBML, lacing, open-ended clusters, cues); this module turns what
it reports into tofhil's terms and its failures into one :class:`InputFileError` naming the
file:

* a file FFmpeg's Matroska demuxer cannot open is refused with FFmpeg's reason (an unknown
  EBML DocType, which FFmpeg only warns about, is refused too);
* a file that ends inside an element (a recording cut short) opens with ``truncated`` set and
  ``truncation`` holding FFmpeg's own message; FFmpeg returns complete blocks only, so what
  :meth:`MatroskaFile.frames` lists is whole (the caller decides whether to salvage it).

FFmpeg reports damage only through its log (``av_read_frame`` ends with EOF either way), so
warnings and errors are captured while the file is opened and indexed (and not printed).

Opening the file indexes every packet (stream, time, size, byte position) in one demux pass
and keeps the payloads of the first ``HOLD_BYTES`` (a short recording whole, the first frames of
a long one); :meth:`MatroskaFile.payload` demuxes any other packet again, continuing the current
pass when frames are read in file order and seeking (Cues) otherwise, so a multi-gigabyte
recording is never held in memory.
"""

from __future__ import annotations

import math
import threading
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import av
import av.logging

from tofhil.errors import InputFileError

#: Metadata keys FFmpeg fills from Matroska headers (Info, TrackEntry, AttachedFile), not from Tags.
_HEADER_KEYS = frozenset({"title", "encoder", "creation_time", "language", "filename", "mimetype"})
#: FFmpeg log levels we keep (its numbers: smaller is more severe).
_ERROR = av.logging.ERROR
_log_lock = threading.RLock()
#: Payload bytes kept from the indexing pass (the rest is demuxed again when asked for).
HOLD_BYTES = 64 << 20


@contextmanager
def _ffmpeg_log() -> Iterator[list[tuple[int, str, str]]]:
    """FFmpeg's warnings and errors while the block runs, as (level, context, message).

    PyAV discards FFmpeg's log by default; it is switched on (to WARNING) only for the block,
    captured rather than printed, and restored afterwards.
    """
    with _log_lock:
        before, skip = av.logging.get_level(), av.logging.get_skip_repeated()
        av.logging.set_level(av.logging.WARNING)
        av.logging.set_skip_repeated(False)  # else a message equal to the previous file's is dropped
        try:
            with av.logging.Capture() as logs:
                yield logs
        finally:
            av.logging.set_level(before)
            av.logging.set_skip_repeated(skip)


def _messages(logs: list[tuple[int, str, str]], max_level: int) -> list[str]:
    out: list[str] = []
    for level, _, msg in logs:
        text = " ".join(msg.split())
        if level <= max_level and text and text not in out:
            out.append(text)
    return out


def _said(messages: list[str]) -> str:
    """FFmpeg's first messages (the cause; what follows is mostly its resynchronisation)."""
    more = len(messages) - 2
    return "; ".join(messages[:2]) + (f" (+{more} more)" if more > 0 else "")


@dataclass
class Track:
    """One stream of the file, as FFmpeg reports it."""

    index: int          #: FFmpeg stream index (also the key of :attr:`MatroskaFile.tracks`)
    type: str           #: "video", "subtitle", "attachment", ...
    codec_id: str       #: FFmpeg's codec name, e.g. "rawvideo", "mjpeg"
    name: str = ""      #: Matroska TrackEntry Name (FFmpeg: metadata "title")
    fourcc: str = ""    #: the codec tag of ``V_MS/VFW/FOURCC`` tracks, e.g. "b16g"
    pix_fmt: str = ""   #: FFmpeg's pixel format, e.g. "gray16be"
    width: int = 0
    height: int = 0
    time_base: float = math.nan  #: seconds per timestamp unit (Matroska TimecodeScale)


@dataclass(frozen=True)
class BlockRef:
    """One packet (one frame of a video track) of the file; its payload is not read yet."""

    track: int           #: stream index
    pts: int | None      #: presentation time in the track's time base
    time_s: float        #: pts in seconds (NaN when the file gives none)
    size: int            #: payload bytes
    pos: int             #: byte position FFmpeg reports for the block (-1 if unknown)
    order: int           #: index in file order among all packets


@dataclass
class MatroskaFile:
    """An opened Matroska file: use as a context manager, or call :meth:`close`."""

    path: Path
    tracks: dict[int, Track] = field(default_factory=dict)
    attachments: dict[str, bytes] = field(default_factory=dict)
    #: Global tags by name; per-stream tags (tracks and attachments) under ``track_tags[index]``.
    tags: dict[str, str] = field(default_factory=dict)
    track_tags: dict[int, dict[str, str]] = field(default_factory=dict)
    blocks: list[BlockRef] = field(default_factory=list)
    #: True when FFmpeg reported damage (a file cut short); ``truncation`` holds its messages.
    truncated: bool = False
    truncation: str = ""

    def __post_init__(self) -> None:
        self._container: Any = None
        self._demux: Iterator[Any] | None = None
        self._cursor = -1
        self._by_key: dict[tuple[int, int | None, int], BlockRef] = {}
        self._held: dict[int, Any] = {}  # order -> av.Packet (its buffer, not a copy)
        self._held_bytes = 0
        if self.path.stat().st_size == 0:
            raise InputFileError("is empty", file=self.path, expected="a Matroska (.mkv) file")
        try:
            self._open()
        except BaseException:
            self.close()
            raise

    # ------------------------------------------------------------------ opening and indexing
    def _open(self) -> None:
        with _ffmpeg_log() as logs:
            try:
                # probesize: the track headers say all we need; do not let FFmpeg decode frames
                # (MJPEG colour) to guess stream parameters.
                self._container = av.open(str(self.path), format="matroska",
                                          container_options={"probesize": "32"})
            except UnicodeDecodeError as exc:  # PyAV decodes tags (Matroska UTF-8 strings) strictly
                raise InputFileError(f"has a name or tag that is not UTF-8 ({exc.reason} at byte "
                                     f"{exc.start} of {exc.object[:40]!r})", file=self.path,
                                     field="Tags / TrackEntry.Name", expected="UTF-8 strings") from None
            except (av.FFmpegError, OSError) as exc:
                self._refuse(exc, logs)
            self._describe()
            try:
                self._index()
            except av.FFmpegError as exc:  # damage FFmpeg cannot step over: keep what came before
                logs.append((_ERROR, "", str(exc)))
        doctype = [m for m in _messages(logs, av.logging.WARNING) if "doctype" in m.lower()]
        if doctype:
            raise InputFileError("; ".join(doctype), file=self.path, field="EBML.DocType",
                                 expected="'matroska' or 'webm'")
        errors = _messages(logs, _ERROR)
        if errors:
            self.truncated = True
            last = self.blocks[-1] if self.blocks else None
            kept = (f"{len(self.blocks)} complete packets, the last at byte {last.pos} (track {last.track}, "
                    f"{last.time_s:.6f} s)" if last is not None else "no complete packet")
            self.truncation = f"FFmpeg: {_said(errors)}; {kept}"

    def _refuse(self, exc: BaseException, logs: list[tuple[int, str, str]]) -> None:
        said = _messages(logs, av.logging.WARNING)
        reason = _said(said) if said else (getattr(exc, "strerror", None) or str(exc))
        low = " ".join(said).lower()
        if "doctype" in low:
            fld, expected = "EBML.DocType", "'matroska' or 'webm'"
        elif "ebml header parsing failed" in low:
            fld, expected = "EBML header", "a Matroska (.mkv) file"
        elif "prematurely" in low or "truncat" in low or "exceeds containing" in low:
            fld, expected = "Segment", "a complete Matroska file (it looks truncated)"
        else:
            fld, expected = "EBML header", "a Matroska (.mkv) file"
        raise InputFileError(f"FFmpeg's Matroska demuxer cannot open it: {reason}", file=self.path,
                             field=fld, expected=expected) from None

    def _describe(self) -> None:
        c = self._container
        self.tags = {k: v for k, v in c.metadata.items() if k not in _HEADER_KEYS}
        for s in c.streams:
            meta = dict(s.metadata)
            tags = {k: v for k, v in meta.items() if k not in _HEADER_KEYS}
            if tags:
                self.track_tags[s.index] = tags
            if s.type == "attachment":
                self.attachments[getattr(s, "name", None) or meta.get("filename", f"#{s.index}")] = bytes(s.data)
                continue
            cc = s.codec_context
            tb = s.time_base
            self.tracks[s.index] = Track(
                index=s.index, type=s.type, codec_id=(cc.name if cc is not None else ""),
                name=meta.get("title", ""),
                fourcc=(str(cc.codec_tag or "") if cc is not None else ""),
                pix_fmt=(str(getattr(cc, "pix_fmt", "") or "") if cc is not None else ""),
                width=int(getattr(cc, "width", 0) or 0), height=int(getattr(cc, "height", 0) or 0),
                time_base=float(tb) if tb else math.nan)

    def _index(self) -> None:
        for pkt in self._container.demux():
            if not pkt.size:
                continue  # PyAV's flush packets at the end
            if pkt.is_corrupt:
                raise InputFileError(f"packet {len(self.blocks)} of track {pkt.stream.index} is flagged corrupt",
                                     file=self.path, field=f"track {pkt.stream.index}", expected="intact blocks")
            pts = pkt.pts if pkt.pts is not None else pkt.dts
            tb = self.tracks[pkt.stream.index].time_base if pkt.stream.index in self.tracks else math.nan
            ref = BlockRef(track=pkt.stream.index, pts=pts, time_s=(pts * tb if pts is not None else math.nan),
                           size=pkt.size, pos=pkt.pos if pkt.pos is not None else -1, order=len(self.blocks))
            self.blocks.append(ref)
            if self._held_bytes + ref.size <= HOLD_BYTES:
                self._held[ref.order] = pkt
                self._held_bytes += ref.size
            self._by_key.setdefault(self._key(ref.track, ref.pts, ref.pos), ref)

    @staticmethod
    def _key(track: int, pts: int | None, pos: int | None) -> tuple[int, int | None, int]:
        return track, pts, pos if pos is not None else -1

    # ------------------------------------------------------------------ access
    def track_by_name(self, name: str) -> Track | None:
        for t in self.tracks.values():
            if t.name == name:
                return t
        return None

    def frames(self, track: Track) -> list[BlockRef]:
        """The complete packets of ``track`` in file order."""
        return [b for b in self.blocks if b.track == track.index]

    def time_s(self, block: BlockRef) -> float:
        return block.time_s

    def payload(self, block: BlockRef) -> bytes:
        """The bytes of ``block``, demuxed again (in file order this is one pass over the file)."""
        if self._container is None:
            raise InputFileError("is closed", file=self.path, expected="an open recording")
        held = self._held.get(block.order)
        if held is not None:
            return bytes(held)
        want = self._key(block.track, block.pts, block.pos)
        try:
            for attempt in range(2):
                if self._demux is None or self._cursor >= block.order or attempt:
                    self._seek(block, rewind=bool(attempt))
                assert self._demux is not None
                for pkt in self._demux:
                    if not pkt.size:
                        continue
                    key = self._key(pkt.stream.index, pkt.pts if pkt.pts is not None else pkt.dts, pkt.pos)
                    ref = self._by_key.get(key)
                    if ref is not None:
                        self._cursor = ref.order
                    if key == want:
                        data = bytes(pkt)
                        if len(data) != block.size:
                            break
                        return data
                    if ref is not None and ref.order > block.order:
                        break  # passed it: seek (then rewind) and try again
        except av.FFmpegError as exc:
            raise InputFileError(f"cannot read the packet at byte {block.pos} again: {exc}", file=self.path,
                                 field=f"track {block.track}", expected="a readable recording") from None
        raise InputFileError(f"the packet at byte {block.pos} ({block.size} bytes, {block.time_s:.6f} s) "
                             "could not be read again", file=self.path, field=f"track {block.track}",
                             expected="an unchanged file")

    def _seek(self, block: BlockRef, rewind: bool) -> None:
        self._demux = None
        self._cursor = -1
        stream = self._container.streams[block.track]
        if rewind or block.pts is None:
            self._container.seek(0, stream=stream, backward=True, any_frame=True)
        else:
            self._container.seek(block.pts, stream=stream, backward=True)
        self._demux = self._container.demux()

    def close(self) -> None:
        self._demux = None
        self._held.clear()
        if self._container is not None:
            self._container.close()
            self._container = None

    def __enter__(self) -> "MatroskaFile":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_mkv(path: str | Path) -> MatroskaFile:
    """Open and index a Matroska file; raises :class:`InputFileError` for malformed input."""
    p = Path(path)
    if not p.is_file():
        raise InputFileError("no such file" if not p.exists() else "is not a file", file=p,
                             expected="a Matroska (.mkv) recording")
    return MatroskaFile(p)
