"""The real captures in ../shared/data/real/ (see its README), as every test reads them.

A missing file skips the test on a developer machine and fails it when ``CI=true``: in CI
the shared data must be there, so a missing capture is a broken set-up, not a skip.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"
ADI = REAL / "adi_tof"
AZURE_KINECT_MKV = REAL / "azure_kinect" / "recording.mkv"


def need(path: Path) -> Path:
    """``path`` if the capture is there; otherwise skip (fail in CI)."""
    if not path.is_file():
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(f"real capture missing in CI: {path}")
        pytest.skip(f"real capture not present: {path}")
    return path


def adi_office_points(step: int) -> np.ndarray:
    """Every ``step``-th point of the ADI office frame (frame_mode2.bin), read as z-depth
    through an assumed 75 deg camera: no intrinsics ship with it, and the tests that use
    this cloud only need a consistent real surface, not metric truth."""
    from tofhil.camera import CameraModel

    rec = np.fromfile(need(ADI / "frame_mode2.bin"),
                      dtype=np.dtype([("d", "<u2"), ("c", "u1"), ("ab", "<u2")])).reshape(512, 512)
    z = rec["d"].astype(np.float64) / 1000.0
    return CameraModel.from_fov(512, 512, 75.0).points(z, kind="z", valid=z > 0)[::step]
