"""DepthAI driver on a real Luxonis ToF camera (skipped when none is attached)."""

from __future__ import annotations

import numpy as np
import pytest

dai = pytest.importorskip("depthai")

from tofhil.drivers.base import CaptureSettings, DeviceError, open_device  # noqa: E402

pytestmark = pytest.mark.device


def _devices() -> list:
    try:
        return dai.Device.getAllAvailableDevices()
    except RuntimeError:
        return []


needs_device = pytest.mark.skipif(not _devices(), reason="no DepthAI device found "
                                  "(dai.Device.getAllAvailableDevices() is empty): connect an OAK ToF camera")


def test_no_device_gives_a_clear_error():
    if _devices():
        pytest.skip("a DepthAI device is attached")
    with pytest.raises(DeviceError, match="no DepthAI device found"):
        open_device("depthai")


@needs_device
def test_device_streams_paired_depth_with_factory_camera():
    with open_device("depthai") as dev:
        dev.configure(CaptureSettings(mode="distance", extra={"outputs": "depth,amplitude,intensity"}))
        frames = list(dev.stream(5, timeout_s=5.0))
        cam = dev.camera
    assert len(frames) == 5
    seqs = [f.sequence for f in frames]
    assert seqs == sorted(seqs) and len(set(seqs)) == 5
    ts = [f.timestamp_s for f in frames]
    assert all(b > a for a, b in zip(ts, ts[1:]))
    d = frames[-1].depth
    assert d.distance_m.shape == cam.shape and d.amplitude is not None
    valid = d.distance_m[d.valid]
    assert valid.size and np.all((valid > 0.05) & (valid < 10.0))  # metres, not millimetres
