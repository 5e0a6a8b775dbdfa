"""The one evaluation core: residual maps, per-region statistics, cloud and NDT metrics.

``tofhil compare`` and ``tofhil diagnose`` are layouts over this module; every figure a
report or the CLI prints is computed here, once.

- Residual = A - B per pixel (A the measurement, B the reference: the twin or a ground
  truth), on radial distance. For single-frequency data the depth residual is wrapped to
  the unambiguous range (:func:`wrap_period`), so that a pixel near the wrap compares right.
- A pixel is compared where it is *valid in both* frames; a region's statistics use its
  pixels valid in both. :data:`DEPTH_RMSE` names the headline figure:
  ``sqrt(mean((d_A - d_B)^2))`` over the pixels of a region valid in A and in B.
- Regions are named pixel masks: the whole image, the scene's objects, user ROIs
  (``X0,Y0,X1,Y1``, half-open) and masks (PNG or .npy), and diagnosis's held-out pixels.
- Statistics are robust (median, MAD) next to the classical ones (mean, RMSE), because
  jump-edge pixels and stray-light outliers make the error distribution heavy-tailed.
- Each region also says why pixels are missing: how many are saturated (a tap clipped at
  the ADC's end) or non-finite in A or B, so a region dominated by saturation says so.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from tofhil.eval.metrics.noise import MAD_TO_SIGMA
from tofhil.demod import TapLimits, bad_extremes, clip_limits
from tofhil.errors import TofhilError, require_input_file
from tofhil.schema import to_plain
from tofhil.frames import DepthFrame

#: MAD -> standard deviation for a Gaussian distribution.

#: The name of the headline figure, printed wherever it is printed.
DEPTH_RMSE = ("depth RMSE over pixels valid in both that carry a measurement (signal above noise, "
              "unwrapped to the same interval)")

#: A multi-frequency depth residual beyond this fraction of the shortest single-frequency
#: unambiguous range is an unwrapping to the wrong interval, not a surface: no model error of
#: the twin moves a pixel by a quarter of a period, noise in the phases does.
UNWRAP_ERROR_FRACTION = 0.25
#: A pixel whose depth noise exceeds this fraction of the shortest unambiguous range has no
#: signal above its noise (a phase noise of 0.3 rad: a signal about 3 times its noise).
NO_SIGNAL_FRACTION = 0.05
#: Trimmed RMSE: the RMSE after leaving out this fraction of the pixels with the largest |r|
#: (stated wherever it is printed). 5 %: a strip of shadow or an object edge a few pixels wide
#: does not carry the figure, a systematic error over a region of the image does.
TRIM_FRACTION = 0.05
#: Side of the neighbourhood whose depth spread tests a side's spatial coherence (pixels).
COHERENCE_WINDOW_PX = 3
#: Only a pixel dimmer than this fraction of its side's 99th-percentile amplitude may be found
#: incoherent: a lit surface's edge (a card's corner among clipped pixels) mixes two depths in
#: its window without lacking a signal; a shadow lit only by multipath is far below it.
DIM_FRACTION = 0.05

#: A clipped ADC shows as several pixels pinned at one extreme tap value.


def json_safe(x: Any) -> Any:
    """Plain JSON values for reports: numpy to Python, non-finite floats to ``None``."""
    return to_plain(x, nonfinite_as_none=True)


# ---------------------------------------------------------------------------- regions


@dataclass
class Region:
    """A named pixel mask ``[H, W]``; ``kind`` is "all", "object", "roi", "mask" or "held-out"."""

    name: str
    mask: np.ndarray
    kind: str = "roi"


def whole_image(shape: tuple[int, int]) -> Region:
    return Region("all", np.ones(shape, dtype=bool), "all")


def parse_roi(text: str, shape: tuple[int, int], name: str | None = None) -> Region:
    """``"X0,Y0,X1,Y1"`` -> a Region: columns X0..X1-1 and rows Y0..Y1-1 (half-open, as numpy
    slices and the TOFcam635 firmware: ``4,4,156,12`` is 152 x 8 pixels)."""
    try:
        x0, y0, x1, y1 = (int(v) for v in text.split(","))
    except ValueError:
        raise TofhilError(f"got {text!r}", field="--roi",
                          expected="X0,Y0,X1,Y1 (four integers, pixels, X1 and Y1 exclusive)") from None
    h, w = shape
    if not (0 <= x0 < x1 <= w and 0 <= y0 < y1 <= h):
        raise TofhilError(f"ROI {text} is empty or outside the {w}x{h} image", field="--roi",
                          expected=f"0 <= X0 < X1 <= {w}, 0 <= Y0 < Y1 <= {h} (X1, Y1 exclusive)")
    mask = np.zeros(shape, dtype=bool)
    mask[y0:y1, x0:x1] = True
    return Region(name or f"roi_{x0}_{y0}_{x1}_{y1}", mask, "roi")


def load_mask(path: str | Path, shape: tuple[int, int]) -> Region:
    """A region from a mask file: ``.npy`` (bool or numbers, non-zero = inside) or an image
    (PNG and what matplotlib reads; any channel non-zero = inside), of the image's size."""
    p = require_input_file(path, field="--mask", expected="a mask image (.png) or array (.npy)")
    try:
        if p.suffix.lower() == ".npy":
            arr = np.load(p, allow_pickle=False)
        else:
            import matplotlib.image as mpimg

            arr = mpimg.imread(p)
    except Exception as exc:  # unreadable: a damaged or foreign file
        raise TofhilError(f"cannot be read ({type(exc).__name__}: {exc})", file=p, field="--mask",
                          expected="a mask image (.png) or array (.npy)") from None
    arr = np.asarray(arr)
    if arr.ndim == 3:  # an image with channels: inside where any colour channel is set
        arr = arr[..., :3].any(axis=2) if arr.shape[2] >= 3 else arr[..., 0]
    if arr.ndim != 2 or arr.shape != tuple(shape):
        raise TofhilError(f"has shape {arr.shape}", file=p, field="--mask",
                          expected=f"a {shape[1]} x {shape[0]} mask (rows x columns {shape})")
    if arr.dtype.kind == "f" and not np.isfinite(arr).all():
        raise TofhilError("contains NaN or infinite values", file=p, field="--mask", expected="0 / 1 values")
    mask = arr.astype(bool)
    if not mask.any():
        raise TofhilError("selects no pixel", file=p, field="--mask", expected="a non-empty mask")
    return Region(f"mask_{p.stem}", mask, "mask")


