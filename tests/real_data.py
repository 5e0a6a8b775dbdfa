"""The real captures in ../shared/data/real/ (see its README), as every test reads them.

A missing file skips the test on a developer machine and fails it when ``CI=true``: in CI
the shared data must be there, so a missing capture is a broken set-up, not a skip.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"
ADI = REAL / "adi_tof"
AZURE_KINECT_MKV = REAL / "azure_kinect" / "recording.mkv"
IFM_O3R = REAL / "ifm_o3r" / "o3r_frame.h5"


@dataclass(frozen=True)
class CaptureSettings:
    """What a capture's files do not record and a twin needs: the modulation frequency and
    the emitter's wavelength, given to ``scene-from-capture`` as ``--freq-hz`` and
    ``--wavelength-m``. The README of ../shared/data/real/ gives neither for any capture, so
    these are stated choices, not the devices' values: each frequency is one whose unambiguous
    range ``c / 2f`` covers the capture's depths, so nothing wraps; the wavelengths are the
    devices' nominal ones (ADI ToF modules 940 nm, Azure Kinect 850 nm). A figure that depends on
    the frequency (wiggling in radians of it, a phase delay) holds at this frequency only."""

    file: Path
    freq_hz: float
    wavelength_m: float

    def options(self) -> list[str]:
        """The ``scene-from-capture`` options."""
        return ["--freq-hz", f"{self.freq_hz:g}", "--wavelength-m", f"{self.wavelength_m:g}"]


#: Every real capture and its settings (tests and benchmarks/real_captures.py read these).
CAPTURES = {
    # the plane at 0.31-0.42 m (99.9 % of the pixels below 0.47 m); 100 MHz: 1.50 m unambiguous
    "near": CaptureSettings(ADI / "near_plane_depth.bin", 100e6, 940e-9),
    # an office, median depth 1.77 m, at most 4.2 m; 30 MHz: 5.0 m unambiguous
    "office": CaptureSettings(ADI / "frame_mode2.bin", 30e6, 940e-9),
    # a mug, a table, a wall and a window up to ~2.5 m; 30 MHz: 5.0 m unambiguous
    "kinect": CaptureSettings(AZURE_KINECT_MKV, 30e6, 850e-9),
    # one ifm O3R frame, 0.20-1.97 m (median 0.51 m); 60 MHz (the O3R's usual modes, README):
    # 2.5 m unambiguous; the O3R's VCSELs are 940 nm
    "o3r": CaptureSettings(IFM_O3R, 60e6, 940e-9),
}


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
