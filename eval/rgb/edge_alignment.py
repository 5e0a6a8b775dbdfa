"""How well a colour image lines up with the depth it colours: the misalignment at depth edges, in
colour pixels, measured against the colour image's own edges.

Depth silhouette: a depth pixel whose row neighbour on one side is valid and at least
``jump_m`` farther (the object in front of its background; invalid neighbours are skipped, the
edge then lies somewhere in the gap). The silhouette is put half a depth pixel outward from that
pixel at its depth, moved into the colour camera and projected (the lens models of both cameras).
Colour edge: along the colour image's row through that point, within ``search_px``, the
sub-pixel peak (parabola through three samples) of the smoothed horizontal grey-level gradient's
magnitude. Offsets are signed along u (colour edge minus depth edge) and kept apart for left and
right silhouettes: a misregistration along the baseline shifts both the same way, a silhouette
drawn too wide or narrow (mixed pixels, blur) moves them apart, so

- ``shift_px``   = mean of the two sides' medians (the registration error along u),
- ``spread_px``  = half their difference, outward positive (the colour silhouette's extra width).

The measure checks itself: the extrinsics are moved along the baseline by ``probe_m`` and the
predicted displacement of each edge point (re-projected) is compared with the measured change of
``shift_px``; the slope must be near 1 (``SLOPE_RANGE``), or the figure does not measure the
registration (an edge detector that locks to texture, or a window that is too small) and is
reported as failed.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from tofhil.eval.metrics.noise import robust_sigma
from tofhil.eval.rgb.colorize import project

#: The self-check passes when the measured shift follows the predicted one with a slope in this range.
SLOPE_RANGE = (0.8, 1.2)


@dataclass
class SideOffsets:
    """Signed offsets (colour edge u minus depth edge u, colour px) of one silhouette side."""

    n: int
    median_px: float
    mad_px: float


@dataclass
class EdgeAlignment:
    left: SideOffsets
    right: SideOffsets
    shift_px: float
    spread_px: float
    probes: list[dict[str, float]] = field(default_factory=list)   # baseline moved: predicted vs measured
    slope: float = float("nan")
    slope_left: float = float("nan")
    slope_right: float = float("nan")
    passed: bool = False
    depth_edges_uv: np.ndarray = field(default=None, repr=False)   # [N, 2] colour-image positions
    color_edges_u: np.ndarray = field(default=None, repr=False)    # [N] matched colour edge u (NaN: none)
    side: np.ndarray = field(default=None, repr=False)             # [N] -1 left, +1 right

    def to_dict(self) -> dict[str, Any]:
        return {"left": vars(self.left), "right": vars(self.right), "shift_px": self.shift_px,
                "spread_px": self.spread_px, "probes": self.probes, "slope": self.slope, "slope_left": self.slope_left,
                "slope_right": self.slope_right, "self_check_passed": self.passed,
                "slope_range": list(SLOPE_RANGE)}


def silhouette_points(z_m: np.ndarray, valid: np.ndarray, pixel_to_ray: Callable[[np.ndarray, np.ndarray], Any],
                      jump_m: float = 0.2, max_gap_px: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Depth-camera points ``[N, 3]`` on the silhouettes (half a pixel outward of the foreground
    pixel, at its depth) and their side (-1: background to the left, +1: to the right). Between
    the foreground pixel and its farther neighbour up to ``max_gap_px - 1`` invalid pixels may
    lie (depth cameras drop the mixed pixels of an edge)."""
    z = np.where(valid, z_m, np.nan)
    pts, sides = [], []
    for side in (-1, 1):
        edge = np.zeros(z.shape, dtype=bool)
        gap = np.ones(z.shape, dtype=bool)           # all pixels between are invalid so far
        for g in range(1, max_gap_px + 1):
            nb = np.roll(z, -side * g, axis=1)       # the pixel g steps to that side
            edge |= gap & np.isfinite(z) & np.isfinite(nb) & (nb - z > jump_m)
            gap &= ~np.isfinite(nb)
            edge[:, :g] &= side > 0
            edge[:, z.shape[1] - g:] &= side < 0
        v, u = np.nonzero(edge)
        x, y, ok = pixel_to_ray(u + 0.5 * side, v.astype(np.float64))
        zz = z[v, u]
        p = np.stack([x * zz, y * zz, zz], axis=1)[np.asarray(ok, bool)]
        pts.append(p)
        sides.append(np.full(len(p), side))
    return np.concatenate(pts), np.concatenate(sides)


def _grad_u(rgb: np.ndarray, sigma_px: float) -> np.ndarray:
    import cv2

    grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float32)
    grey = cv2.GaussianBlur(grey, (0, 0), sigma_px)
    return np.abs(cv2.Sobel(grey, cv2.CV_32F, 1, 0, ksize=3))


