"""Pixel-aligned comparison of two depth frames taken with the same camera model.

Residual = A - B per pixel (A the measurement or corrected measurement, B the reference:
the twin's render or a ground truth), on radial distance, over regions: all pixels valid
in both, one region per object id when the twin provides an object-id map, and user ROIs.
Statistics are robust (median, MAD) next to the classical ones (mean, RMSE), because
jump-edge pixels and stray-light outliers make the error distribution heavy-tailed.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Any, Iterable

import numpy as np

from tofhil.errors import TofhilError
from tofhil.frames import DepthFrame

#: MAD -> standard deviation for a Gaussian distribution.
MAD_TO_SIGMA = 1.4826


@dataclass
class Region:
    """A named pixel mask ``[H, W]``."""

    name: str
    mask: np.ndarray
    kind: str = "roi"  # "all", "object" or "roi"


def parse_roi(text: str, shape: tuple[int, int], name: str | None = None) -> Region:
    """``"x0,y0,x1,y1"`` (pixel columns x0..x1-1, rows y0..y1-1) -> a Region."""
    try:
        x0, y0, x1, y1 = (int(v) for v in text.split(","))
    except ValueError:
        raise TofhilError(f"got {text!r}", field="--roi", expected="x0,y0,x1,y1 (four integers, pixels)") from None
    h, w = shape
    if not (0 <= x0 < x1 <= w and 0 <= y0 < y1 <= h):
        raise TofhilError(f"ROI {text} is empty or outside the {w}x{h} image", field="--roi",
                          expected=f"0 <= x0 < x1 <= {w}, 0 <= y0 < y1 <= {h}")
    mask = np.zeros(shape, dtype=bool)
    mask[y0:y1, x0:x1] = True
    return Region(name or f"roi_{x0}_{y0}_{x1}_{y1}", mask, "roi")


def object_regions(object_id: np.ndarray, names: dict[int, str] | None = None,
                   min_pixels: int = 1) -> list[Region]:
    """One region per object id present in the map (ids < 0 mean background / no hit)."""
    ids = np.unique(object_id)
    out = []
    for i in ids:
        if i < 0:
            continue
        mask = object_id == i
        if mask.sum() >= min_pixels:
            label = (names or {}).get(int(i), f"object_{int(i)}")
            out.append(Region(label, mask, "object"))
    return out


def robust_stats(values: np.ndarray) -> dict[str, float]:
    """median, MAD (raw), sigma_mad, mean, std, RMSE, p95 of |x|, count."""
    x = np.asarray(values, dtype=np.float64).ravel()
    x = x[np.isfinite(x)]
    if x.size == 0:
        nan = float("nan")
        return {"n": 0, "median": nan, "mad": nan, "sigma_mad": nan, "mean": nan, "std": nan,
                "rmse": nan, "p95_abs": nan, "mean_abs": nan}
    med = float(np.median(x))
    mad = float(np.median(np.abs(x - med)))
    return {"n": int(x.size), "median": med, "mad": mad, "sigma_mad": MAD_TO_SIGMA * mad,
            "mean": float(x.mean()), "std": float(x.std()), "rmse": float(np.sqrt(np.mean(x * x))),
            "p95_abs": float(np.percentile(np.abs(x), 95)), "mean_abs": float(np.abs(x).mean())}


def check_aligned(a: DepthFrame, b: DepthFrame) -> dict[str, Any]:
    """Both frames must share the image size; differing intrinsics are reported, not fatal."""
    if a.camera.shape != b.camera.shape:
        raise TofhilError(f"images are {a.camera.shape} and {b.camera.shape}", field="camera",
                          expected="two sessions with the same camera model (pixel-aligned comparison)")
    same = (a.camera.fx, a.camera.fy, a.camera.cx, a.camera.cy, a.camera.dist) == \
           (b.camera.fx, b.camera.fy, b.camera.cx, b.camera.cy, b.camera.dist)
    return {"same_intrinsics": bool(same)}


def residual_maps(a: DepthFrame, b: DepthFrame) -> dict[str, np.ndarray]:
    """Per-pixel maps: radial residual A - B (NaN where either is invalid), amplitude ratio A/B."""
    both = np.asarray(a.valid) & np.asarray(b.valid)
    with np.errstate(invalid="ignore"):
        res = np.where(both, np.asarray(a.radial_m, np.float64) - np.asarray(b.radial_m, np.float64), np.nan)
    ratio = np.full(res.shape, np.nan)
    if a.amplitude is not None and b.amplitude is not None:
        aa, ab = np.asarray(a.amplitude, np.float64), np.asarray(b.amplitude, np.float64)
        ok = (ab > 0) & np.isfinite(aa) & np.isfinite(ab)
        ratio[ok] = aa[ok] / ab[ok]
    return {"depth_residual_m": res, "amplitude_ratio": ratio, "valid_both": both}


def compare_frames(a: DepthFrame, b: DepthFrame, regions: Iterable[Region] = ()) -> dict[str, Any]:
    """Statistics per region of A - B: depth residual, amplitude ratio, valid fractions.

    The region "all" (every pixel) is always included; each region's stats use the pixels
    valid in both frames.
    """
    info = check_aligned(a, b)
    maps = residual_maps(a, b)
    regs = [Region("all", np.ones(a.camera.shape, dtype=bool), "all")] + list(regions)
    out: dict[str, Any] = {"alignment": info, "regions": {}}
    for r in regs:
        m = r.mask & maps["valid_both"]
        ratio = maps["amplitude_ratio"][m]
        ratio = ratio[np.isfinite(ratio)]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            out["regions"][r.name] = {
                "kind": r.kind,
                "pixels": int(r.mask.sum()),
                "valid_fraction_a": float(np.asarray(a.valid)[r.mask].mean()) if r.mask.any() else float("nan"),
                "valid_fraction_b": float(np.asarray(b.valid)[r.mask].mean()) if r.mask.any() else float("nan"),
                "depth_residual_m": robust_stats(maps["depth_residual_m"][m]),
                "amplitude_ratio_median": float(np.median(ratio)) if ratio.size else float("nan"),
                "amplitude_ratio": robust_stats(ratio),
            }
    return out


def mean_depth_frame(frames: Iterable[DepthFrame], min_valid_fraction: float = 0.5) -> tuple[DepthFrame, np.ndarray]:
    """Temporal mean of a session's depth frames and the per-pixel temporal std of distance.

    A pixel is valid in the mean where it was valid in at least ``min_valid_fraction`` of
    the frames; averaging is over its valid frames only.
    """
    n = 0
    acc = acc2 = cnt = amp = None
    first: DepthFrame | None = None
    for f in frames:
        d = np.asarray(f.radial_m, np.float64)
        v = np.asarray(f.valid, bool) & np.isfinite(d)
        if first is None:
            first = f
            acc, acc2, cnt = np.zeros(d.shape), np.zeros(d.shape), np.zeros(d.shape)
            amp = np.zeros(d.shape)
        dz = np.where(v, d, 0.0)
        acc += dz
        acc2 += dz * dz
        cnt += v
        if f.amplitude is not None:
            amp += np.nan_to_num(np.asarray(f.amplitude, np.float64))
        n += 1
    if first is None:
        raise TofhilError("session has no frames", field="n_frames", expected="at least one frame")
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = acc / cnt
        std = np.sqrt(np.maximum(acc2 / cnt - mean * mean, 0.0))
    valid = cnt >= max(1.0, min_valid_fraction * n)
    frame = DepthFrame(distance_m=np.where(valid, mean, np.nan), kind="radial", camera=first.camera,
                       amplitude=amp / n if first.amplitude is not None else None, valid=valid,
                       timestamp_s=first.timestamp_s, sequence=first.sequence)
    return frame, np.where(valid, std, np.nan)