def object_regions(object_id: np.ndarray, names: dict[int, str] | None = None,
                   min_pixels: int = 1) -> list[Region]:
    """One region per object id present in the map (ids < 0 mean background / no hit)."""
    out = []
    for i in np.unique(object_id):
        if i < 0:
            continue
        mask = object_id == i
        if mask.sum() >= min_pixels:
            out.append(Region((names or {}).get(int(i), f"object_{int(i)}"), mask, "object"))
    return out


# ---------------------------------------------------------------------------- statistics


@dataclass
class Stats:
    """Statistics of a residual over a set of pixels (non-finite values left out)."""

    n: int
    median: float
    mad: float          # median absolute deviation from the median (raw, not scaled)
    sigma_mad: float    # MAD_TO_SIGMA * mad
    mean: float
    std: float
    rmse: float
    p95_abs: float
    mean_abs: float
    #: RMSE of the values left after the TRIM_FRACTION with the largest magnitude are dropped.
    rmse_trimmed: float = float("nan")

    def to_json(self) -> dict[str, Any]:
        return json_safe(asdict(self))


def rmse(x: np.ndarray) -> float:
    """Root mean square of residuals (NaN when there are none): the one RMSE every report's
    figure and every effect size is."""
    x = np.asarray(x, dtype=np.float64)
    return float(np.sqrt(np.mean(x * x))) if x.size else float("nan")


def stats(values: np.ndarray) -> Stats:
    """median, MAD, sigma_mad, mean, std, RMSE, p95 of |x|, count of the finite values."""
    x = np.asarray(values, dtype=np.float64).ravel()
    x = x[np.isfinite(x)]
    if x.size == 0:
        nan = float("nan")
        return Stats(0, nan, nan, nan, nan, nan, nan, nan, nan)
    med = float(np.median(x))
    mad = float(np.median(np.abs(x - med)))
    return Stats(n=int(x.size), median=med, mad=mad, sigma_mad=MAD_TO_SIGMA * mad, mean=float(x.mean()),
                 std=float(x.std()), rmse=rmse(x),
                 p95_abs=float(np.percentile(np.abs(x), 95)), mean_abs=float(np.abs(x).mean()),
                 rmse_trimmed=trimmed_rmse(x))


