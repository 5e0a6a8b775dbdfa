"""Session storage of raw taps: bytes per frame and frames per second, the compact layout
(the device's int16 DN, shuffle + gzip per frame chunk) against the layout before it
(float32, no filter), both measured in the same run.

1. The capture loop end to end (TOFcam635 emulator over the in-process pyusb backend, DCS
   mode, 160 x 60 x 4 taps, the session written and flushed frame by frame): frames per
   second and bytes per frame on disk, old layout against new.
2. The session writer alone on the same frames (the part of the loop the layout changes):
   frames per second, and the reader's frames per second back.
3. Filter choices for the compact layout (int16 taps, one frame per chunk, flushed per frame
   as the writer does): gzip levels with and without shuffle, bytes and write time per frame,
   each against the old float32 layout.

Run: python benchmarks/bench_session_storage.py [--frames N]
"""

from __future__ import annotations

import argparse
import functools
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np

import tofhil.drivers.capture as capture_mod
from tofhil.drivers.base import CaptureSettings
from tofhil.drivers.tofcam635.emulator import EmulatedTofCam635, Epc635Emulator
from tofhil.sim.sources import AnalyticWall
from tofhil.session import SessionWriter, open_session

HOUR_AT_30_FPS = 30 * 3600


def _capture(path: Path, frames: int, layout: str) -> tuple[float, float]:
    """(frames/s, bytes/frame) of a capture written in ``layout`` (the writer's tap_storage)."""
    original = capture_mod.SessionWriter
    capture_mod.SessionWriter = functools.partial(SessionWriter, tap_storage=layout)  # type: ignore[misc]
    try:
        with EmulatedTofCam635("emulator", emulator=Epc635Emulator(AnalyticWall(), seed=1)) as dev:
            s = capture_mod.capture(dev, path, frames, CaptureSettings(mode="dcs", integration_time_s=300e-6))
    finally:
        capture_mod.SessionWriter = original  # type: ignore[misc]
    return s.frames_per_s, path.stat().st_size / s.frames_written


def _frames(n: int) -> list:
    """``n`` raw frames as the driver delivers them (int16 canonical DN)."""
    out = []
    with EmulatedTofCam635("emulator", emulator=Epc635Emulator(AnalyticWall(), seed=2)) as dev:
        dev.configure(CaptureSettings(mode="dcs", integration_time_s=300e-6))
        for frame in dev.stream(n, timeout_s=2.0):
            out.append(frame.raw)
    return out


def _writer(path: Path, frames: list, layout: str) -> tuple[float, float, float]:
    """(write frames/s, bytes/frame, read frames/s) of the session writer alone."""
    t0 = time.perf_counter()
    with SessionWriter(path, frames[0].camera, tap_storage=layout) as w:
        for raw in frames:
            w.append(raw)
    write_fps = len(frames) / (time.perf_counter() - t0)
    t0 = time.perf_counter()
    with open_session(path) as s:
        for i in range(s.n_frames):
            s.raw_frame(i)
    read_fps = len(frames) / (time.perf_counter() - t0)
    return write_fps, path.stat().st_size / len(frames), read_fps


