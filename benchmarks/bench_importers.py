"""Importer and DepthAI-driver benchmark (ratios against baselines measured in the same run).

1. Azure Kinect MKV: index the file and decode a depth + IR frame with PyAV (FFmpeg's demuxer),
   against reading the same number of bytes with ``np.fromfile`` (the I/O floor).
2. ADI interleaved decode (one structured numpy view) against a per-pixel ``struct``
   loop over the same bytes (the obvious pure-Python decoder), on a 64-row strip.
3. DepthAI host-only pipeline: frames/s through the real queues, decoding and pairing
   (640 x 480, depth + amplitude + intensity), against the source's own frame rate.

    python benchmarks/bench_importers.py [--repeats N]
"""

from __future__ import annotations

import argparse
import struct
import time
from pathlib import Path

import numpy as np

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"


def timed(fn, repeats: int) -> float:
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts))


def bench_mkv(repeats: int) -> None:
    from tofhil.drivers.importers.mkv import open_mkv

    path = REAL / "azure_kinect" / "recording.mkv"
    if not path.is_file():
        print(f"mkv: {path} not present, skipped")
        return

    def ours() -> None:
        with open_mkv(path) as m:
            for name in ("DEPTH", "IR"):
                t = m.track_by_name(name)
                np.frombuffer(m.payload(m.frames(t)[0]), ">u2").astype(np.uint16)

    def floor() -> None:
        np.fromfile(path, dtype=np.uint8)

    a, b = timed(ours, repeats), timed(floor, repeats)
    print(f"mkv index + decode depth & IR: {a * 1e3:.2f} ms; np.fromfile of the whole file "
          f"{b * 1e3:.2f} ms; ratio {a / b:.1f}x")


def bench_adi(repeats: int) -> None:
    from tofhil.drivers.importers.adi import read_adi_interleaved

    path = REAL / "adi_tof" / "frame_mode2.bin"
    if not path.is_file():
        print(f"adi: {path} not present, skipped")
        return
    raw = path.read_bytes()
    rows = 64

    def per_pixel() -> None:
        out = np.empty((rows * 512, 3), np.uint32)
        for i in range(rows * 512):
            out[i] = struct.unpack_from("<HBH", raw, 5 * i)

    t_loop = timed(per_pixel, max(1, repeats // 5)) * (512 / rows)  # scaled to a full frame
    t_ours = timed(lambda: read_adi_interleaved(path), repeats)
    print(f"ADI interleaved 512x512: {t_ours * 1e3:.2f} ms; per-pixel struct loop (scaled) "
          f"{t_loop * 1e3:.1f} ms; speed-up {t_loop / t_ours:.0f}x")


def bench_depthai(n: int) -> None:
    try:
        import depthai  # noqa: F401
    except ImportError:
        print("depthai not installed, skipped")
        return
    from tofhil.drivers.base import CaptureSettings
    from tofhil.drivers.depthai.driver import DepthAIToF
    from tofhil.sim.sources import PlaneScene

    def rate(fps: float) -> float:
        dev = DepthAIToF("depthai-sim", host_scene=PlaneScene(fps=fps))
        with dev:
            dev.configure(CaptureSettings(mode="distance"))
            next(iter(dev.stream(1, timeout_s=10)))  # start-up excluded
            t0 = time.perf_counter()
            got = sum(1 for _ in dev.stream(n, timeout_s=10))
            return got / (time.perf_counter() - t0)

    fps = 60.0
    live = rate(fps)
    print(f"DepthAI host pipeline 640x480 depth+amplitude+intensity: {live:.1f} frames/s "
          f"against a {fps:.0f} frames/s source: ratio {live / fps:.2f} (1.0 = keeps up)")
    flat = rate(10_000.0)
    # Luxonis docs: the ToF node emits depth at half the raw camera rate (60 fps raw -> 30).
    print(f"  unthrottled source: {flat:.0f} frames/s = {flat / 30.0:.1f}x an OAK ToF's 30 depth "
          "frames/s (queues + decoding + pairing + radial conversion)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--frames", type=int, default=60)
    args = ap.parse_args()
    bench_mkv(args.repeats)
    bench_adi(args.repeats)
    bench_depthai(args.frames)


if __name__ == "__main__":
    main()
