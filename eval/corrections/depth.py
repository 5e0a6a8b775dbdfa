"""Depth-domain corrections (the SR4000 study's filters of ``eval/corrections/depth_filters.py``) on
depth frames, with the bounds that depend on the image (windows no larger than it)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from tofhil.errors import TofhilError
from tofhil.eval.corrections import depth_filters as df
from tofhil.frames import DepthFrame


def _radial(d: DepthFrame) -> np.ndarray:
    return np.asarray(d.radial_m, dtype=np.float64)


def _with_radial(d: DepthFrame, radial: np.ndarray, valid: np.ndarray | None = None) -> DepthFrame:
    dist = radial if d.kind == "radial" else d.camera.radial_to_z(radial)
    return replace(d, distance_m=dist, valid=d.valid if valid is None else valid)


def _within_image(d: DepthFrame, field: str, value: float, limit: int, what: str) -> None:
    if value > limit:
        h, w = np.shape(d.distance_m)[-2:]
        raise TofhilError(f"got {value:g} for a {w}x{h} image", field=field, expected=f"{what} <= {limit}")


def amplitude(d: DepthFrame, min_amplitude: float) -> DepthFrame:
    if d.amplitude is None or not np.isfinite(d.amplitude).any():
        raise TofhilError("amplitude thresholding needs an amplitude image", field="depth/amplitude",
                          expected="a session with amplitude or raw taps")
    return replace(d, valid=df.amplitude_threshold(d.amplitude, d.valid, min_amplitude))


def jump_angle(d: DepthFrame, angle_deg: float) -> DepthFrame:
    flag = df.jump_edge_angle(_radial(d), d.valid, d.camera, angle_deg)
    return replace(d, valid=d.valid & ~flag)


def jump_distance(d: DepthFrame, max_step_m: float, relative: float) -> DepthFrame:
    flag = df.jump_edge_distance(_radial(d), d.valid, max_step_m, relative)
    return replace(d, valid=d.valid & ~flag)


def smooth_gaussian(d: DepthFrame, sigma_px: float) -> DepthFrame:
    _within_image(d, "smooth-gaussian:sigma_px", sigma_px, max(np.shape(d.distance_m)[-2:]), "a sigma in pixels")
    return _with_radial(d, df.gaussian_smooth(_radial(d), d.valid, sigma_px))


def smooth_median(d: DepthFrame, size: int) -> DepthFrame:
    _within_image(d, "smooth-median:size", size, min(np.shape(d.distance_m)[-2:]), "an odd window size")
    return _with_radial(d, df.median_smooth(_radial(d), d.valid, size))


def smooth_bilateral(d: DepthFrame, sigma_px: float, sigma_m: float) -> DepthFrame:
    # The window reaches 2 sigma_px: keep it within the image.
    _within_image(d, "smooth-bilateral:sigma_px", sigma_px, max(1, min(np.shape(d.distance_m)[-2:]) // 2),
                  "a sigma in pixels")
    return _with_radial(d, df.bilateral_smooth(_radial(d), d.valid, sigma_px, sigma_m))