def trimmed_rmse(x: np.ndarray, fraction: float = TRIM_FRACTION) -> float:
    """RMSE of ``x`` without the ``fraction`` of values of largest magnitude (NaN when none)."""
    x = np.asarray(x, dtype=np.float64).ravel()
    x = x[np.isfinite(x)]
    keep = x.size - int(math.floor(fraction * x.size))
    if keep <= 0:
        return float("nan")
    return rmse(np.partition(np.abs(x), keep - 1)[:keep])


def incoherent_depth(radial_m: np.ndarray, valid: np.ndarray, limit_m: float,
                     window: int = COHERENCE_WINDOW_PX) -> np.ndarray:
    """Pixels whose depth does not agree with their neighbours': the robust spread (MAD x
    1.4826) of the valid depths in a ``window`` x ``window`` neighbourhood, or the pixel's own
    distance from their median, above ``limit_m``.

    A side's own noise that its frames' scatter does not show: a twin's pixel lit by no light
    of its own (a shadow lit only by multipath) gets a depth from its render's Monte Carlo
    noise, fixed over the frames but random from pixel to pixel. Median-based, it keeps an
    object's edge (at most a third of the window across it); a corner, or a line a pixel wide,
    at another depth is an outlier of its window, so callers apply it to dim pixels only."""
    d = np.where(valid & np.isfinite(radial_m), np.asarray(radial_m, np.float64), np.nan)
    h, w = d.shape
    r = window // 2
    padded = np.pad(d, r, constant_values=np.nan)
    stack = np.stack([padded[i:i + h, j:j + w] for i in range(window) for j in range(window)])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN neighbourhoods
        med = np.nanmedian(stack, axis=0)
        spread = MAD_TO_SIGMA * np.nanmedian(np.abs(stack - med), axis=0)
    enough = np.sum(np.isfinite(stack), axis=0) >= (window * window + 1) // 2
    outlier = np.abs(np.nan_to_num(d - med, nan=0.0)) > limit_m
    return valid & enough & ((np.nan_to_num(spread, nan=0.0) > limit_m) | outlier)


# ---------------------------------------------------------------------------- validity


@dataclass
class TapHealth:
    """Per-pixel flags of a session's raw taps over the frames used: any tap clipped, any
    tap NaN or infinite. Depth-only sessions have none (all False)."""

    saturated: np.ndarray
    nonfinite: np.ndarray

    @classmethod
    def none(cls, shape: tuple[int, int]) -> "TapHealth":
        return cls(np.zeros(shape, bool), np.zeros(shape, bool))

    @classmethod
    def from_taps(cls, taps: Iterable[np.ndarray], level: float | None = None,
                  declared: TapLimits | None = None) -> "TapHealth":
        """From raw tap arrays ``[F, K, H, W]`` (one per frame); clip levels by
        :func:`tofhil.demod.clip_limits` (``level``, else ``declared``, else detected)."""
        tmax = tmin = bad = None
        for t in taps:
            t = np.asarray(t, np.float64)
            fin = np.isfinite(t)
            hi = np.where(fin, t, -np.inf).max(axis=(0, 1))
            lo = np.where(fin, t, np.inf).min(axis=(0, 1))
            nf = ~fin.all(axis=(0, 1))
            tmax = hi if tmax is None else np.maximum(tmax, hi)
            tmin = lo if tmin is None else np.minimum(tmin, lo)
            bad = nf if bad is None else bad | nf
        if tmax is None:
            raise TofhilError("no frames", field="raw/taps", expected="at least one frame")
        limits = clip_limits(tmax, tmin, declared, level)
        return cls(bad_extremes(tmax, tmin, limits) & ~bad, bad)

    @property
    def invalid(self) -> np.ndarray:
        return self.saturated | self.nonfinite


def wrap_period(freq_hz: Sequence[float] | np.ndarray | None) -> float | None:
    """The unambiguous range [m] of single-frequency data (the depth residual wraps there);
    ``None`` for several frequencies (unwrapped distances compare directly) or unknown."""
    if freq_hz is None:
        return None
    f = np.atleast_1d(np.asarray(freq_hz, np.float64))
    if f.size != 1 or not (np.isfinite(f[0]) and f[0] > 0):
        return None
    from tofhil.demod import ambiguity_range_m

    return float(ambiguity_range_m(float(f[0])))


def wrapped_difference(a: np.ndarray, b: np.ndarray, period: float) -> np.ndarray:
    """``a - b`` on a circle of circumference ``period`` (distances near the wrap compare right)."""
    return (a - b + period / 2) % period - period / 2


# ---------------------------------------------------------------------------- residual maps


