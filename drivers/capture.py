"""Capture frames from any driver into a session file, frame by frame.

Every frame that arrives whole is appended (and made durable) before the next is requested;
corrupt frames are dropped by the driver and only counted; a lost device is retried with
backoff by the driver and, if it stays away, the session ends cleanly with every completed
frame saved. A capture killed outright (SIGKILL) loses at most the frame in flight (the
session writer raises ``n_frames`` only after a frame's data is flushed); SIGINT/SIGTERM
end it cleanly.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

from tofhil.outputs import refuse_existing
from tofhil.drivers.base import CaptureSettings, DeviceDisconnected, Driver, EndOfRecording, Frame
from tofhil.errors import DeviceError
from tofhil.session import SessionWriter


@dataclass
class CaptureSummary:
    """What a capture achieved, for the CLI summary and for tests."""

    path: str
    requested: int
    frames_written: int
    dropped: int
    reconnects: int
    elapsed_s: float
    #: None when all requested frames were written; otherwise why the session ended early.
    ended_early: str | None = None
    #: A recorded source ran out (replay without loop): a clean end, the frames it had.
    end_of_recording: bool = False

    @property
    def frames_per_s(self) -> float:
        return self.frames_written / self.elapsed_s if self.elapsed_s > 0 else float("nan")

    def to_dict(self) -> dict[str, object]:
        return asdict(self) | {"frames_per_s": self.frames_per_s}


def capture(driver: Driver, out_path: str | Path, n_frames: int, settings: CaptureSettings, *,
            force: bool = False, scene_text: str = "", timeout_s: float = 2.0,
            on_frame: Callable[[Frame], None] | None = None,
            device_extra: dict[str, object] | None = None) -> CaptureSummary:
    """Configure an opened ``driver``, stream ``n_frames`` good frames into ``out_path``.

    ``on_frame`` is the frame observer: called with each frame after it is safely written
    (progress bars, the live view). It runs in the capture loop, so it must return at once:
    the live view (``tofhil.app.view``) only hands the frame to a bounded queue. An exception
    from it ends the capture as any other would, with every written frame kept (Ctrl-C seen
    there is an interrupt). ``timeout_s`` bounds the wait for one frame's reply (a frame
    that misses it is dropped). ``device_extra`` adds keys to the session's device header
    (an emulator's noise seed).
    """
    if n_frames < 1:
        raise DeviceError(f"--frames {n_frames}", field="--frames", expected="a positive number of frames")
    if settings.mode == "grayscale":
        raise DeviceError("grayscale frames have no place in a session file", field="--mode",
                          expected="dcs or distance")
    out_path = Path(out_path)
    refuse_existing(out_path, force, recorded=True)  # fail before touching the device, not after the first frame
    driver.configure(settings)
    device = driver.info().to_dict() | {"settings": settings.to_dict(), "spec": driver.spec} | dict(device_extra or {})
    # a recording that embeds its scene (replay) passes it on, as the emulator's caller does
    scene_text = scene_text or getattr(driver, "scene_text", "") or ""
    start = time.monotonic()
    ended: str | None = None
    end_of_recording = False
    writer: SessionWriter | None = None
    colors: list[tuple[int, object]] = []     # (frame index, colour image) for the rgb/ group
    try:
        for frame in driver.stream(n_frames, timeout_s=timeout_s):
            if writer is None:  # the first frame's header tells the true image size (ROI)
                part = frame.raw if frame.raw is not None else frame.depth
                assert part is not None
                writer = SessionWriter(out_path, part.camera, device=device, scene_text=scene_text, force=force)
            if "rgb" in frame.images and getattr(driver, "rgb_camera", None) is not None:
                colors.append((writer.n_frames, frame.images["rgb"]))
            writer.append(raw=frame.raw, depth=frame.depth)
            if on_frame is not None:
                on_frame(frame)
    except EndOfRecording as exc:
        ended = str(exc)
        end_of_recording = True
    except DeviceDisconnected as exc:
        ended = f"device lost: {exc}"
    except KeyboardInterrupt:
        ended = "interrupted"
    finally:
        written = writer.n_frames if writer is not None else 0
        if writer is not None:
            writer.close()
            colors = [c for c in colors if c[0] < written]
            if colors:   # the colour camera's frames beside ToF (tofhil/session_rgb.py)
                from tofhil.session_rgb import write_rgb

                write_rgb(out_path, [c[1] for c in colors], driver.rgb_camera, frame_index=[c[0] for c in colors],
                          tof_to_camera=getattr(driver, "tof_to_rgb", None))
    return CaptureSummary(path=str(out_path), requested=n_frames, frames_written=written,
                          dropped=driver.stats.dropped, reconnects=driver.stats.reconnects,
                          elapsed_s=time.monotonic() - start, ended_early=ended,
                          end_of_recording=end_of_recording)
