"""Capture sessions through the real pyusb driver from the in-process emulator: frame by
frame, with faults, a lost device, refused overwrites, the CLI, and a SIGKILL mid-session."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from tofhil.depth import depth_from_raw
from tofhil.drivers.base import CaptureSettings
from tofhil.drivers.capture import capture
from tofhil.drivers.tofcam635.emulator import EmulatedTofCam635, Epc635Emulator
from tofhil.drivers.tofcam635.faults import FaultPlan
from tofhil.sim.sources import AnalyticWall, NoiseModel, WallSpec
from tofhil.errors import DeviceError, InputFileError
from tofhil.session import open_session

NO_NOISE = NoiseModel(read_noise_dn=0.0, electrons_per_dn=math.inf)


def device(distance_m: float = 1.3, faults: FaultPlan | None = None, noise: NoiseModel | None = NO_NOISE):
    emu = Epc635Emulator(AnalyticWall(WallSpec(distance_m=distance_m)), noise=noise, faults=faults)
    dev = EmulatedTofCam635("emulator", emulator=emu)
    dev.backoff_s = 0.02
    return dev


def test_dcs_session_holds_every_frame_with_device_attributes(tmp_path: Path) -> None:
    out = tmp_path / "s.h5"
    with device(1.3) as dev:
        summary = capture(dev, out, 6, CaptureSettings(mode="dcs", integration_time_s=500e-6, mod_freq_hz=10e6),
                          scene_text=dev.emulator.source.scene_text())
    assert (summary.frames_written, summary.dropped, summary.reconnects, summary.ended_early) == (6, 0, 0, None)
    with open_session(out) as s:
        assert s.n_frames == 6 and s.has_raw and not s.has_depth
        assert s.freq_hz.tolist() == [10e6] and s.integration_time_s == pytest.approx(500e-6)
        np.testing.assert_allclose(np.degrees(s.theta_rad), [0, 90, 180, 270])
        assert s.device["model"] == "TOFcam635" and s.device["serial"] == "1038.20"
        assert s.device["settings"]["mode"] == "dcs" and "wall" in s.scene_text
        assert s.camera.shape == (60, 160)
        seqs = []
        for raw in s.raw_frames():
            np.testing.assert_allclose(depth_from_raw(raw).radial_m, 1.3 / s.camera.ray_z, atol=3e-3)
            seqs.append(raw.sequence)
        assert seqs == list(range(seqs[0], seqs[0] + 6))


def test_distance_session_with_roi_and_faults(tmp_path: Path) -> None:
    out = tmp_path / "d.h5"
    plan = FaultPlan(at={0: "crc", 2: "truncate", 4: "disconnect"}, disconnect_s=0.1)
    with device(0.9, plan) as dev:
        summary = capture(dev, out, 5, CaptureSettings(mode="distance", roi=(0, 8, 160, 48), min_amplitude=0),
                          timeout_s=0.4)
    assert (summary.frames_written, summary.dropped, summary.reconnects) == (5, 2, 1)
    with open_session(out) as s:
        assert s.n_frames == 5 and s.has_depth and not s.has_raw and s.camera.shape == (40, 160)
        for d in s.depth_frames():
            # 3 mm: the corners are dim (the twin's cos^8 falloff) and the integer DCS add ~0.5 DN / A rad.
            np.testing.assert_allclose(d.radial_m, 0.9 / s.camera.ray_z, atol=3e-3)
            assert d.valid.all()


def test_a_lost_device_ends_the_session_with_completed_frames_saved(tmp_path: Path) -> None:
    out = tmp_path / "lost.h5"
    dev = device(1.0, FaultPlan(at={3: "disconnect"}, disconnect_s=60.0))
    dev.max_reconnects = 2
    with dev:
        summary = capture(dev, out, 10, CaptureSettings(mode="dcs"))
    assert summary.frames_written == 3 and summary.ended_early and "device lost" in summary.ended_early
    with open_session(out) as s:
        assert s.n_frames == 3 and all(np.isfinite(r.taps).all() for r in s.raw_frames())


def test_existing_output_is_refused_before_touching_the_device(tmp_path: Path) -> None:
    out = tmp_path / "keep.h5"
    out.write_bytes(b"precious")
    with device() as dev:
        with pytest.raises(InputFileError, match="refusing to overwrite"):
            capture(dev, out, 2, CaptureSettings())
        assert dev.emulator.stats.images == 0
        with pytest.raises(DeviceError, match="grayscale"):
            capture(dev, tmp_path / "g.h5", 2, CaptureSettings(mode="grayscale"))
    assert out.read_bytes() == b"precious"


def _tofhil(*args: str) -> list[str]:
    return [sys.executable, "-m", "tofhil.cli", *args]


def test_cli_capture_prints_the_summary(tmp_path: Path) -> None:
    out = tmp_path / "cli.h5"
    r = subprocess.run(_tofhil("capture", "--device", "emulator:wall:1.5", "--frames", "4", "--out", str(out),
                               "--integration-time-us", "400", "--mod-freq-hz", "20e6", "--faults", "crc@1"),
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "frames written 4/4, dropped 1, reconnects 0" in r.stdout
    with open_session(out) as s:
        assert s.n_frames == 4 and json.loads(json.dumps(s.device))["emulated"] is True
    again = subprocess.run(_tofhil("capture", "--device", "emulator:wall:1.5", "--frames", "1", "--out", str(out)),
                           capture_output=True, text=True, timeout=120)
    assert again.returncode == 2 and "already exists" in again.stderr and "Traceback" not in again.stderr
    bad = subprocess.run(_tofhil("capture", "--device", "usb", "--frames", "1", "--out", str(tmp_path / "x.h5"),
                                 "--mod-freq-hz", "33e6"), capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "Traceback" not in bad.stderr


def test_cli_devices_and_emulate_usage() -> None:
    r = subprocess.run(_tofhil("devices", "--json"), capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    entries = json.loads(r.stdout)
    assert {"spec": "emulator", "kind": "emulated"}.items() <= next(e for e in entries if e["spec"] == "emulator").items()
    no_pty = subprocess.run(_tofhil("emulate", "--scene", "wall:1"), capture_output=True, text=True, timeout=120)
    assert no_pty.returncode == 2 and "--pty" in no_pty.stderr and "Traceback" not in no_pty.stderr


@pytest.mark.device
def test_capture_from_a_real_camera(tmp_path: Path) -> None:
    """Runs only with a TOFcam635 plugged in (skipped otherwise, also in CI)."""
    from tofhil.drivers.tofcam635.driver import TofCam635
    from tofhil.drivers.tofcam635.transport import default_usb_backend, find_usb_devices

    try:
        found = find_usb_devices(default_usb_backend())
    except DeviceError:
        found = []
    if not found:
        pytest.skip("no TOFcam635 connected")
    with TofCam635("usb") as dev:
        summary = capture(dev, tmp_path / "real.h5", 3, CaptureSettings(mode="dcs", integration_time_s=500e-6))
    assert summary.frames_written == 3
    with open_session(tmp_path / "real.h5") as s:
        assert s.n_frames == 3 and s.device["chip_type"] == 4


def test_sigkill_mid_capture_loses_at_most_the_frame_in_flight(tmp_path: Path) -> None:
    out = tmp_path / "killed.h5"
    proc = subprocess.Popen(_tofhil("capture", "--device", "emulator:wall:1.0", "--frames", "100000",
                                    "--out", str(out)), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        frame_bytes = 4 * 60 * 160 * 4  # one float32 DCS frame
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and (not out.exists() or out.stat().st_size < 8 * frame_bytes):
            time.sleep(0.05)
        assert out.exists(), "capture never started"
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)
    with open_session(out) as s:
        assert s.n_frames >= 5
        for raw in s.raw_frames():  # every counted frame is complete (default noise: ~1 cm per pixel)
            err = depth_from_raw(raw).radial_m - 1.0 / s.camera.ray_z
            assert abs(float(np.median(err))) < 3e-3 and float(np.percentile(np.abs(err), 99)) < 0.05


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_an_interrupted_capture_says_how_many_frames_it_kept(tmp_path: Path, sig: signal.Signals) -> None:
    """Ctrl-C or SIGTERM: "interrupted: N frames kept in FILE", exit 130, the file opens with N frames."""
    out = tmp_path / "interrupted.h5"
    # A shell starts background jobs with SIGINT ignored, and Python keeps an ignored SIGINT: give
    # the capture the default disposition, as a terminal user's Ctrl-C has (CI may run us in the background).
    proc = subprocess.Popen(_tofhil("capture", "--device", "emulator:wall:1.0", "--frames", "100000",
                                    "--out", str(out)), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and (not out.exists() or out.stat().st_size < 8 * 4 * 60 * 160 * 4):
            time.sleep(0.05)
        assert out.exists(), "capture never started"
        proc.send_signal(sig)
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=10)
    assert proc.returncode == 130, stderr
    assert "Traceback" not in stderr
    lines = [line for line in (stdout + stderr).splitlines() if line.startswith("interrupted:")]
    assert len(lines) == 1, stdout + stderr
    n = int(lines[0].split()[1])
    assert lines[0] == f"interrupted: {n} frames kept in {out}"
    with open_session(out) as s:
        assert s.n_frames == n >= 5


def test_emulate_refuses_a_frame_rate_that_is_not_positive() -> None:
    for rate in ("-1", "0", "nan", "inf"):
        r = subprocess.run(_tofhil("emulate", "--pty", f"--frame-rate={rate}"), capture_output=True, text=True,
                           timeout=120)
        assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
        assert r.stderr.strip().count("\n") == 0 and "--frame-rate" in r.stderr and "(0, " in r.stderr  # the range excludes 0


def test_devices_prints_no_library_warning() -> None:
    """depthai's container warning ("USB protocol not available ...") is not news to a user."""
    r = subprocess.run(_tofhil("devices"), capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "[warning]" not in r.stdout + r.stderr and "emulator" in r.stdout


def test_cli_roi_is_half_open(tmp_path: Path) -> None:
    """--roi X0,Y0,X1,Y1 with X1, Y1 exclusive: 4,4,156,12 is 152 x 8 pixels; unaligned is refused."""
    out = tmp_path / "roi.h5"
    r = subprocess.run(_tofhil("capture", "--device", "emulator:wall:1.0", "--frames", "1", "--out", str(out),
                               "--roi", "4,4,156,12"), capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    with open_session(out) as s:
        assert s.camera.shape == (8, 152)
    bad = subprocess.run(_tofhil("capture", "--device", "emulator:wall:1.0", "--frames", "1",
                                 "--out", str(tmp_path / "bad.h5"), "--roi", "4,4,155,12"),
                         capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "Traceback" not in bad.stderr and "roi" in bad.stderr
    assert not (tmp_path / "bad.h5").exists()


def test_a_sigterm_lost_in_a_destructor_is_raised_again_at_the_next_frame(monkeypatch: pytest.MonkeyPatch) -> None:
    """A KeyboardInterrupt raised inside h5py's __del__ or a weakref callback is swallowed by Python;
    the capture's SIGTERM handler must leave the flag the capture loop checks, as Ctrl-C's does
    (CI once saw a SIGTERMed 100000-frame capture run on)."""
    import tofhil.cli as cli
    from tofhil.cli.devices import _sigterm_as_interrupt

    monkeypatch.setitem(cli._INTERRUPT, "requested", False)
    previous = signal.getsignal(signal.SIGTERM)
    try:
        _sigterm_as_interrupt()
        handler = signal.getsignal(signal.SIGTERM)
        try:  # what Python does to an exception raised in a destructor: print and drop it
            handler(signal.SIGTERM, None)
        except KeyboardInterrupt:
            pass
        steps = cli.progress(iter(range(10)), 10, "frames")
        with pytest.raises(KeyboardInterrupt):
            next(steps)
    finally:
        signal.signal(signal.SIGTERM, previous)
