"""Where the time of a bench procedure goes: a full photon-transfer and an accuracy-vs-distance
campaign on the emulated TOFcam635 (pyusb backend), split into capture, bench changes, the
twin, the analysis and the report.

    python benchmarks/bench_bench.py [--frames 8] [--repeats 1]

Prints, per procedure, the wall time of each phase and its share, the captured frames per
second, and as a baseline the emulator alone making the same number of DCS frames (no USB
framing, no driver, no session file), so the capture's overhead is a ratio measured in the
same run.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from tofhil.app.bench import BenchOptions, run_bench


def emulator_alone(n_frames: int) -> float:
    """Seconds for the flat-field emulator to make ``n_frames`` DCS frames by itself."""
    from tofhil.app.bench.rigs import flat_field_bench, flat_field_source
    from tofhil.drivers.tofcam635.emulator import Epc635Emulator

    sensor, light, _ = flat_field_bench()
    emu = Epc635Emulator(flat_field_source(sensor, light), seed=0)
    emu.device_dcs(125e-6)  # the render (cached) is not the baseline
    t0 = time.perf_counter()
    for _ in range(n_frames):
        emu.device_dcs(125e-6)
    return time.perf_counter() - t0


def run(name: str, device: str, opts: BenchOptions, out: Path) -> tuple[float, dict[str, float], int]:
    t0 = time.perf_counter()
    res = run_bench(name, device, out, options=opts, force=True)
    wall = time.perf_counter() - t0
    frames = opts.frames * res.details["campaign"]["taken"]
    return wall, res.seconds, frames


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=1)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        for name in ("photon-transfer", "accuracy-vs-distance"):
            for rep in range(args.repeats):
                opts = BenchOptions(frames=args.frames, seed=rep, extra={"work_dir": str(Path(tmp) / "work")})
                wall, sec, frames = run(name, "emulator", opts, Path(tmp) / f"{name}-{rep}")
                base = emulator_alone(frames)
                print(f"\n{name} (repeat {rep + 1}): {wall:.1f} s wall, {frames} frames "
                      f"({frames / sec.get('capture', float('nan')):.0f} frames/s captured; the emulator alone "
                      f"{frames / base:.0f} frames/s: capture = {sec.get('capture', 0) / base:.1f} x the emulator)")
                accounted = sum(v for k, v in sec.items() if k != "capture_emulator_render")
                for phase, s in sorted(sec.items(), key=lambda kv: -kv[1]):
                    if s > 0.005:
                        inside = "  (inside capture)" if phase == "capture_emulator_render" else ""
                        print(f"  {phase:<10} {s:7.2f} s  {100 * s / wall:5.1f} %{inside}")
                print(f"  {'other':<10} {wall - accounted:7.2f} s  {100 * (wall - accounted) / wall:5.1f} %  "
                      "(imports, the first numba compile, opening the device)")


if __name__ == "__main__":
    main()
