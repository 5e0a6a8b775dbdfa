"""Core benchmark: demodulation + two-frequency unwrapping of a 640 x 480, 2 x 4-tap frame.

Prints the time per frame and its ratio to one plain pass over the same tap data
(``taps.sum()``), both measured in this run on one core, alternating (these machines are
shared and noisy: compare ratios, not seconds), for 2 x 4 taps, 3 x 4 taps and 1 x 3 taps.
Aims: <= 2x the plain pass and > 200 frames/s.

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


def alternating(fns, repeats: int) -> list[tuple[float, float]]:
    """(median, min) CPU time of this thread per call of each function, the functions called
    in turn so all see the same machine load (wall time on a shared machine measures the
    scheduler as much as the code)."""
    times = [[] for _ in fns]
    for _ in range(repeats):
        for fn, acc in zip(fns, times):
            t0 = time.thread_time()
            fn()
            acc.append(time.thread_time() - t0)
    return [(float(np.median(t)), float(np.min(t))) for t in times]


def frame_for(freq: np.ndarray, k: int, cam, rng: np.random.Generator) -> tuple[RawFrame, np.ndarray]:
    from tofhil.unwrap import frequency_plan

    theta = equally_spaced_phases(k)
    d = rng.uniform(0.2, min(7.0, 0.98 * frequency_plan(freq).unambiguous_range_m), cam.shape)
    phase = np.stack([distance_to_phase(d, f) for f in freq])
    shape = (len(freq),) + cam.shape
    taps = taps_from_signal(np.full(shape, 200.0), phase, np.full(shape, 900.0), theta)
    taps = (taps + rng.normal(0, 2.0, taps.shape)).astype(np.float32)
    return RawFrame(taps=taps, freq_hz=freq, theta_rad=theta, integration_time_s=1e-3, camera=cam), d


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=50)
    args = ap.parse_args()

    cam = load_camera_preset("oak_tof_33d")
    rng = np.random.default_rng(0)
    print(f"frame: {cam.width} x {cam.height}, float32, 1 core, CPU time of this thread, median of {args.repeats}")
    for freq, k in ((np.array([80e6, 100e6]), 4), (np.array([80e6, 100e6, 120e6]), 4), (np.array([44e6]), 3)):
        frame, d = frame_for(freq, k, cam, rng)
        taps = frame.taps
        depth_from_raw(frame)  # warm-up (compilation, ray cache, allocations)
        (base_med, base_min), (demod_med, demod_min) = alternating(
            [lambda: taps.sum(), lambda: depth_from_raw(frame)], args.repeats)
        err = np.abs(depth_from_raw(frame).distance_m - d)
        print(f"{len(freq)} frequencies x {k} taps: taps.sum() {base_med * 1e3:6.3f} ms, demodulate + unwrap + "
              f"validity {demod_med * 1e3:6.3f} ms -> ratio {demod_med / base_med:5.2f} x one pass (aim <= 2x), "
              f"{1.0 / demod_med:6.1f} frames/s (aim > 200); median |error| {np.median(err) * 1e3:.2f} mm")

if __name__ == "__main__":
    main()