@dataclass
class ResidualMaps:
    """Per-pixel maps of A against B ``[H, W]``; NaN where a pixel is not valid in both."""

    depth_residual_m: np.ndarray       # A - B radial distance (wrapped when wrap_m is set)
    amplitude_difference: np.ndarray   # |A| - |B| (same units only when A and B share them)
    amplitude_ratio: np.ndarray        # |A| / |B|
    valid_a: np.ndarray
    valid_b: np.ndarray
    wrap_m: float | None = None
    health_a: TapHealth | None = None
    health_b: TapHealth | None = None
    #: Pixels valid in both whose depths were unwrapped to different intervals (several
    #: frequencies), and pixels without a signal above their noise on either side: counted
    #: and mapped, and left out of the depth figures (None: not tested).
    unwrap_error: np.ndarray | None = None
    no_signal: np.ndarray | None = None

    @property
    def valid_both(self) -> np.ndarray:
        return self.valid_a & self.valid_b

    @property
    def compared(self) -> np.ndarray:
        """The pixels the depth figures use: valid in both and carrying a measurement."""
        m = self.valid_both
        for flags in (self.unwrap_error, self.no_signal):
            if flags is not None:
                m = m & ~flags
        return m


#: Pixels below this fraction of the image's 99th-percentile amplitude are unlit (a shadow).
MIN_RELATIVE_AMPLITUDE = 1e-3


def lit_pixels(amplitude: np.ndarray | None, min_relative: float = MIN_RELATIVE_AMPLITUDE,
               regions: Sequence[np.ndarray] = ()) -> np.ndarray | None:
    """Pixels whose amplitude reaches ``min_relative`` of the 99th percentile of their own
    region (each mask of ``regions``, e.g. the scene's objects: a dark object is not a shadow
    of a bright one), elsewhere of the whole image: where no light arrives (a shadow) the
    phase means nothing. ``None`` without amplitudes."""
    if amplitude is None or min_relative <= 0:
        return None
    a = np.asarray(amplitude, np.float64)
    if not np.isfinite(a).any():
        return None
    a0 = np.nan_to_num(a)
    lit = a0 >= min_relative * np.nanpercentile(a, 99)
    for m in regions:
        m = np.asarray(m, bool)
        if m.shape == a.shape and np.isfinite(a[m]).any():
            lit[m] = a0[m] >= min_relative * np.nanpercentile(a[m], 99)
    return lit


def frame_validity(frame: DepthFrame, health: TapHealth | None = None) -> np.ndarray:
    """A frame's valid pixels: its own flag, a finite distance, and no clipped or non-finite tap."""
    v = np.asarray(frame.valid, bool) & np.isfinite(np.asarray(frame.radial_m, np.float64))
    if health is not None:
        v &= ~health.invalid
    return v


def residual_maps(a: DepthFrame, b: DepthFrame, *, wrap_m: float | None = None,
                  health_a: TapHealth | None = None, health_b: TapHealth | None = None,
                  freq_hz: Sequence[float] | np.ndarray | None = None,
                  noise_m: np.ndarray | None = None,
                  own_noise_m: tuple[np.ndarray | None, np.ndarray | None] | None = None) -> ResidualMaps:
    """Depth residual A - B (radial distance, whatever kind each frame stores), amplitude
    difference and ratio, on the pixels valid in both. With the modulation frequencies,
    pixels unwrapped to different intervals (several frequencies) and pixels without a
    signal above noise are flagged: with ``own_noise_m`` (each side's own depth noise per
    pixel, A's and B's), a pixel whose depth on either side is lost in that side's own noise,
    its frames' scatter or its neighbours' disagreement (:func:`incoherent_depth`); else,
    with ``noise_m`` (the residual's depth noise per pixel), one whose residual is."""
    check_aligned(a, b)
    va, vb = frame_validity(a, health_a), frame_validity(b, health_b)
    both = va & vb
    da, db = np.asarray(a.radial_m, np.float64), np.asarray(b.radial_m, np.float64)
    with np.errstate(invalid="ignore"):
        diff = wrapped_difference(da, db, wrap_m) if wrap_m else da - db
    res = np.where(both, diff, np.nan)
    adiff = np.full(res.shape, np.nan)
    ratio = np.full(res.shape, np.nan)
    if a.amplitude is not None and b.amplitude is not None:
        aa, ab = np.asarray(a.amplitude, np.float64), np.asarray(b.amplitude, np.float64)
        ok = both & np.isfinite(aa) & np.isfinite(ab)
        adiff[ok] = aa[ok] - ab[ok]
        ok &= ab > 0
        ratio[ok] = aa[ok] / ab[ok]
    unwrap_error = no_signal = None
    f = None if freq_hz is None else np.atleast_1d(np.asarray(freq_hz, np.float64))
    if f is not None and f.size and np.all(np.isfinite(f) & (f > 0)):
        from tofhil.demod import ambiguity_range_m

        shortest = float(ambiguity_range_m(float(f.max())))
        limit = NO_SIGNAL_FRACTION * shortest
        if own_noise_m is not None:
            no_signal = np.zeros(both.shape, bool)
            for frame, valid, own in ((a, va, own_noise_m[0]), (b, vb, own_noise_m[1])):
                if own is not None:
                    no_signal |= np.nan_to_num(np.asarray(own, np.float64), nan=0.0) > limit
                no_signal |= _dim(frame.amplitude) & incoherent_depth(np.asarray(frame.radial_m, np.float64),
                                                                      valid, limit)
            no_signal &= both
        elif noise_m is not None:
            no_signal = both & (np.nan_to_num(np.asarray(noise_m, np.float64), nan=0.0) > limit)
        if f.size >= 2:
            with np.errstate(invalid="ignore"):
                unwrap_error = both & (np.abs(np.nan_to_num(res)) > UNWRAP_ERROR_FRACTION * shortest)
            if no_signal is not None:
                unwrap_error &= ~no_signal
    return ResidualMaps(res, adiff, ratio, va, vb, wrap_m, health_a, health_b, unwrap_error, no_signal)