def _filters(path: Path, taps: np.ndarray, dtype: str, **filters) -> tuple[float, float]:
    """(seconds per frame, bytes per frame) of the taps alone in one chunk per frame, flushed
    after every frame (the writer's durability protocol)."""
    shape = taps.shape[1:]
    t0 = time.perf_counter()
    with h5py.File(path, "w") as f:
        ds = f.create_dataset("taps", shape=(0,) + shape, maxshape=(None,) + shape, dtype=dtype,
                              chunks=(1,) + shape, **filters)
        for i, t in enumerate(taps):
            ds.resize(i + 1, axis=0)
            ds[i] = t
            f.flush()
    dt = (time.perf_counter() - t0) / len(taps)
    with h5py.File(path, "r") as f:
        stored = f["taps"].id.get_storage_size()
    return dt, stored / len(taps)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=300)
    args = ap.parse_args()
    n = args.frames
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        print(f"raw-tap session storage, TOFcam635 emulator (160 x 60 x 4 taps, 12-bit DN), {n} frames")
        print("1. capture loop end to end (in-process pyusb backend, DCS)")
        fps_old, b_old = _capture(root / "cap_old.h5", n, "float32")
        fps_new, b_new = _capture(root / "cap_new.h5", n, "compact")
        with open_session(root / "cap_new.h5") as s:
            dtype = s.stored_tap_dtype
        print(f"   old (float32, no filter)          {fps_old:8.1f} frames/s  {b_old / 1e3:8.1f} kB/frame  "
              f"{b_old * HOUR_AT_30_FPS / 1e9:6.2f} GB per hour at 30 fps")
        print(f"   new ({dtype}, shuffle + gzip 1)     {fps_new:8.1f} frames/s  {b_new / 1e3:8.1f} kB/frame  "
              f"{b_new * HOUR_AT_30_FPS / 1e9:6.2f} GB per hour at 30 fps")
        print(f"   new / old: {fps_new / fps_old:.2f} x the frame rate, {b_new / b_old:.3f} x the bytes "
              f"({b_old / b_new:.1f} x smaller)")

        frames = _frames(n)
        print("2. session writer alone (the same frames), and reading them back")
        w_old, bw_old, r_old = _writer(root / "w_old.h5", frames, "float32")
        w_new, bw_new, r_new = _writer(root / "w_new.h5", frames, "compact")
        print(f"   old: write {w_old:8.1f} frames/s, read {r_old:8.1f} frames/s, {bw_old / 1e3:7.1f} kB/frame")
        print(f"   new: write {w_new:8.1f} frames/s, read {r_new:8.1f} frames/s, {bw_new / 1e3:7.1f} kB/frame")
        print(f"   new / old: write {w_new / w_old:.2f} x, read {r_new / r_old:.2f} x, bytes {bw_new / bw_old:.3f} x")
        with open_session(root / "w_new.h5") as s_new, open_session(root / "w_old.h5") as s_old:
            same = all(np.array_equal(s_new.raw_frame(i).taps, s_old.raw_frame(i).taps) for i in range(n))
        print(f"   the taps read back are the same float32 values: {same}")

        print("3. filter choices (taps only, one chunk per frame, flushed per frame)")
        taps = np.stack([f.taps for f in frames])
        t_ref, b_ref = _filters(root / "f_ref.h5", taps.astype(np.float32), "f4")
        print(f"   float32, no filter (old)     {t_ref * 1e3:6.3f} ms/frame {b_ref / 1e3:7.1f} kB/frame  (1.00 x, 1.000 x)")
        for label, dt, filt in (("int16, no filter", "i2", {}),
                                ("int16, gzip 1", "i2", {"compression": "gzip", "compression_opts": 1}),
                                ("int16, shuffle + gzip 1", "i2", {"shuffle": True, "compression": "gzip",
                                                                   "compression_opts": 1}),
                                ("int16, shuffle + gzip 4", "i2", {"shuffle": True, "compression": "gzip",
                                                                   "compression_opts": 4}),
                                ("int16, shuffle + gzip 6", "i2", {"shuffle": True, "compression": "gzip",
                                                                   "compression_opts": 6}),
                                ("float32, shuffle + gzip 1", "f4", {"shuffle": True, "compression": "gzip",
                                                                     "compression_opts": 1})):
            src = taps if dt == "i2" else taps.astype(np.float32)
            t, b = _filters(root / "f.h5", src, dt, **filt)
            print(f"   {label:28s} {t * 1e3:6.3f} ms/frame {b / 1e3:7.1f} kB/frame  "
                  f"({t / t_ref:4.2f} x the time, {b / b_ref:.3f} x the bytes)")


if __name__ == "__main__":
    main()
