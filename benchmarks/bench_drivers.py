"""Driver throughput: epc635 frame parsing against the sensor's frame rate, and end-to-end
capture from the emulator (in-process pyusb backend and pseudo-terminal).

Baselines measured in the same run:
* parsing: the vendor client's way of decoding a distance + amplitude image (a Python loop
  over pixels masking the confidence bits), against our vectorised parser (CRC, reassembly,
  header, pixels, canonical taps);
* capture: the emulator producing frames alone (render cache + noise + DCS + framing), against
  the whole loop (driver, transport, parser, session file).
Fixed references: the TOFcam635 manual's "up to 50 TOF measurements per second", and the
10 Mbit/s UART link (8N1, 10 bits per byte) a real camera's data must cross.

Run: python benchmarks/bench_drivers.py [--frames N]
"""

from __future__ import annotations

import argparse
import math
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from tofhil.drivers.tofcam635 import protocol as P
from tofhil.drivers.base import CaptureSettings
from tofhil.drivers.capture import capture
from tofhil.drivers.tofcam635.driver import TofCam635
from tofhil.drivers.tofcam635.emulator import EmulatedTofCam635, Epc635Emulator
from tofhil.drivers.tofcam635.profile import dcs_to_canonical
from tofhil.sim.sources import AnalyticWall

SENSOR_FPS = 50.0  # TOFcam635 manual: up to 50 TOF measurements per second
UART_BYTES_PER_S = 10e6 / 10  # 10 Mbit/s, 8N1


def _rate(fn, min_time_s: float = 0.5) -> float:
    """Calls per second of ``fn`` (repeated for at least ``min_time_s``)."""
    fn()
    n, t0 = 0, time.perf_counter()
    while True:
        fn()
        n += 1
        dt = time.perf_counter() - t0
        if dt >= min_time_s:
            return n / dt


def bench_parsing() -> None:
    rng = np.random.default_rng(0)
    header = P.ImageHeader(width=160, height=60)
    dcs = rng.integers(0, 4096, (4, 60, 160)).astype("<i2")
    dcs_wire = P.encode_image_packets(P.DataType.DCS, header, dcs.tobytes())
    da = rng.integers(0, 16000, (60, 160, 2)).astype("<u2")
    da_wire = P.encode_image_packets(P.DataType.DISTANCE_AMPLITUDE, header, da.tobytes())

    def parse(wire: bytes, dtype: int):
        parser = P.PacketParser()
        parser.feed(wire)
        asm = P.ImageAssembler(dtype)
        while (pkt := parser.next_packet()) is not None:
            img = asm.add(pkt)
            if img is not None:
                return img
        raise RuntimeError("incomplete")

    def ours_dcs() -> None:
        dcs_to_canonical(P.decode_dcs(parse(dcs_wire, P.DataType.DCS)))

    def ours_da() -> None:
        P.decode_distance_amplitude(parse(da_wire, P.DataType.DISTANCE_AMPLITUDE))

    payload = da_wire[4 + P.HEADER_SIZE:-4]

    def vendor_loop_da() -> None:  # the vendor client's decode (CRC not even included)
        values = np.frombuffer(payload, dtype="h")
        out = []
        for i in range(len(values)):
            out.append(values[i] & 0x3FFF)
        np.reshape(out[::2], (60, 160)), np.reshape(out[1::2], (60, 160))

    r_dcs, r_da, r_loop = _rate(ours_dcs), _rate(ours_da), _rate(vendor_loop_da)
    link_dcs = UART_BYTES_PER_S / len(dcs_wire)
    print("frame parsing (full 160x60 frames, CRC checked)")
    print(f"  DCS (76 890 B, 2 packets)   {r_dcs:9.1f} frames/s = {r_dcs / SENSOR_FPS:7.1f} x the 50 fps sensor, "
          f"{r_dcs / link_dcs:7.1f} x the 10 Mbit/s link ({link_dcs:.1f} frames/s)")
    print(f"  distance+amplitude          {r_da:9.1f} frames/s = {r_da / SENSOR_FPS:7.1f} x the sensor")
    print(f"  vendor per-pixel loop (baseline, no CRC) {r_loop:7.1f} frames/s -> ours is {r_da / r_loop:.1f} x faster")


def bench_generation(emu: Epc635Emulator, n: int) -> float:
    emu.receive(P.encode_command(P.Cmd.GET_DCS, [0]))
    emu.transmit()
    t0 = time.perf_counter()
    for _ in range(n):
        emu.receive(P.encode_command(P.Cmd.GET_DCS, [0]))
        emu.transmit()
    return n / (time.perf_counter() - t0)


def bench_capture(frames: int) -> None:
    print("end-to-end capture (DCS, 160x60, analytic wall, session file written frame by frame)")
    gen = bench_generation(Epc635Emulator(AnalyticWall(), seed=1), frames)
    with tempfile.TemporaryDirectory() as tmp:
        with EmulatedTofCam635("emulator", emulator=Epc635Emulator(AnalyticWall(), seed=1)) as dev:
            s = capture(dev, Path(tmp) / "usb.h5", frames, CaptureSettings(mode="dcs", integration_time_s=300e-6))
        usb_fps = s.frames_per_s
        proc = subprocess.Popen([sys.executable, "-m", "tofhil.cli", "emulate", "--scene", "wall:1.0", "--pty"],
                                stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        try:
            line = proc.stdout.readline().strip() if proc.stdout else ""
            port = line.removeprefix("PORT=")
            with TofCam635(f"serial:{port}") as dev:
                n_pty = max(10, frames // 3)
                s2 = capture(dev, Path(tmp) / "pty.h5", n_pty, CaptureSettings(mode="dcs", integration_time_s=300e-6))
            pty_fps = s2.frames_per_s
        finally:
            proc.terminate()
            proc.wait(timeout=10)
    print(f"  emulator alone (baseline)   {gen:9.1f} frames/s")
    print(f"  in-process pyusb backend    {usb_fps:9.1f} frames/s = {usb_fps / gen:5.2f} x the emulator alone, "
          f"{usb_fps / SENSOR_FPS:5.1f} x the 50 fps sensor")
    print(f"  pseudo-terminal (serial)    {pty_fps:9.1f} frames/s = {pty_fps / gen:5.2f} x the emulator alone, "
          f"{pty_fps / SENSOR_FPS:5.1f} x the 50 fps sensor")
    if not math.isfinite(pty_fps):
        print("  (pty capture failed)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=150)
    args = ap.parse_args()
    bench_parsing()
    bench_capture(args.frames)


if __name__ == "__main__":
    main()