def _dim(amplitude: np.ndarray | None) -> np.ndarray | bool:
    """Pixels below :data:`DIM_FRACTION` of the frame's 99th-percentile amplitude (every pixel
    when the frame has no amplitude: its depth's coherence is all there is to go by)."""
    if amplitude is None:
        return True
    a = np.asarray(amplitude, np.float64)
    if not np.isfinite(a).any():
        return True
    return np.nan_to_num(a, nan=0.0) < DIM_FRACTION * np.nanpercentile(a, 99)


def check_aligned(a: DepthFrame, b: DepthFrame) -> dict[str, Any]:
    """Both frames must share the image size; differing intrinsics are reported, not fatal."""
    if a.camera.shape != b.camera.shape:
        raise TofhilError(f"images are {a.camera.shape} and {b.camera.shape}", field="camera",
                          expected="two sessions with the same camera model (pixel-aligned comparison)")
    same = (a.camera.fx, a.camera.fy, a.camera.cx, a.camera.cy, a.camera.distortion_model, a.camera.dist) == \
           (b.camera.fx, b.camera.fy, b.camera.cx, b.camera.cy, b.camera.distortion_model, b.camera.dist)
    return {"same_intrinsics": bool(same)}


# ---------------------------------------------------------------------------- cloud and NDT


@dataclass
class CloudMetrics:
    """A's points against B's (:func:`tofhil.eval.metrics.matching.cloud_metrics`), with ICP when asked."""

    chamfer: float
    hausdorff: float
    hausdorff_p95: float
    precision: float
    recall: float
    fscore: float
    threshold: float
    n_a: int
    n_b: int
    icp_inlier_rmse: float | None = None
    icp_fitness: float | None = None

    def to_json(self) -> dict[str, Any]:
        return json_safe(asdict(self))


@dataclass
class NdtMetrics:
    """A's points scored on B's NDT grid (:func:`tofhil.eval.metrics.ndt.ndt_score`)."""

    cell_size: float
    score_per_point: float
    nvtl: float
    mean_likelihood: float
    mean_likelihood_trilinear: float
    fraction_above: dict[str, float]
    cells: int
    n_points: int
    outlier_ratio: float

    def to_json(self) -> dict[str, Any]:
        return json_safe(asdict(self))


#: Fewer points than this in A or B: no cloud metrics (too few for normals and NDT cells).
MIN_CLOUD_POINTS = 10


