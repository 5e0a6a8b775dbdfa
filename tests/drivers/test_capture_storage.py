"""A TOFcam635 capture stores its taps as the device delivers them (int16 DN, shuffle + gzip per
frame chunk): the same depth as before, and a SIGKILL mid-capture keeps every completed frame."""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np

from tofhil.depth import depth_from_raw
from tofhil.drivers.base import CaptureSettings
from tofhil.drivers.capture import capture
from tofhil.drivers.tofcam635.emulator import EmulatedTofCam635, Epc635Emulator
from tofhil.sim.sources import AnalyticWall, NoiseModel, WallSpec
from tofhil.session import open_session

NO_NOISE = NoiseModel(read_noise_dn=0.0, electrons_per_dn=math.inf)


def test_driver_taps_are_int16_and_the_session_keeps_them(tmp_path: Path) -> None:
    out = tmp_path / "s.h5"
    emu = Epc635Emulator(AnalyticWall(WallSpec(distance_m=1.3)), noise=NO_NOISE)
    with EmulatedTofCam635("emulator", emulator=emu) as dev:
        dev.configure(CaptureSettings(mode="dcs", integration_time_s=500e-6, mod_freq_hz=10e6))
        live = next(iter(dev.stream(1, timeout_s=2.0))).raw
        summary = capture(dev, out, 4, CaptureSettings(mode="dcs", integration_time_s=500e-6, mod_freq_hz=10e6))
    assert live.taps.dtype == np.int16 and -2048 <= live.taps.min() and live.taps.max() <= 2047
    assert summary.frames_written == 4
    with h5py.File(out, "r") as f:
        ds = f["raw/taps"]
        assert ds.dtype == np.int16 and ds.compression == "gzip" and ds.shuffle and ds.chunks[0] == 1
    with open_session(out) as s:
        for raw in s.raw_frames():
            assert raw.taps.dtype == np.float32
            # the wall at 1.3 m along each pixel ray, from the stored integer DN (12-bit quantised)
            err = depth_from_raw(raw).radial_m - 1.3 / s.camera.ray_z
            assert abs(float(np.median(err))) < 3e-3


def _tofhil(*args: str) -> list[str]:
    return [sys.executable, "-m", "tofhil.cli", *args]


def test_sigkill_mid_capture_keeps_every_completed_compact_frame(tmp_path: Path) -> None:
    out = tmp_path / "killed.h5"
    proc = subprocess.Popen(_tofhil("capture", "--device", "emulator:wall:1.0", "--frames", "100000",
                                    "--out", str(out)), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        compact_frame = 4 * 60 * 160 * 2 // 4   # an int16 DCS frame, at least ~4x deflated
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and (not out.exists() or out.stat().st_size < 8 * compact_frame + 65536):
            time.sleep(0.05)
        assert out.exists(), "capture never started"
        time.sleep(np.random.default_rng(0).uniform(0, 0.02))
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)
    with open_session(out) as s:
        assert s.n_frames >= 5 and s.stored_tap_dtype == np.int16
        for raw in s.raw_frames():  # every counted frame is complete (default noise: ~1 cm per pixel)
            err = depth_from_raw(raw).radial_m - 1.0 / s.camera.ray_z
            assert abs(float(np.median(err))) < 3e-3 and float(np.percentile(np.abs(err), 99)) < 0.05
