"""Core benchmark: demodulation + two-frequency unwrapping of a 640 x 480, 2 x 4-tap frame.

Prints the time per frame and its ratio to one plain pass over the same tap data
(``taps.sum()``), both measured in this run on one core (these machines are shared and noisy:
compare ratios, not seconds). Aims: < 5x the plain pass and > 200 frames/s.

    python benchmarks/bench_core.py [--repeats N]
"""

from __future__ import annotations

import argparse
import os

# one core, as the aim says: keep BLAS single-threaded
for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(var, "1")

import time  # noqa: E402

import numpy as np  # noqa: E402

from tofhil.camera import load_camera_preset  # noqa: E402
from tofhil.demod import distance_to_phase, equally_spaced_phases, taps_from_signal  # noqa: E402
from tofhil.depth import depth_from_raw  # noqa: E402
from tofhil.frames import RawFrame  # noqa: E402


def best_time(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), float(np.min(times))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=50)
    args = ap.parse_args()

    cam = load_camera_preset("oak_tof_33d")
    freq = np.array([80e6, 100e6])
    theta = equally_spaced_phases(4)
    rng = np.random.default_rng(0)
    d = rng.uniform(0.2, 7.0, cam.shape)
    phase = np.stack([distance_to_phase(d, f) for f in freq])
    taps = taps_from_signal(np.full((2,) + cam.shape, 200.0), phase, np.full((2,) + cam.shape, 900.0), theta)
    taps = (taps + rng.normal(0, 2.0, taps.shape)).astype(np.float32)
    frame = RawFrame(taps=taps, freq_hz=freq, theta_rad=theta, integration_time_s=1e-3, camera=cam)

    depth_from_raw(frame)  # warm-up (ray cache, allocations)
    base_med, base_min = best_time(lambda: taps.sum(), args.repeats)
    demod_med, demod_min = best_time(lambda: depth_from_raw(frame), args.repeats)
    err = np.abs(depth_from_raw(frame).distance_m - d)
    print(f"frame: {cam.width} x {cam.height}, {len(freq)} frequencies x {len(theta)} taps, float32, 1 core")
    print(f"baseline taps.sum():            median {base_med * 1e3:7.3f} ms  (min {base_min * 1e3:.3f})")
    print(f"demodulate + unwrap + validity: median {demod_med * 1e3:7.3f} ms  (min {demod_min * 1e3:.3f})")
    print(f"ratio to plain pass (median):   {demod_med / base_med:7.2f} x   (aim < 5x)")
    print(f"frames per second (median):     {1.0 / demod_med:7.1f}      (aim > 200)")
    print(f"sanity: median |error| {np.median(err) * 1e3:.2f} mm, max {err.max() * 1e3:.1f} mm")


if __name__ == "__main__":
    main()