def color_edges(grad: np.ndarray, uv: np.ndarray, search_px: int) -> np.ndarray:
    """Sub-pixel u of the strongest horizontal gradient within ``search_px`` of each ``uv`` on its row."""
    h, w = grad.shape
    u0 = np.round(uv[:, 0]).astype(np.int64)
    row = np.round(uv[:, 1]).astype(np.int64)
    offs = np.arange(-search_px, search_px + 1)
    cols = u0[:, None] + offs[None, :]
    ok = (row >= 0) & (row < h) & (cols[:, 0] >= 1) & (cols[:, -1] < w - 1)
    out = np.full(len(uv), np.nan)
    if not ok.any():
        return out
    g = grad[row[ok][:, None], cols[ok]]
    k = np.argmax(g, axis=1)
    inner = (k > 0) & (k < len(offs) - 1)          # a peak at the window's end is not an edge found
    ki = np.clip(k, 1, len(offs) - 2)
    a, b, c = (g[np.arange(len(g)), ki + d] for d in (-1, 0, 1))
    den = a - 2 * b + c
    frac = np.where(den < 0, 0.5 * (a - c) / np.where(den < 0, den, -1.0), 0.0)
    u = cols[ok][np.arange(len(g)), ki] + frac
    out[np.flatnonzero(ok)[inner]] = u[inner]
    return out


def _side(d: np.ndarray) -> SideOffsets:
    d = d[np.isfinite(d)]
    if d.size == 0:
        return SideOffsets(0, float("nan"), float("nan"))
    med = float(np.median(d))
    return SideOffsets(int(d.size), med, robust_sigma(d))


def _measure(points: np.ndarray, sides: np.ndarray, tof_to_color: np.ndarray, color_camera: Any, grad: np.ndarray,
             search_px: int) -> tuple[SideOffsets, SideOffsets, np.ndarray, np.ndarray]:
    pc = points @ tof_to_color[:3, :3].T + tof_to_color[:3, 3]
    uv = project(color_camera, pc)
    cu = color_edges(grad, uv, search_px)
    d = cu - uv[:, 0]
    return _side(d[sides < 0]), _side(d[sides > 0]), uv, cu


def edge_alignment(z_m: np.ndarray, valid: np.ndarray, pixel_to_ray: Callable[[np.ndarray, np.ndarray], Any],
                   tof_to_color: np.ndarray, color_camera: Any, rgb: np.ndarray, *, jump_m: float = 0.2,
                   search_px: int = 20, sigma_px: float = 1.5, probe_m: tuple[float, ...] = (-0.004, -0.002, 0.002, 0.004)
                   ) -> EdgeAlignment:
    """Measure the colour/depth misalignment at depth silhouettes and check the measure (module doc)."""
    pts, sides = silhouette_points(z_m, valid, pixel_to_ray, jump_m)
    grad = _grad_u(rgb, sigma_px)
    left, right, uv, cu = _measure(pts, sides, tof_to_color, color_camera, grad, search_px)
    shift = 0.5 * (left.median_px + right.median_px)
    res = EdgeAlignment(left=left, right=right, shift_px=shift, spread_px=0.5 * (left.median_px * -1 + right.median_px),
                        depth_edges_uv=uv, color_edges_u=cu, side=sides)
    # the self-check: move the colour camera along the baseline (x) and re-measure
    pred, meas, meas_l, meas_r = [], [], [], []
    for dx in probe_m:
        t = tof_to_color.copy()
        t[0, 3] += dx
        l2, r2, uv2, _ = _measure(pts, sides, t, color_camera, grad, search_px)
        p = float(np.median(uv2[:, 0] - uv[:, 0]))           # where the depth edges moved to
        m = 0.5 * (l2.median_px + r2.median_px) - shift        # measured offsets move by minus that
        pred.append(-p)
        meas.append(m)
        meas_l.append(l2.median_px - left.median_px)
        meas_r.append(r2.median_px - right.median_px)
        res.probes.append({"baseline_change_m": dx, "predicted_px": -p, "measured_px": m,
                           "measured_left_px": meas_l[-1], "measured_right_px": meas_r[-1]})
    res.slope, res.slope_left, res.slope_right = (_slope(pred, m) for m in (meas, meas_l, meas_r))
    res.passed = SLOPE_RANGE[0] <= res.slope <= SLOPE_RANGE[1]
    return res


def _slope(pred: list[float], meas: list[float]) -> float:
    """Least-squares slope through the origin of measured against predicted changes."""
    p, m = np.asarray(pred), np.asarray(meas)
    if not np.all(np.isfinite(m)) or not np.any(p != 0):
        return float("nan")
    return float(np.sum(p * m) / np.sum(p * p))
