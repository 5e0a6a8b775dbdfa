"""The live view's cost to the capture: the emulated TOFcam635 captured into a session with the
view off and on (``--save VIEW.rrd``, headless), in the same run, interleaved.

Cases (each run ``--repeats`` times, in turn, so that a change in the machine's load hits all):
* off: the capture alone (baseline);
* view: the view at its defaults (at most 30 frames/s, and its thread under 5 % of the time:
  depth, amplitude, the cloud, written to an .rrd), as ``tofhil capture --save VIEW.rrd``;
* view, every frame: ``--view-rate 0`` (every frame the viewer keeps up with);
* view + twin: the defaults with a scene (the twin rendered once on the viewer thread, the
  residual per frame).
Printed: the capture's frames per second (median), the ratio to "off" (aim: >= 0.9), and
how many frames the view showed and dropped.

Run: python benchmarks/bench_view.py [--frames N] [--repeats R]
"""

from __future__ import annotations

import argparse
import math
import statistics
import tempfile
from pathlib import Path

from tofhil.app.view import LiveView
from tofhil.drivers.base import CaptureSettings
from tofhil.drivers.capture import capture
from tofhil.drivers.tofcam635.emulator import EmulatedTofCam635, Epc635Emulator
from tofhil.sim.sources import AnalyticWall, NoiseModel, WallSpec


def _device() -> EmulatedTofCam635:
    noise = NoiseModel(read_noise_dn=2.0, electrons_per_dn=math.inf)
    return EmulatedTofCam635("emulator", emulator=Epc635Emulator(AnalyticWall(WallSpec(distance_m=1.0)), noise=noise))


def run_case(case: str, frames: int, tmp: Path, i: int) -> tuple[float, int, int]:
    """(capture frames/s, view frames shown, dropped) of one capture."""
    live = None
    if case != "off":
        from tofhil.sim.scene import load_scene

        live = LiveView(save=tmp / f"{case.replace(' ', '_')}-{i}.rrd",
                        max_rate_hz=None if case == "view, every frame" else 30.0,
                        scene=load_scene("wall") if case == "view + twin" else None)
    with _device() as dev:
        summary = capture(dev, tmp / f"s-{case.replace(' ', '_')}-{i}.h5", frames, CaptureSettings(mode="dcs"),
                          on_frame=None if live is None else live.offer)
    if live is None:
        return summary.frames_per_s, 0, 0
    view = live.close()
    return summary.frames_per_s, view.shown, view.dropped


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=400)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    cases = ["off", "view", "view, every frame", "view + twin"]
    rates: dict[str, list[float]] = {c: [] for c in cases}
    shown: dict[str, list[tuple[int, int]]] = {c: [] for c in cases}
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        run_case("view + twin", 20, tmp, -1)  # warm-up: numba and Rerun load once, outside the figures
        for i in range(args.repeats):
            for case in cases:
                fps, n_shown, n_dropped = run_case(case, args.frames, tmp, i)
                rates[case].append(fps)
                shown[case].append((n_shown, n_dropped))
    base = statistics.median(rates["off"])
    print(f"emulated TOFcam635 (160 x 60 x 4 taps, pyusb backend, session file), {args.frames} frames, "
          f"{args.repeats} runs per case, interleaved")
    print(f"{'case':22s} {'frames/s (median)':>18s} {'runs':>24s} {'ratio to off':>13s}  view shown / dropped")
    for case in cases:
        r = rates[case]
        views = ", ".join(f"{a}/{b}" for a, b in shown[case]) if case != "off" else ""
        print(f"{case:22s} {statistics.median(r):18.1f} {' '.join(f'{x:.0f}' for x in r):>24s} "
              f"{statistics.median(r) / base:13.2f}  {views}")


if __name__ == "__main__":
    main()
