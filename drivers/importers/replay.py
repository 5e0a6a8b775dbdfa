"""A recorded session as a device: ``--device replay:PATH[?loop=1&realtime=1]``.

Streams the session's frames in order with their recorded timestamps and sequence
numbers: raw taps (mode ``dcs``) when the session has them, depth frames (mode
``distance``) when it has those. ``realtime=1`` paces the frames by their timestamp
differences; ``loop=1`` starts over at the end (sequence numbers keep rising, timestamps
shifted by the session's duration plus one frame period). Without ``loop``, reading past
the last frame raises :class:`EndOfRecording` ("end of session"), which ends a capture cleanly
with the frames recorded; a capture copies the session's embedded scene (:attr:`scene_text`).
"""

from __future__ import annotations

import math
import time
from dataclasses import replace
from pathlib import Path
from urllib.parse import parse_qs

import numpy as np

from tofhil.camera import CameraModel
from tofhil.drivers.base import (CaptureSettings, DeviceEntry, DeviceError, DeviceInfo, Driver, EndOfRecording, Frame,
                                 register_driver)
from tofhil.session import Session, open_session


class ReplayDriver(Driver):
    scheme = "replay"

    def __init__(self, spec: str) -> None:
        super().__init__(spec)
        _, _, rest = spec.partition(":")
        path, _, query = rest.partition("?")
        if not path:
            raise DeviceError("no session path", field="--device", expected="replay:PATH_TO_SESSION.h5")
        opts = {k: v[-1] for k, v in parse_qs(query).items()}
        unknown = sorted(set(opts) - {"loop", "realtime"})
        if unknown:
            raise DeviceError(f"unknown replay option(s) {', '.join(unknown)}", field="--device",
                              expected="replay:PATH[?loop=1&realtime=1]")
        self.path = Path(path)
        self.loop = opts.get("loop", "0") not in ("0", "false", "")
        self.realtime = opts.get("realtime", "0") not in ("0", "false", "")
        self.session: Session | None = None
        self._i = 0
        self._pass = 0
        self._t_wall0: float | None = None
        self._t_rec0 = 0.0

    def _open_device(self) -> None:
        self.session = open_session(self.path)  # InputFileError names the file and field
        if self.session.n_frames == 0:
            self.session.close()
            self.session = None
            raise DeviceError("the session has no complete frame", field=str(self.path),
                              expected="a session with at least one frame")
        self._i = 0
        self._pass = 0

    def _close_device(self) -> None:
        if self.session is not None:
            self.session.close()
            self.session = None

    def _apply_settings(self, settings: CaptureSettings) -> None:
        s = self._sess
        if settings.mode == "dcs" and not s.has_raw:
            raise DeviceError("the session has no raw taps", field="mode", expected="--mode distance")
        if settings.mode == "distance" and not s.has_depth and not s.has_raw:
            raise DeviceError("the session has no depth frames", field="mode", expected="--mode dcs")
        if settings.mode == "grayscale":
            raise DeviceError("replay has no grayscale images", field="mode", expected="dcs | distance")
        for name in ("integration_time_s", "mod_freq_hz", "channel", "roi", "min_amplitude"):
            if getattr(settings, name) is not None:
                raise DeviceError(f"{name} cannot change a recording", field=name, expected="leave it unset")

    @property
    def _sess(self) -> Session:
        if self.session is None:
            raise DeviceError("device is not open", field=self.spec)
        return self.session

    @property
    def camera(self) -> CameraModel:
        return self._sess.camera

    @property
    def scene_text(self) -> str:
        """The scene the recording embeds (its twin), copied into a capture of it."""
        return self._sess.scene_text

    def info(self) -> DeviceInfo:
        s = self._sess
        dev = dict(s.device)
        return DeviceInfo(driver="replay", model=str(dev.get("model", "recorded session")),
                          serial=str(dev.get("serial", "")), firmware=str(dev.get("firmware", "")),
                          vendor=str(dev.get("vendor", "")),
                          extra={"replay_of": str(self.path.resolve()), "recorded_device": dev})

    def _duration(self) -> float:
        s = self._sess
        ts = np.asarray(s._file["frames/timestamp_s"][:s.n_frames], dtype=float)
        if s.n_frames < 2 or not np.all(np.isfinite(ts)):
            return float(s.n_frames)
        return float(ts[-1] - ts[0] + np.median(np.diff(ts)))

    def read_frame(self, timeout_s: float = 2.0) -> Frame:
        self._require_open()
        s = self._sess
        if self._i >= s.n_frames:
            if not self.loop:
                raise EndOfRecording(f"end of session after {s.n_frames} frames", field=str(self.path),
                                     expected="at most as many frames as recorded (or replay:PATH?loop=1)")
            self._i = 0
            self._pass += 1
        i = self._i
        self._i += 1
        want_raw = self.settings.mode == "dcs"
        raw = s.raw_frame(i) if (s.has_raw and want_raw) else None
        depth = s.depth_frame(i) if s.has_depth and (not want_raw or not s.has_raw) else None
        if raw is None and depth is None:  # distance asked, only raw recorded: demodulate
            from tofhil.depth import depth_from_raw

            depth = depth_from_raw(s.raw_frame(i))
        item = raw if raw is not None else depth
        assert item is not None
        shift = self._pass * self._duration()
        seq = item.sequence + self._pass * s.n_frames
        t = item.timestamp_s + shift if math.isfinite(item.timestamp_s) else item.timestamp_s
        if raw is not None:
            raw = replace(raw, timestamp_s=t, sequence=seq)
        if depth is not None:
            depth = replace(depth, timestamp_s=t, sequence=seq)
        if self.realtime and math.isfinite(t):
            if self._t_wall0 is None:
                self._t_wall0, self._t_rec0 = time.monotonic(), t
            wait = (t - self._t_rec0) - (time.monotonic() - self._t_wall0)
            if wait > 0:
                time.sleep(wait)
        return Frame(raw=raw, depth=depth, sequence=seq, timestamp_s=t)


def _list() -> list[DeviceEntry]:
    return []  # sessions are files, not attached devices: name one with replay:PATH


register_driver("replay", ReplayDriver, lister=_list,
                description="a recorded session streamed as a device (replay:PATH[?loop=1&realtime=1])")