def cloud_and_ndt(a: DepthFrame, b: DepthFrame, valid_a: np.ndarray, valid_b: np.ndarray, *,
                  cell_size: float, threshold: float, icp_max_distance: float | None = None
                  ) -> tuple[CloudMetrics | None, NdtMetrics | None, np.ndarray | None, str | None]:
    """Cloud metrics and NDT scores of A's points (pixels ``valid_a``) against B's.

    Returns the metrics, the per-pixel trilinear NDT likelihood of A's points (NaN where A
    has no point), and why they were skipped (``None`` when computed).
    """
    from tofhil.eval.metrics.matching import cloud_metrics, icp
    from tofhil.eval.metrics.ndt import ndt_score

    ma = a.camera.valid_mask(a.distance_m, valid_a)
    mb = b.camera.valid_mask(b.distance_m, valid_b)
    pa = a.camera.points(a.distance_m, a.kind, ma)
    pb = b.camera.points(b.distance_m, b.kind, mb)
    if len(pa) < MIN_CLOUD_POINTS or len(pb) < MIN_CLOUD_POINTS:
        return None, None, None, f"too few points (A {len(pa)}, B {len(pb)})"
    c = cloud_metrics(pa, pb, threshold=threshold)
    cloud = CloudMetrics(**{k: c[k] for k in ("chamfer", "hausdorff", "hausdorff_p95", "precision", "recall",
                                              "fscore", "threshold", "n_a", "n_b")})
    if icp_max_distance is not None:
        r = icp(pa, pb, icp_max_distance)
        cloud.icp_inlier_rmse, cloud.icp_fitness = r.inlier_rmse, r.fitness
    s = ndt_score(pb, pa, cell_size=cell_size)
    nd = NdtMetrics(cell_size=float(cell_size), score_per_point=s.score_per_point, nvtl=s.nvtl,
                    mean_likelihood=s.mean_likelihood, mean_likelihood_trilinear=s.mean_likelihood_trilinear,
                    fraction_above={repr(float(k)): float(v) for k, v in s.fraction_above.items()}, cells=s.cells,
                    n_points=s.n_points, outlier_ratio=s.outlier_ratio)
    lmap = np.full(a.camera.shape, np.nan)
    lmap[ma] = s.likelihood_trilinear
    return cloud, nd, lmap, None


# ---------------------------------------------------------------------------- regions


@dataclass
class RegionMetrics:
    """Every figure of one region of A against B."""

    name: str
    kind: str
    pixels: int
    valid_fraction_a: float
    valid_fraction_b: float
    valid_both_fraction: float
    saturated_fraction_a: float      # pixels with a clipped tap in A
    saturated_fraction_b: float
    nonfinite_fraction_a: float      # pixels with a NaN or infinite tap in A
    nonfinite_fraction_b: float
    depth_residual_m: Stats
    amplitude_difference: Stats
    amplitude_ratio: Stats
    cloud: CloudMetrics | None = None
    ndt: NdtMetrics | None = None
    cloud_skipped: str | None = None
    #: Depth noise of the residual expected from the averaged frames' scatter: the RMS over
    #: the region's compared pixels of sqrt(sigma_A^2 + sigma_B^2). The RMSE cannot go below it.
    noise_floor_m: float | None = None
    #: Pixels valid in both left out of the depth figures: unwrapped to different intervals,
    #: and without a signal above noise (None: not tested).
    unwrap_error_pixels: int | None = None
    no_signal_pixels: int | None = None

    @property
    def depth_rmse_m(self) -> float:
        """:data:`DEPTH_RMSE` of this region."""
        return self.depth_residual_m.rmse

    @property
    def saturation_dominated(self) -> bool:
        """More of the region is lost to clipped or non-finite taps than is compared."""
        lost = max(self.saturated_fraction_a + self.nonfinite_fraction_a,
                   self.saturated_fraction_b + self.nonfinite_fraction_b)
        return lost > 0 and lost >= self.valid_both_fraction

    def validity_note(self) -> str | None:
        """One line on clipped / non-finite taps, or ``None`` when there are none."""
        parts = []
        for side, sat, nf in (("A", self.saturated_fraction_a, self.nonfinite_fraction_a),
                              ("B", self.saturated_fraction_b, self.nonfinite_fraction_b)):
            if sat > 0:
                parts.append(f"{100 * sat:.1f} % of its pixels saturated in {side}")
            if nf > 0:
                parts.append(f"{100 * nf:.1f} % with non-finite taps in {side}")
        if not parts:
            return None
        line = f"{self.name}: " + ", ".join(parts) + f" (excluded; {100 * self.valid_both_fraction:.1f} % compared)"
        if self.saturation_dominated:
            line += (" -- dominated by saturation: no pixel left to compare" if self.valid_both_fraction == 0
                     else " -- dominated by saturation: its figures describe the few unsaturated pixels")
        return line

    def to_json(self) -> dict[str, Any]:
        d: dict[str, Any] = {k: getattr(self, k) for k in (
            "kind", "pixels", "valid_fraction_a", "valid_fraction_b", "valid_both_fraction",
            "saturated_fraction_a", "saturated_fraction_b", "nonfinite_fraction_a", "nonfinite_fraction_b")}
        d["saturation_dominated"] = self.saturation_dominated
        d["depth_residual_m"] = self.depth_residual_m.to_json()
        d["depth_rmse_m"] = self.depth_rmse_m
        d["amplitude_difference"] = self.amplitude_difference.to_json()
        d["amplitude_ratio"] = self.amplitude_ratio.to_json()
        d["amplitude_ratio_median"] = self.amplitude_ratio.median
        if self.cloud is not None:
            d["cloud"] = self.cloud.to_json()
        if self.ndt is not None:
            d["ndt"] = self.ndt.to_json()
        if self.cloud_skipped:
            d["cloud_skipped"] = self.cloud_skipped
        d["noise_floor_m"] = self.noise_floor_m
        d["unwrap_error_pixels"] = self.unwrap_error_pixels
        d["no_signal_pixels"] = self.no_signal_pixels
        d["depth_compared_pixels"] = self.depth_residual_m.n
        return json_safe(d)

    def excluded_note(self) -> str | None:
        """One line on the pixels valid in both that the depth figures leave out, or None."""
        parts = []
        if self.unwrap_error_pixels:
            parts.append(f"{self.unwrap_error_pixels} pixels unwrapped to the wrong interval (a phase inconsistency "
                         "between the frequencies or noise in them, not a surface)")
        if self.no_signal_pixels:
            parts.append(f"{self.no_signal_pixels} pixels without a signal above noise on one side (shadows, "
                         "dark surfaces, depths at random from pixel to pixel)")
        if not parts:
            return None
        return f"{self.name}: " + "; ".join(parts) + f": mapped and counted, not in the depth figures " \
            f"({self.depth_residual_m.n} pixels compared)"


