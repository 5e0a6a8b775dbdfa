"""Fault injection through the real driver: corrupt, truncated and garbled replies, silent
timeouts, USB stalls and disconnects. Bad frames are dropped and counted (never delivered),
a disconnect is survived by reconnecting, a permanent loss ends the stream with an error."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tofhil.depth import depth_from_raw
from tofhil.drivers.base import CaptureSettings, DeviceDisconnected
from tofhil.drivers.tofcam635 import protocol as P
from tofhil.drivers.tofcam635.emulator import EmulatedTofCam635, Epc635Emulator
from tofhil.drivers.tofcam635.faults import FaultPlan
from tofhil.sim.sources import AnalyticWall, NoiseModel, WallSpec
from tofhil.errors import DeviceError

NO_NOISE = NoiseModel(read_noise_dn=0.0, electrons_per_dn=math.inf)


def faulty(plan: FaultPlan, distance_m: float = 1.1) -> EmulatedTofCam635:
    emu = Epc635Emulator(AnalyticWall(WallSpec(distance_m=distance_m)), noise=NO_NOISE, faults=plan)
    dev = EmulatedTofCam635("emulator", emulator=emu)
    dev.backoff_s = 0.02
    return dev


def _check_wall(frames: list, distance_m: float) -> None:
    for f in frames:
        assert f.raw is not None
        np.testing.assert_allclose(depth_from_raw(f.raw).radial_m, distance_m / f.raw.camera.ray_z, atol=3e-3)


def test_corrupt_frames_are_dropped_and_counted() -> None:
    plan = FaultPlan(at={1: "crc", 3: "truncate", 5: "garbage", 7: "timeout", 9: "stall"})
    with faulty(plan) as dev:
        dev.configure(CaptureSettings(mode="dcs", integration_time_s=400e-6))
        frames = list(dev.stream(10, timeout_s=0.3))
        emu = dev.emulator
        assert len(frames) == 10
        # garbage before a good reply is skipped by resynchronisation: that frame is kept
        assert dev.stats.dropped == 4
        assert emu.stats.images == 14
        assert emu.stats.faults == {"crc": 1, "truncate": 1, "garbage": 1, "timeout": 1, "stall": 1}
        assert dev.stats.reconnects == 0
        _check_wall(frames, 1.1)
        seq = [f.sequence for f in frames]
        assert len(set(seq)) == 10 and seq == sorted(seq)


def test_distance_mode_survives_random_faults() -> None:
    plan = FaultPlan(rates={"crc": 0.15, "truncate": 0.1}, seed=3)
    with faulty(plan, 2.0) as dev:
        dev.configure(CaptureSettings(mode="distance", integration_time_s=1000e-6, min_amplitude=0))
        frames = list(dev.stream(15, timeout_s=0.3))
        injected = sum(dev.emulator.stats.faults.values())
        assert injected > 0 and dev.stats.dropped == injected
        for f in frames:
            assert f.depth is not None
            np.testing.assert_allclose(f.depth.radial_m, 2.0 / f.depth.camera.ray_z, atol=3e-3)


def test_disconnect_is_survived_by_reconnecting() -> None:
    plan = FaultPlan(at={3: "disconnect"}, disconnect_s=0.15)
    with faulty(plan) as dev:
        dev.configure(CaptureSettings(mode="dcs", integration_time_s=400e-6, mod_freq_hz=10e6))
        frames = list(dev.stream(8, timeout_s=0.3))
        assert len(frames) == 8 and dev.stats.reconnects == 1
        # the replugged camera started from its defaults: the driver re-applied the settings
        assert all(f.raw is not None and f.raw.freq_hz[0] == 10e6 for f in frames)
        assert all(f.raw.integration_time_s == pytest.approx(400e-6) for f in frames)  # type: ignore[union-attr]
        assert dev.usb_backend.kernel_detaches == 4  # cdc_acm detached again after the replug
        _check_wall(frames, 1.1)
        # the restarted camera's frame counter starts again: sequence numbers stay monotonic, no jump
        steps = np.diff([f.sequence for f in frames])
        assert steps.min() >= 1 and steps.max() <= 2


def test_a_device_that_stays_away_ends_the_stream() -> None:
    plan = FaultPlan(at={2: "disconnect"}, disconnect_s=60.0)
    dev = faulty(plan)
    dev.max_reconnects = 3
    with dev:
        dev.configure(CaptureSettings(mode="dcs"))
        got = []
        with pytest.raises(DeviceDisconnected, match="not back after 3 attempts"):
            for f in dev.stream(6, timeout_s=0.3):
                got.append(f)
        assert len(got) == 2 and dev.stats.reconnects == 0


def test_endless_corruption_is_reported_not_looped_forever() -> None:
    with faulty(FaultPlan(rates={"crc": 1.0})) as dev:
        dev.configure(CaptureSettings(mode="dcs"))
        with pytest.raises(DeviceError, match="in a row were corrupt"):
            list(dev.stream(2, timeout_s=0.3, max_dropped=5))
        assert dev.stats.dropped == 6


def test_fault_plan_text_is_validated() -> None:
    plan = FaultPlan.parse("crc@3, timeout=0.25, disconnect_s=1.5")
    assert plan.at == {3: "crc"} and plan.rates == {"timeout": 0.25} and plan.disconnect_s == 1.5
    with pytest.raises(DeviceError, match="unknown fault"):
        FaultPlan.parse("melt@1")
    with pytest.raises(DeviceError, match="KIND@FRAME"):
        FaultPlan.parse("crc@x")


def test_a_truncated_usb_frame_is_a_clear_device_error() -> None:
    """Through pyusb: the reply stops mid-packet; the driver says so, with the transport and sizes."""
    emu = Epc635Emulator(AnalyticWall(), faults=FaultPlan(at={0: "truncate"}))
    with EmulatedTofCam635("emulator", emulator=emu) as dev:
        dev.reply_timeout_s = 0.3
        with pytest.raises(DeviceError, match=r"USB 0483:5740 .*truncated reply, \d+ bytes received, \d+ more"):
            dev.acquire(P.Cmd.GET_DCS)
        assert dev.acquire(P.Cmd.GET_DCS).header.width == 160  # the next frame is whole
