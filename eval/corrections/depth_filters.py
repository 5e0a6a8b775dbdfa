"""Depth-image error handling of the SR4000 study: thresholds, jump edges, smoothing.

All functions take a radial distance image ``[H, W]`` (metres) and a validity mask and
return new arrays; invalid pixels never contribute to a smoothed value and stay invalid.
Neighbourhoods are handled by shifting whole images (one numpy operation per offset), so
there is no per-pixel Python loop.
"""

from __future__ import annotations

import numpy as np

from tofhil.camera import CameraModel

#: The 8-neighbourhood as (row, column) offsets.
NEIGHBOURS_8: tuple[tuple[int, int], ...] = ((-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1))


def shifted(a: np.ndarray, dy: int, dx: int, fill: float | bool = np.nan) -> np.ndarray:
    """``out[v, u] = a[v + dy, u + dx]`` (``fill`` where that is off the image)."""
    h, w = a.shape[-2:]
    out = np.full(a.shape, fill, dtype=a.dtype)
    ys, yd = (slice(dy, h), slice(0, h - dy)) if dy >= 0 else (slice(0, h + dy), slice(-dy, h))
    xs, xd = (slice(dx, w), slice(0, w - dx)) if dx >= 0 else (slice(0, w + dx), slice(-dx, w))
    out[..., yd, xd] = a[..., ys, xs]
    return out


def amplitude_threshold(amplitude: np.ndarray, valid: np.ndarray, min_amplitude: float) -> np.ndarray:
    """Validity with pixels of amplitude below ``min_amplitude`` removed (low SNR)."""
    return np.asarray(valid, dtype=bool) & (np.asarray(amplitude) >= min_amplitude)


def jump_edge_angle(radial_m: np.ndarray, valid: np.ndarray, camera: CameraModel,
                    min_angle_deg: float = 10.0) -> np.ndarray:
    """Jump-edge flags by the angle criterion on the 8 neighbours.

    For a pixel ``p`` and a valid neighbour ``n`` (3-D points), the angle between the
    line of sight through ``p`` and the segment ``p -> n`` is ~90 deg on a surface facing
    the camera and near 0 or 180 deg across a depth jump, where mixed pixels lie along
    the ray. The pixel is flagged when, for any neighbour, that angle folded into
    [0, 90] deg is below ``min_angle_deg``.
    """
    d = np.where(valid, radial_m, np.nan).astype(np.float64)
    rays = camera.rays.transpose(2, 0, 1)  # [3, H, W]
    p = rays * d  # [3, H, W]
    flag = np.zeros(d.shape, dtype=bool)
    cos_max = np.cos(np.radians(min_angle_deg))
    for dy, dx in NEIGHBOURS_8:
        n = shifted(p, dy, dx)
        seg = n - p
        norm = np.sqrt((seg ** 2).sum(axis=0))
        with np.errstate(invalid="ignore", divide="ignore"):
            c = np.abs((seg * rays).sum(axis=0)) / norm
        flag |= np.nan_to_num(c, nan=0.0) > cos_max
    return flag & np.asarray(valid, dtype=bool)


def jump_edge_distance(radial_m: np.ndarray, valid: np.ndarray, max_step_m: float = 0.05,
                       relative: float = 0.0) -> np.ndarray:
    """Jump-edge flags by the distance criterion: a neighbour differs by more than
    ``max_step_m + relative * d`` (any of the 8 valid neighbours)."""
    d = np.where(valid, radial_m, np.nan).astype(np.float64)
    limit = max_step_m + relative * d
    flag = np.zeros(d.shape, dtype=bool)
    for dy, dx in NEIGHBOURS_8:
        with np.errstate(invalid="ignore"):
            flag |= np.abs(shifted(d, dy, dx) - d) > limit
    return flag & np.asarray(valid, dtype=bool)


def gaussian_smooth(radial_m: np.ndarray, valid: np.ndarray, sigma_px: float = 1.0) -> np.ndarray:
    """Normalised Gaussian smoothing: only valid pixels are averaged (weights renormalised)."""
    from scipy.ndimage import gaussian_filter

    v = np.asarray(valid, dtype=np.float64)
    d = np.where(valid, radial_m, 0.0).astype(np.float64)
    num = gaussian_filter(d * v, sigma_px, mode="constant")
    den = gaussian_filter(v, sigma_px, mode="constant")
    with np.errstate(invalid="ignore", divide="ignore"):
        out = num / den
    return np.where(valid, out, radial_m)


def median_smooth(radial_m: np.ndarray, valid: np.ndarray, size: int = 3, *,
                  max_bytes: int = 1 << 27) -> np.ndarray:
    """Median over the valid pixels of a ``size x size`` window (odd ``size``).

    The windows are strided views of the NaN-padded image, taken a block of rows at a time
    so that memory stays below ``max_bytes`` whatever the window size."""
    if size < 1 or size % 2 == 0:
        raise ValueError(f"median window size must be odd and >= 1, got {size}")
    import warnings

    r = size // 2
    d = np.where(valid, radial_m, np.nan).astype(np.float64)
    h, w = d.shape
    windows = np.lib.stride_tricks.sliding_window_view(np.pad(d, r, constant_values=np.nan), (size, size))
    rows = max(1, int(max_bytes // (8 * size * size * w)))
    out = np.empty_like(d)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN windows: pixel is invalid anyway
        for y0 in range(0, h, rows):
            block = windows[y0:y0 + rows].reshape(-1, w, size * size)
            out[y0:y0 + rows] = np.nanmedian(block, axis=-1)
    return np.where(valid, out, radial_m)


def bilateral_smooth(radial_m: np.ndarray, valid: np.ndarray, sigma_px: float = 1.5,
                     sigma_m: float = 0.03, radius: int | None = None) -> np.ndarray:
    """Bilateral smoothing: spatial Gaussian ``sigma_px`` times range Gaussian ``sigma_m``
    on the distance difference, so depth edges are kept while flat areas are averaged."""
    r = int(np.ceil(2 * sigma_px)) if radius is None else radius
    d = np.where(valid, radial_m, np.nan).astype(np.float64)
    num = np.zeros_like(d)
    den = np.zeros_like(d)
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            n = shifted(d, dy, dx)
            with np.errstate(invalid="ignore"):
                wgt = np.exp(-0.5 * (dy * dy + dx * dx) / sigma_px ** 2 - 0.5 * ((n - d) / sigma_m) ** 2)
            wgt = np.nan_to_num(wgt, nan=0.0)
            num += wgt * np.nan_to_num(n)
            den += wgt
    with np.errstate(invalid="ignore", divide="ignore"):
        out = num / den
    return np.where(valid, out, radial_m)