def _fraction(flags: np.ndarray | None, mask: np.ndarray) -> float:
    n = int(mask.sum())
    if n == 0:
        return float("nan")
    return 0.0 if flags is None else float(np.count_nonzero(flags & mask)) / n


def noise_floor(noise_m: np.ndarray | None, mask: np.ndarray) -> float | None:
    """RMS of the per-pixel residual noise ``noise_m`` over ``mask`` (finite values); None
    without a noise map or a finite value."""
    if noise_m is None:
        return None
    x = np.asarray(noise_m, np.float64)[mask]
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(x * x))) if x.size else None


def region_metrics(maps: ResidualMaps, region: Region, noise_m: np.ndarray | None = None) -> RegionMetrics:
    """Statistics of the residual maps over one region's pixels valid in both; ``noise_m``
    the per-pixel standard deviation of the residual expected from noise (:func:`noise_floor`)."""
    r = region.mask
    m = r & maps.valid_both
    compared = r & maps.compared
    ha, hb = maps.health_a, maps.health_b
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return RegionMetrics(noise_floor_m=noise_floor(noise_m, compared),
            unwrap_error_pixels=None if maps.unwrap_error is None else int((maps.unwrap_error & r).sum()),
            no_signal_pixels=None if maps.no_signal is None else int((maps.no_signal & r).sum()),
            name=region.name, kind=region.kind, pixels=int(r.sum()),
            valid_fraction_a=_fraction(maps.valid_a, r), valid_fraction_b=_fraction(maps.valid_b, r),
            valid_both_fraction=_fraction(maps.valid_both, r),
            saturated_fraction_a=_fraction(None if ha is None else ha.saturated, r),
            saturated_fraction_b=_fraction(None if hb is None else hb.saturated, r),
            nonfinite_fraction_a=_fraction(None if ha is None else ha.nonfinite, r),
            nonfinite_fraction_b=_fraction(None if hb is None else hb.nonfinite, r),
            depth_residual_m=stats(maps.depth_residual_m[compared]),
            amplitude_difference=stats(maps.amplitude_difference[m]),
            amplitude_ratio=stats(maps.amplitude_ratio[m]))


