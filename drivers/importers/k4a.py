"""Azure Kinect recordings (Matroska, as written by k4arecorder) -> depth frames + camera model.

What the file holds (Azure Kinect SDK, ``docs/recording.md`` and ``src/record``):
* tracks ``DEPTH`` and ``IR``: ``V_MS/VFW/FOURCC`` with fourcc ``b16g`` = 16-bit
  grey, **big-endian** (verified on the shipped recording: decoding big-endian gives 1 mm
  steps between neighbours, little-endian gives 256 mm), depth in millimetres, 0 = invalid;
* tags ``K4A_DEPTH_MODE`` (e.g. ``NFOV_UNBINNED``), serial number, firmware versions and
  ``K4A_START_OFFSET_NS`` (block timestamps are device timestamps minus this offset);
* the attachment ``calibration.json``: factory intrinsics of the 1024 x 1024 depth sensor,
  normalised by the sensor size, in the order of ``k4a_calibration_intrinsic_parameters_t``:
  ``cx cy fx fy k1 k2 k3 k4 k5 k6 codx cody p2 p1`` (note p2 before p1).

Physics: Azure Kinect depth is **z-depth** (along the optical axis):
``transformation_unproject`` in the SDK returns ``(x*z, y*z, z)``. tofhil sessions store
radial distance, so ``radial = z * |(x, y, 1)|`` with ``(x, y)`` the undistorted
normalised coordinates of each pixel under the full factory model.

Lens model: the factory model is Brown-Conrady with a *rational* radial term
``(1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4 + k6 r^6)``: OpenCV's rational model,
which the session's camera holds exactly (``model: rational``, ``dist = (k1, k2, p1, p2, k3,
k4, k5, k6)``). Only a calibration with a centre of distortion ``(codx, cody)`` off the
principal point (the SDK's BrownConrady model leaves it at 0) is not an OpenCV model; it is
refitted to ``(k1, k2, p1, p2, k3)`` by linear least squares so that the 5-parameter model maps
each pixel's true ray back onto that pixel. Either way the largest and RMS reprojection
residual in pixels are reported, the original calibration is kept verbatim in the session's
device JSON, and the radial distances are computed with the exact factory model.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from tofhil.camera import CameraModel
from tofhil.drivers.importers.mkv import BlockRef, MatroskaFile, Track, open_mkv
from tofhil.errors import InputFileError

#: Depth modes: (calibration image binned resolution, crop offset, output resolution),
#: from the SDK's ``transformation_get_mode_specific_depth_camera_calibration``.
DEPTH_MODES: dict[str, tuple[tuple[int, int], tuple[int, int], tuple[int, int]]] = {
    "NFOV_2X2BINNED": ((512, 512), (96, 90), (320, 288)),
    "NFOV_UNBINNED": ((1024, 1024), (192, 180), (640, 576)),
    "WFOV_2X2BINNED": ((512, 512), (0, 0), (512, 512)),
    "WFOV_UNBINNED": ((1024, 1024), (0, 0), (1024, 1024)),
    "PASSIVE_IR": ((1024, 1024), (0, 0), (1024, 1024)),
}

PARAM_NAMES = ("cx", "cy", "fx", "fy", "k1", "k2", "k3", "k4", "k5", "k6", "codx", "cody", "p2", "p1")


@dataclass(frozen=True)
class K4AIntrinsics:
    """The factory depth-camera model in pixels of one depth mode (OpenCV pixel centres)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    k: tuple[float, float, float, float, float, float]
    p1: float
    p2: float
    codx: float = 0.0
    cody: float = 0.0
    metric_radius: float = math.inf

    def distort(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Undistorted normalised -> distorted normalised (the SDK's Brown-Conrady projection)."""
        k1, k2, k3, k4, k5, k6 = self.k
        xp, yp = x - self.codx, y - self.cody
        rs = xp * xp + yp * yp
        d = (1 + rs * (k1 + rs * (k2 + rs * k3))) / (1 + rs * (k4 + rs * (k5 + rs * k6)))
        xd = xp * d + (rs + 2 * xp * xp) * self.p2 + 2 * xp * yp * self.p1 + self.codx
        yd = yp * d + (rs + 2 * yp * yp) * self.p1 + 2 * xp * yp * self.p2 + self.cody
        return xd, yd

    def camera_model(self, name: str = "") -> CameraModel | None:
        """The factory model as OpenCV's rational model, exactly; None when the centre of
        distortion is off the principal point (no OpenCV model has that term)."""
        if self.codx != 0.0 or self.cody != 0.0:
            return None
        k1, k2, k3, k4, k5, k6 = self.k
        return CameraModel(width=self.width, height=self.height, fx=self.fx, fy=self.fy, cx=self.cx, cy=self.cy,
                           dist=(k1, k2, self.p1, self.p2, k3, k4, k5, k6), distortion_model="rational", name=name)

    def undistort(self, u: np.ndarray, v: np.ndarray, iters: int = 50) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Pixel -> undistorted normalised coordinates and a validity mask.

        Gauss-Newton on the forward model, vectorised over all pixels (numerical 2x2
        Jacobian); a pixel is valid when it converges to < 1e-3 px and lies inside the
        calibration's metric radius, as in the SDK.
        """
        xd = (np.asarray(u, float) - self.cx) / self.fx
        yd = (np.asarray(v, float) - self.cy) / self.fy
        x, y = xd.copy(), yd.copy()
        h = 1e-6
        for _ in range(iters):
            fx_, fy_ = self.distort(x, y)
            ex, ey = xd - fx_, yd - fy_
            if np.nanmax(np.abs(ex) + np.abs(ey), initial=0.0) < 1e-12:
                break  # converged everywhere (Newton: a handful of iterations)
            ax, ay = self.distort(x + h, y)
            bx, by = self.distort(x, y + h)
            j00, j10 = (ax - fx_) / h, (ay - fy_) / h
            j01, j11 = (bx - fx_) / h, (by - fy_) / h
            det = j00 * j11 - j01 * j10
            det = np.where(np.abs(det) < 1e-12, 1e-12, det)
            x = x + (j11 * ex - j01 * ey) / det
            y = y + (-j10 * ex + j00 * ey) / det
        fx_, fy_ = self.distort(x, y)
        err_px = np.hypot((fx_ - xd) * self.fx, (fy_ - yd) * self.fy)
        valid = np.isfinite(err_px) & (err_px < 1e-3) & (x * x + y * y <= self.metric_radius ** 2)
        return x, y, valid


#: How the session's camera was made from the factory model (the device JSON's ``camera_fit``).
EXACT_METHOD = "the factory rational Brown-Conrady model as OpenCV's rational model (k1..k6, p1, p2), exactly"
REFIT_METHOD = ("OpenCV (k1,k2,p1,p2,k3) least-squares refit of the factory rational Brown-Conrady model "
                "(its centre of distortion is off the principal point); fx, fy, cx, cy kept")


@dataclass
class CameraFit:
    camera: CameraModel
    max_residual_px: float
    rms_residual_px: float
    n_pixels: int
    method: str = REFIT_METHOD

    def to_dict(self) -> dict[str, Any]:
        return {"method": self.method,
                "max_residual_px": self.max_residual_px, "rms_residual_px": self.rms_residual_px,
                "pixels_fitted": self.n_pixels}


@dataclass
class K4ARecording:
    path: Path
    depth_mode: str
    intrinsics: K4AIntrinsics
    fit: CameraFit
    calibration: dict[str, Any]
    tags: dict[str, str]
    #: The open file and, per frame, (timestamp_s, depth block, IR block or None); frames are
    #: decoded only when iterated, so long recordings are not held in memory.
    mkv: MatroskaFile
    depth_track: Track
    ir_track: Track | None
    refs: list[tuple[float, BlockRef, BlockRef | None]] = field(default_factory=list)
    truncated: str = ""

    @property
    def camera(self) -> CameraModel:
        return self.fit.camera

    def __len__(self) -> int:
        return len(self.refs)

    def frame(self, i: int) -> tuple[float, np.ndarray, np.ndarray | None]:
        """(timestamp_s, depth z in mm uint16 [H, W], IR uint16 [H, W] or None) of frame ``i``."""
        t, dblk, iblk = self.refs[i]
        depth = _decode_b16g(self.mkv, self.depth_track, self.mkv.payload(dblk), "depth")
        ir = None
        if iblk is not None and self.ir_track is not None:
            ir = _decode_b16g(self.mkv, self.ir_track, self.mkv.payload(iblk), "IR")
        return t, depth, ir

    def iter_frames(self) -> Iterator[tuple[float, np.ndarray, np.ndarray | None]]:
        for i in range(len(self.refs)):
            yield self.frame(i)

    @property
    def frames(self) -> list[tuple[float, np.ndarray, np.ndarray | None]]:
        """Every frame decoded (convenient for short recordings; use ``iter_frames`` otherwise)."""
        return list(self.iter_frames())

    def close(self) -> None:
        self.mkv.close()

    def __enter__(self) -> "K4ARecording":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def radial_m(self, z_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """z-depth in mm -> (radial distance in m, valid mask) with the exact factory rays."""
        norm, ok = self._ray_norm
        z = z_mm.astype(np.float64) * 1e-3
        valid = (z_mm > 0) & ok
        return np.where(valid, z * norm, 0.0), valid

    @property
    def _ray_norm(self) -> tuple[np.ndarray, np.ndarray]:
        if not hasattr(self, "_norm_cache"):
            v, u = np.mgrid[0:self.intrinsics.height, 0:self.intrinsics.width].astype(np.float64)
            x, y, ok = self.intrinsics.undistort(u, v)
            self._norm_cache = (np.sqrt(x * x + y * y + 1.0), ok)
        return self._norm_cache


def intrinsics_from_calibration(calib: dict[str, Any], depth_mode: str, *, source: Path) -> K4AIntrinsics:
    """The depth camera of ``calibration.json`` in pixels of ``depth_mode``."""
    try:
        cams = calib["CalibrationInformation"]["Cameras"]
    except (KeyError, TypeError):
        raise InputFileError("missing", file=source, field="calibration.json:CalibrationInformation.Cameras",
                             expected="the Azure Kinect factory calibration") from None
    depth = [c for c in cams if isinstance(c, dict) and c.get("Purpose") == "CALIBRATION_CameraPurposeDepth"]
    if not depth:
        raise InputFileError("no camera with Purpose CALIBRATION_CameraPurposeDepth", file=source,
                             field="calibration.json:Cameras[].Purpose", expected="a depth camera entry")
    cam = depth[0]
    intr = cam.get("Intrinsics", {})
    params = intr.get("ModelParameters")
    model = intr.get("ModelType", "")
    if model != "CALIBRATION_LensDistortionModelBrownConrady":
        raise InputFileError(f"lens model {model!r}", file=source,
                             field="calibration.json:Cameras[depth].Intrinsics.ModelType",
                             expected="CALIBRATION_LensDistortionModelBrownConrady")
    if not isinstance(params, list) or len(params) < 14:
        raise InputFileError(f"has {len(params) if isinstance(params, list) else params!r} values",
                             file=source, field="calibration.json:Cameras[depth].Intrinsics.ModelParameters",
                             expected="14 numbers (cx cy fx fy k1..k6 codx cody p2 p1)")
    try:
        p = dict(zip(PARAM_NAMES, (float(v) for v in params[:14])))
    except (TypeError, ValueError):
        p = {}
    if len(p) != 14 or not all(math.isfinite(v) for v in p.values()) or p["fx"] <= 0 or p["fy"] <= 0:
        raise InputFileError(f"has unusable values {params[:14]!r}", file=source,
                             field="calibration.json:Cameras[depth].Intrinsics.ModelParameters",
                             expected="14 finite numbers with fx, fy > 0")
    if depth_mode not in DEPTH_MODES:
        raise InputFileError(f"depth mode {depth_mode!r}", file=source, field="K4A_DEPTH_MODE",
                             expected=" | ".join(DEPTH_MODES))
    if (cam.get("SensorWidth"), cam.get("SensorHeight")) != (1024, 1024):
        raise InputFileError(f"sensor is {cam.get('SensorWidth')}x{cam.get('SensorHeight')}", file=source,
                             field="calibration.json:Cameras[depth].SensorWidth", expected="1024 x 1024")
    (bw, bh), (ox, oy), (w, h) = DEPTH_MODES[depth_mode]
    # Raw calibration is unitised with (0, 0) at the corner of the first pixel; convert to
    # pixels with (0, 0) at the first pixel's centre, then crop (the SDK's conversion).
    return K4AIntrinsics(width=w, height=h, fx=p["fx"] * bw, fy=p["fy"] * bh,
                         cx=p["cx"] * bw - ox - 0.5, cy=p["cy"] * bh - oy - 0.5,
                         k=(p["k1"], p["k2"], p["k3"], p["k4"], p["k5"], p["k6"]), p1=p["p1"], p2=p["p2"],
                         codx=p["codx"], cody=p["cody"],
                         metric_radius=float(cam.get("MetricRadius") or math.inf))


def factory_camera(intr: K4AIntrinsics, name: str = "azure_kinect_depth", step: int = 2,
                   support: np.ndarray | None = None) -> CameraFit:
    """The session's camera of the factory model: exact (rational) when OpenCV can hold it,
    else :func:`fit_opencv_model`; residuals of the factory rays reprojected, in pixels, over
    the pixels that see anything (``support``) inside the metric radius."""
    cam = intr.camera_model(name)
    if cam is None:
        return fit_opencv_model(intr, name, step, support)
    v, u = np.mgrid[0:intr.height:step, 0:intr.width:step].astype(np.float64)
    x, y, ok = intr.undistort(u, v)
    if support is not None and support[::step, ::step].sum() > 1000:
        ok &= support[::step, ::step]
    uv = cam.project(np.stack([x[ok], y[ok], np.ones(int(ok.sum()))], axis=1))
    res = np.hypot(uv[:, 0] - u[ok], uv[:, 1] - v[ok])
    return CameraFit(cam, float(res.max(initial=0.0)), float(np.sqrt(np.mean(res ** 2))) if res.size else 0.0,
                     int(res.size), EXACT_METHOD)


def fit_opencv_model(intr: K4AIntrinsics, name: str = "azure_kinect_depth", step: int = 2,
                     support: np.ndarray | None = None) -> CameraFit:
    """Refit OpenCV (k1, k2, p1, p2, k3) to the factory model; residuals in pixels.

    For each pixel's true undistorted coordinates (x, y), the 5-parameter forward model is
    linear in its coefficients: ``xd - x = k1 x r^2 + k2 x r^4 + k3 x r^6 + 2 p1 x y + p2 (r^2 + 2x^2)``
    (and likewise for y), so the refit is one linear least-squares solve, weighted by the
    focal lengths so that the residual is in pixels. ``support`` ([H, W] bool, optional)
    restricts the fit to pixels that can see anything (the NFOV modes have a hexagonal
    field of view; their image corners never carry depth), when it covers enough pixels.
    """
    v, u = np.mgrid[0:intr.height:step, 0:intr.width:step].astype(np.float64)
    x, y, ok = intr.undistort(u, v)
    if support is not None and support[::step, ::step].sum() > 1000:
        ok &= support[::step, ::step]
    x, y, u, v = x[ok], y[ok], u[ok], v[ok]
    if x.size < 100:
        raise InputFileError("the factory lens model leaves fewer than 100 valid pixels",
                             field="calibration.json", expected="a usable depth camera calibration")
    xd, yd = (u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy
    r2 = x * x + y * y
    # columns: k1, k2, p1, p2, k3
    ax = np.stack([x * r2, x * r2 ** 2, 2 * x * y, r2 + 2 * x * x, x * r2 ** 3], axis=1) * intr.fx
    ay = np.stack([y * r2, y * r2 ** 2, r2 + 2 * y * y, 2 * x * y, y * r2 ** 3], axis=1) * intr.fy
    a = np.concatenate([ax, ay])
    b = np.concatenate([(xd - x) * intr.fx, (yd - y) * intr.fy])
    coef, *_ = np.linalg.lstsq(a, b, rcond=None)
    k1, k2, p1, p2, k3 = (float(c) for c in coef)
    cam = CameraModel(width=intr.width, height=intr.height, fx=intr.fx, fy=intr.fy, cx=intr.cx, cy=intr.cy,
                      dist=(k1, k2, p1, p2, k3), name=name)
    # Residual: project the true rays with the refit model and compare to the pixel.
    uv = cam.project(np.stack([x, y, np.ones_like(x)], axis=1))
    res = np.hypot(uv[:, 0] - u, uv[:, 1] - v)
    return CameraFit(cam, float(res.max()), float(np.sqrt(np.mean(res ** 2))), int(x.size))


def _decode_b16g(mkv: MatroskaFile, track: Track, payload: bytes, what: str) -> np.ndarray:
    expected = track.width * track.height * 2
    if len(payload) != expected:
        raise InputFileError(f"a {what} frame has {len(payload)} bytes", file=mkv.path,
                             field=f"track {track.name}",
                             expected=f"{expected} ({track.width} x {track.height} x uint16 big-endian)")
    # b16g is big-endian; convert to native uint16 in one vectorised step.
    return np.frombuffer(payload, dtype=">u2").reshape(track.height, track.width).astype(np.uint16)


def read_k4a_recording(path: str | Path, *, max_frames: int | None = None,
                       salvage: bool = False) -> K4ARecording:
    """Read an Azure Kinect recording: depth (+ IR) frames, tags and the depth camera.

    ``salvage``: a recording cut short keeps its complete frames (otherwise a truncated
    file is an error). The recording keeps the file open (frames are decoded on demand):
    use it as a context manager or call ``close()``.
    """
    path = Path(path)
    mkv = open_mkv(path)
    try:
        return _read(mkv, path, max_frames, salvage)
    except BaseException:
        mkv.close()
        raise


def _read(mkv: MatroskaFile, path: Path, max_frames: int | None, salvage: bool) -> K4ARecording:
    if mkv.truncated and not salvage:
        raise InputFileError(f"is truncated: {mkv.truncation}", file=path, field="Segment",
                             expected="a complete recording (pass --salvage to import its complete frames)")
    tags = dict(mkv.tags)
    for t in mkv.track_tags.values():
        tags.update(t)
    depth_t = mkv.track_by_name("DEPTH")
    if depth_t is None:
        raise InputFileError("has no track named DEPTH", file=path, field="Tracks.TrackEntry.Name",
                             expected="an Azure Kinect recording with a depth track")
    if depth_t.fourcc != "b16g":
        raise InputFileError(f"depth codec is {depth_t.codec_id or 'unknown'} {depth_t.fourcc!r}", file=path,
                             field="DEPTH.CodecPrivate", expected="raw video, fourcc 'b16g' (uint16 big-endian)")
    ir_t = mkv.track_by_name("IR")
    if ir_t is not None and ir_t.fourcc != "b16g":
        ir_t = None  # passive/other IR encodings are not amplitude; leave it out
    calib_name = tags.get("K4A_CALIBRATION_FILE", "calibration.json")
    if calib_name not in mkv.attachments:
        raise InputFileError(f"has no attachment {calib_name!r}", file=path, field="Attachments",
                             expected="the factory calibration attachment written by k4arecorder")
    try:
        calib = json.loads(mkv.attachments[calib_name].decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputFileError(f"is not valid JSON ({exc})", file=path, field=f"attachment {calib_name}",
                             expected="JSON text") from None
    mode = tags.get("K4A_DEPTH_MODE", "")
    if not mode:
        mode = {(640, 576): "NFOV_UNBINNED", (320, 288): "NFOV_2X2BINNED", (512, 512): "WFOV_2X2BINNED",
                (1024, 1024): "WFOV_UNBINNED"}.get((depth_t.width, depth_t.height), "")
    intr = intrinsics_from_calibration(calib, mode, source=path)
    if (intr.width, intr.height) != (depth_t.width, depth_t.height):
        raise InputFileError(f"depth track is {depth_t.width}x{depth_t.height}", file=path,
                             field="DEPTH.Video.PixelWidth",
                             expected=f"{intr.width}x{intr.height} for depth mode {mode}")
    try:
        offset_s = float(tags.get("K4A_START_OFFSET_NS", "0") or 0) * 1e-9
    except ValueError:
        raise InputFileError(f"is {tags.get('K4A_START_OFFSET_NS')!r}", file=path, field="K4A_START_OFFSET_NS",
                             expected="an integer number of nanoseconds") from None
    ir_by_time = {b.pts: b for b in mkv.frames(ir_t)} if ir_t is not None else {}
    refs = []
    for blk in mkv.frames(depth_t):
        if max_frames is not None and len(refs) >= max_frames:
            break
        # Block times are device times minus the recording's start offset.
        refs.append((blk.time_s + offset_s, blk, ir_by_time.get(blk.pts)))
    if not refs:
        raise InputFileError("has no complete depth frame", file=path, field="DEPTH",
                             expected="at least one depth block")
    rec = K4ARecording(path=path, depth_mode=mode, intrinsics=intr,
                       fit=CameraFit(CameraModel(width=intr.width, height=intr.height, fx=intr.fx, fy=intr.fy,
                                                 cx=intr.cx, cy=intr.cy), math.nan, math.nan, 0),
                       calibration=calib, tags=tags, mkv=mkv, depth_track=depth_t, ir_track=ir_t, refs=refs,
                       truncated=mkv.truncation)
    # Fit the lens where the sensor sees anything (any of the first frames has depth there).
    support = np.zeros((intr.height, intr.width), bool)
    for i in range(min(len(refs), 30)):
        support |= rec.frame(i)[1] > 0
    rec.fit = factory_camera(intr, support=support)
    return rec