@dataclass
class Evaluation:
    """A against B: the residual maps, every region's metrics, NDT likelihood map of "all"."""

    maps: ResidualMaps
    regions: dict[str, RegionMetrics]
    alignment: dict[str, Any]
    ndt_map: np.ndarray | None = field(default=None, repr=False)

    def to_json(self) -> dict[str, Any]:
        return json_safe({"alignment": self.alignment, "wrap_m": self.maps.wrap_m,
                          "regions": {k: v.to_json() for k, v in self.regions.items()}})

    def validity_notes(self) -> list[str]:
        """Clipped or non-finite taps, and pixels valid in both that carry no comparable depth."""
        notes = [n for n in (r.validity_note() for r in self.regions.values()) if n]
        return notes + [n for n in (r.excluded_note() for r in self.regions.values()) if n]


def evaluate(a: DepthFrame, b: DepthFrame, regions: Sequence[Region] = (), *, wrap_m: float | None = None,
             health_a: TapHealth | None = None, health_b: TapHealth | None = None,
             cloud_regions: bool | Sequence[str] = False, cell_size: float = 0.1, threshold: float = 0.01,
             icp_max_distance: float | None = None, include_all: bool = True,
             source: str | None = None, noise_m: np.ndarray | None = None,
             freq_hz: Sequence[float] | np.ndarray | None = None,
             own_noise_m: tuple[np.ndarray | None, np.ndarray | None] | None = None) -> Evaluation:
    """Evaluate A against B over the whole image (unless ``include_all=False``) and ``regions``.

    ``cloud_regions``: True for cloud and NDT metrics in every region, or the names of the
    regions that get them. Refuses a pair with no pixel valid in both (``source`` names it).
    ``noise_m``: per-pixel standard deviation of the residual expected from noise; each
    region then reports its noise floor. ``freq_hz``: the modulation frequencies, for the
    pixels that carry no comparable depth (:func:`residual_maps`, also for ``own_noise_m``).
    """
    if not threshold > 0 or not math.isfinite(threshold):
        raise TofhilError(f"is {threshold}", field="threshold", expected="a positive distance in metres")
    if not cell_size > 0 or not math.isfinite(cell_size):
        raise TofhilError(f"is {cell_size}", field="cell_size", expected="a positive length in metres")
    alignment = check_aligned(a, b)
    maps = residual_maps(a, b, wrap_m=wrap_m, health_a=health_a, health_b=health_b, freq_hz=freq_hz, noise_m=noise_m,
                         own_noise_m=own_noise_m)
    if not maps.valid_both.any():
        why = []
        for side, v in (("A", maps.valid_a), ("B", maps.valid_b)):
            if not v.any():
                why.append(f"{side} has no valid pixel")
        raise TofhilError("no pixel is valid in both A and B" + (f" ({', '.join(why)})" if why else ""),
                          file=source, field="depth/valid",
                          expected="two captures of the same view with finite, unsaturated pixels")
    regs = ([whole_image(a.camera.shape)] if include_all else []) + list(regions)
    names = [r.name for r in regs]
    if len(set(names)) != len(names):
        raise TofhilError(f"region names repeat: {', '.join(sorted({n for n in names if names.count(n) > 1}))}",
                          field="regions", expected="distinct region names")
    out: dict[str, RegionMetrics] = {}
    ndt_map = None
    for r in regs:
        rm = region_metrics(maps, r, noise_m)
        wanted = cloud_regions is True or (not isinstance(cloud_regions, bool) and r.name in cloud_regions)
        if wanted:
            cloud, nd, lmap, skipped = cloud_and_ndt(a, b, maps.valid_a & r.mask, maps.valid_b & r.mask,
                                                     cell_size=cell_size, threshold=threshold,
                                                     icp_max_distance=icp_max_distance)
            rm.cloud, rm.ndt, rm.cloud_skipped = cloud, nd, skipped
            if ndt_map is None and lmap is not None:
                ndt_map = lmap
        out[r.name] = rm
    return Evaluation(maps, out, alignment, ndt_map)


# ---------------------------------------------------------------------------- frames


def mean_depth_frame(frames: Iterable[DepthFrame], min_valid_fraction: float = 0.5) -> tuple[DepthFrame, np.ndarray]:
    """Temporal mean of a session's depth frames and the per-pixel temporal std of distance.

    A pixel is valid in the mean where it was valid (and finite) in at least
    ``min_valid_fraction`` of the frames; averaging is over its valid frames only.
    """
    n = 0
    acc = acc2 = cnt = amp = None
    first: DepthFrame | None = None
    for f in frames:
        d = np.asarray(f.radial_m, np.float64)
        v = np.asarray(f.valid, bool) & np.isfinite(d)
        if first is None:
            first = f
            acc, acc2, cnt, amp = (np.zeros(d.shape) for _ in range(4))
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
