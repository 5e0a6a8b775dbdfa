"""Camera calibration from amplitude images of a board: intrinsics and OpenCV distortion.

Each view is one session (one board pose); its frames' amplitudes are averaged (the board
does not move, the noise does). The board is found in every view (:mod:`tofhil.targets`),
``cv2.calibrateCameraExtended`` fits the intrinsics and the distortion of the chosen model to
all views at once, and views whose reprojection error stands out are rejected (each with its
reason) before the final fit. The result is a :class:`tofhil.camera.CameraModel` written as
a camera preset (``configs/cameras/*.yaml`` layout) that scenes and ``load_camera_preset`` read.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from tofhil.boards import BoardSpec
from tofhil.camera import CameraModel
from tofhil.errors import TofhilError
from tofhil.targets import BoardDetection, amplitude_image, detect_board, opencv_points
from tofhil.progress import Progress

#: Distortion models: the coefficients fitted. ``none`` .. ``full``: of plumb_bob's (k1, k2, p1,
#: p2, k3); ``rational``: OpenCV's rational model (``CALIB_RATIONAL_MODEL``: k1..k6, p1, p2);
#: ``thin_prism``: rational + thin prism (``CALIB_THIN_PRISM_MODEL``: s1..s4 too); ``fisheye``:
#: ``cv2.fisheye.calibrate`` (k1..k4, equidistant).
DISTORTION_MODELS = {"none": (), "k1": ("k1",), "k1k2": ("k1", "k2"), "k1k2p": ("k1", "k2", "p1", "p2"),
                     "full": ("k1", "k2", "p1", "p2", "k3"),
                     "rational": ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
                     "thin_prism": ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4"),
                     "fisheye": ("k1", "k2", "k3", "k4")}
#: The camera model (tofhil.lens_models) each calibration model gives.
CAMERA_MODEL = {"rational": "rational", "thin_prism": "rational", "fisheye": "fisheye"}
#: OpenCV's order of calibrateCameraExtended's standard deviations after fx, fy, cx, cy.
_STD_NAMES = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4", "tau_x", "tau_y")
#: Fewest views a calibration accepts (each view gives a homography: 3 fix the intrinsics).
MIN_VIEWS = 3
#: Fewest corners for a view to take part.
MIN_CORNERS = 6
#: A view is rejected when its RMS reprojection error exceeds this many times the median
#: view's (and ``max_view_error_px``).
OUTLIER_FACTOR = 3.0


@dataclass
class CalibrationView:
    """One view's part in the calibration."""

    name: str
    corners: int = 0
    rms_px: float = float("nan")
    used: bool = False
    reason: str = ""                  # why the view was rejected ("" when used)
    board_to_camera: np.ndarray | None = field(default=None, repr=False)
    detection: BoardDetection | None = field(default=None, repr=False)

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "corners": self.corners,
                "rms_px": None if not np.isfinite(self.rms_px) else round(float(self.rms_px), 4),
                "used": self.used, "reason": self.reason}


@dataclass
class CameraCalibration:
    """The fitted camera, the overall RMS reprojection error and every view's part."""

    camera: CameraModel
    rms_px: float
    views: list[CalibrationView]
    model: str
    std_intrinsics: dict[str, float]    # 1-sigma of fx, fy, cx, cy and the fitted coefficients

    @property
    def used(self) -> list[CalibrationView]:
        return [v for v in self.views if v.used]

    def to_dict(self) -> dict[str, Any]:
        return {"camera": self.camera.to_dict(), "rms_px": round(self.rms_px, 5), "model": self.model,
                "std": {k: float(v) for k, v in self.std_intrinsics.items()},
                "views": [v.to_dict() for v in self.views]}


def mean_amplitude(session_path: str | Path) -> tuple[np.ndarray, CameraModel]:
    """The average amplitude of a session's frames (NaN where no frame was valid) and its
    camera (with the session's modulation frequencies among its preset facts)."""
    from tofhil.depth import depth_from_raw
    from tofhil.session import open_session

    with open_session(session_path) as s:
        if s.n_frames == 0:
            raise TofhilError("has no frames", file=session_path, expected="a session with frames")
        total = np.zeros(s.camera.shape)
        count = np.zeros(s.camera.shape)
        for i in range(s.n_frames):
            frame = s.depth_frame(i) if s.has_depth else depth_from_raw(s.raw_frame(i))
            if frame.amplitude is None:
                raise TofhilError("has no amplitude", file=session_path, field="depth/amplitude",
                                  expected="a session with amplitude images (depth/amplitude or raw taps)")
            a = amplitude_image(frame)
            ok = np.isfinite(a)
            total[ok] += a[ok]
            count[ok] += 1
        camera = s.camera
        if s.has_raw and "freq_hz" not in camera.extra:
            # the preset written from it says which frequencies the camera ran at
            camera = replace(camera, extra=dict(camera.extra, freq_hz=[float(f) for f in s.freq_hz]))
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(count > 0, total / np.maximum(count, 1), np.nan), camera


def _flags(model: str) -> int:
    import cv2

    if model == "rational":
        return cv2.CALIB_RATIONAL_MODEL
    if model == "thin_prism":
        return cv2.CALIB_RATIONAL_MODEL | cv2.CALIB_THIN_PRISM_MODEL
    fitted = set(DISTORTION_MODELS[model])
    flags = 0
    for name, flag in (("k1", cv2.CALIB_FIX_K1), ("k2", cv2.CALIB_FIX_K2), ("k3", cv2.CALIB_FIX_K3)):
        if name not in fitted:
            flags |= flag
    if "p1" not in fitted:
        flags |= cv2.CALIB_ZERO_TANGENT_DIST
    return flags


def calibrate_camera(images: Sequence[tuple[str, np.ndarray]], target: BoardSpec | str | dict, *,
                     base: CameraModel | None = None, model: str = "k1k2p", max_view_error_px: float = 1.0,
                     progress: Progress | None = None) -> CameraCalibration:
    """Intrinsics and distortion from amplitude images ``[(name, image), ...]`` of a board.

    ``base`` gives the image size and the facts kept in the result (name, pixel pitch,
    preset extras such as the modulation frequencies). A view is rejected when the board is
    not found, has fewer than ``MIN_CORNERS`` corners, or (after a first fit over all views)
    its RMS reprojection error exceeds both ``max_view_error_px`` and ``OUTLIER_FACTOR``
    times the median view's; the final fit uses the rest. Raises :class:`TofhilError` when
    fewer than ``MIN_VIEWS`` views remain.
    """
    import cv2

    spec = BoardSpec.parse(target)
    if model not in DISTORTION_MODELS:
        raise TofhilError(f"unknown distortion model {model!r}", field="--model",
                          expected="one of " + ", ".join(DISTORTION_MODELS))
    if not images:
        raise TofhilError("no views", field="SESSIONS", expected=f"at least {MIN_VIEWS} views of the board")
    h, w = np.asarray(images[0][1]).shape
    if base is not None and (base.width, base.height) != (w, h):
        raise TofhilError(f"image is {w}x{h}, camera is {base.width}x{base.height}", field="camera")
    views: list[CalibrationView] = []
    it = progress(images, len(images), "detect board") if progress is not None else images
    for name, img in it:
        v = CalibrationView(name=name)
        views.append(v)
        if np.asarray(img).shape != (h, w):
            v.reason = f"image is {np.asarray(img).shape[1]}x{np.asarray(img).shape[0]}, the first view {w}x{h}"
            continue
        det = detect_board(img, spec)
        if det is None:
            v.reason = f"no {spec.kind} {spec.cols}x{spec.rows} board found"
            continue
        v.corners, v.detection = det.n, det
        if det.n < MIN_CORNERS:
            v.reason = f"only {det.n} corners (fewer than {MIN_CORNERS})"
            continue
        v.used = True
    flags = _flags(model)
    result = None
    for _ in range(2):  # fit all found views; drop outliers once and fit again
        used = [v for v in views if v.used]
        if len(used) < MIN_VIEWS:
            raise TofhilError(f"only {len(used)} usable views of {len(views)} "
                              f"({'; '.join(f'{v.name}: {v.reason}' for v in views if not v.used) or 'none rejected'})",
                              field="SESSIONS", expected=f"at least {MIN_VIEWS} views with the whole board in sight")
        obj = [v.detection.object_points.astype(np.float32) for v in used]
        img = [v.detection.image_points.astype(np.float32) for v in used]
        if model == "fisheye":
            result = _fisheye_calibrate(obj, img, (w, h), base)
        else:
            result = cv2.calibrateCameraExtended(obj, img, (w, h), None, None, flags=flags,
                                                 criteria=(cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12))
        per_view = np.asarray(result[7]).ravel()
        for v, e in zip(used, per_view):
            v.rms_px = float(e)
        limit = max(max_view_error_px, OUTLIER_FACTOR * float(np.median(per_view)))
        bad = [v for v in used if v.rms_px > limit]
        if not bad:
            break
        for v in bad:
            v.used = False
            v.reason = f"reprojection error {v.rms_px:.3f} px > {limit:.3f} px (outlier)"
    rms, K, dist, rvecs, tvecs, std_int = result[:6]
    for v, r, t in zip([v for v in views if v.used], rvecs, tvecs):
        T = np.eye(4)
        T[:3, :3] = cv2.Rodrigues(r)[0]
        T[:3, 3] = np.asarray(t).ravel()
        v.board_to_camera = T
    n_coef = len(DISTORTION_MODELS[model]) if model in CAMERA_MODEL else 5
    d = np.zeros(n_coef)
    dist = np.asarray(dist, dtype=np.float64).ravel()
    d[:min(n_coef, dist.size)] = dist[:n_coef]
    fields = {"width": w, "height": h, "fx": float(K[0, 0]), "fy": float(K[1, 1]),
              "cx": float(K[0, 2]), "cy": float(K[1, 2]), "dist": tuple(float(x) for x in d),
              "distortion_model": CAMERA_MODEL.get(model, "plumb_bob")}
    camera = replace(base, **fields) if base is not None else CameraModel(**fields)
    std = np.asarray(std_int, dtype=np.float64).ravel()
    names = ("fx", "fy", "cx", "cy") + (DISTORTION_MODELS[model] if model == "fisheye" else _STD_NAMES)
    std_d = {n: float(s) for n, s in zip(names, std) if n in ("fx", "fy", "cx", "cy") or n in DISTORTION_MODELS[model]}
    return CameraCalibration(camera=camera, rms_px=float(rms), views=views, model=model, std_intrinsics=std_d)


def _fisheye_calibrate(obj: list[np.ndarray], img: list[np.ndarray], size: tuple[int, int],
                       base: CameraModel | None) -> tuple[Any, ...]:
    """``cv2.fisheye.calibrate`` in the shape of ``calibrateCameraExtended``'s answer: (rms,
    K, D, rvecs, tvecs, std of the intrinsics, -, per-view RMS). The fisheye solver gives no
    standard deviations (NaN) and no per-view errors (computed here by reprojection). It
    starts from the base camera's intrinsics when it is a fisheye of the same size."""
    import cv2

    # (1, N, 3) per view: the layout cv2.fisheye.calibrate accepts in OpenCV 4 and 5 alike
    objs = [o.reshape(1, -1, 3).astype(np.float64) for o in obj]
    imgs = [i.reshape(1, -1, 2).astype(np.float64) for i in img]
    def flag(name: str) -> int:  # OpenCV 4 has them in cv2.fisheye, OpenCV 5 in cv2 (other values)
        return int(getattr(cv2.fisheye, name, None) or getattr(cv2, name))

    flags = flag("CALIB_RECOMPUTE_EXTRINSIC") | flag("CALIB_FIX_SKEW")
    K0, D0 = np.zeros((3, 3)), np.zeros((4, 1))
    if base is not None and base.is_fisheye:
        K0, D0 = base.K.copy(), np.asarray(base.dist, dtype=np.float64).reshape(4, 1)
        flags |= flag("CALIB_USE_INTRINSIC_GUESS")
    try:
        rms, K, D, rvecs, tvecs = cv2.fisheye.calibrate(
            objs, imgs, size, K0, D0, flags=flags,
            criteria=(cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12))
    except cv2.error as exc:
        raise TofhilError(f"cv2.fisheye.calibrate failed ({str(exc).strip().splitlines()[-1]})", field="--model",
                          expected="board views spread over the field of a fisheye lens") from None
    per_view = []
    for o, i, r, t in zip(objs, imgs, rvecs, tvecs):
        proj, _ = cv2.fisheye.projectPoints(o.reshape(-1, 1, 3), r, t, K, D)
        per_view.append(float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - i.reshape(-1, 2)) ** 2, axis=-1)))))
    return rms, K, D, rvecs, tvecs, np.full(8, np.nan), None, np.asarray(per_view)


def calibrate_sessions(sessions: Sequence[str | Path], target: BoardSpec | str | dict, *, model: str = "k1k2p",
                       max_view_error_px: float = 1.0, progress: Progress | None = None) -> CameraCalibration:
    """:func:`calibrate_camera` on the mean amplitude of each session (one board pose each);
    the sessions must share one camera resolution (the first session's camera is the base)."""
    images: list[tuple[str, np.ndarray]] = []
    base: CameraModel | None = None
    for path in sessions:
        amp, cam = mean_amplitude(path)
        if base is None:
            base = cam
        elif (cam.width, cam.height) != (base.width, base.height):
            raise TofhilError(f"camera is {cam.width}x{cam.height}, the first session's {base.width}x{base.height}",
                              file=path, field="camera", expected="sessions of one camera")
        images.append((str(path), amp))
    return calibrate_camera(images, target, base=base, model=model, max_view_error_px=max_view_error_px,
                            progress=progress)


def max_model_difference_px(a: CameraModel, b: CameraModel, step: int = 4) -> float:
    """Largest distance (px) between where cameras ``a`` and ``b`` image the same ray, over a
    grid of ``a``'s pixels: how far apart two calibrations put points anywhere in the image."""
    v, u = np.mgrid[0:a.height:step, 0:a.width:step].astype(np.float64)
    rays = a.pixel_rays(u, v)
    uv = b.project(rays)
    return float(np.max(np.hypot(uv[..., 0] - u, uv[..., 1] - v)))


def preset_text(cal: CameraCalibration, target: BoardSpec, *, name: str | None = None) -> str:
    """The calibrated camera as a camera preset YAML (``configs/cameras`` layout), with the
    calibration's facts as comments (views, errors, rejected views and why)."""
    import yaml

    from tofhil.schema import to_plain

    cam = cal.camera if name is None else replace(cal.camera, name=name)
    d = cam.to_dict()
    d.update({k: v for k, v in cam.extra.items() if k not in d})
    lines = [f"# Calibrated by tofhil calibrate-camera from {len(cal.views)} views of a {target.kind} "
             f"{target.cols}x{target.rows} board ({yaml.safe_dump(to_plain(target.to_dict()), default_flow_style=True).strip()}).",
             f"# Distortion model {cal.model}; RMS reprojection error {cal.rms_px:.4f} px over {len(cal.used)} views.",
             "# 1-sigma: " + ", ".join(f"{k} {v:.3g}" for k, v in cal.std_intrinsics.items())]
    for v in cal.views:
        state = f"used, RMS {v.rms_px:.4f} px" if v.used else f"rejected: {v.reason}"
        lines.append(f"#   view {v.name}: {v.corners} corners, {state}")
    return "\n".join(lines) + "\n" + yaml.safe_dump(to_plain(d), sort_keys=False, default_flow_style=None)


@dataclass
class StereoCalibration:
    """ToF -> second camera extrinsics from simultaneous board views."""

    tof_to_camera: np.ndarray     # 4x4: ToF frame -> the other camera's frame
    rms_px: float                 # RMS reprojection error over both cameras and all views
    views: list[CalibrationView]  # per view pair: corners used, per-pair RMS (both cameras)

    def to_dict(self) -> dict[str, Any]:
        return {"tof_to_camera": self.tof_to_camera.tolist(), "rms_px": round(self.rms_px, 5),
                "views": [v.to_dict() for v in self.views]}


def calibrate_stereo(pairs: Sequence[tuple[str, np.ndarray, np.ndarray]], target: BoardSpec | str | dict,
                     tof_camera: CameraModel, other_camera: CameraModel) -> StereoCalibration:
    """Extrinsics between the ToF camera and a second camera from simultaneous views
    ``[(name, tof_amplitude, other_image), ...]`` of one board, both cameras' intrinsics
    known (``cv2.stereoCalibrate`` with fixed intrinsics, on the corners both cameras see).
    A pair is skipped (with its reason) when either camera misses the board."""
    import cv2

    spec = BoardSpec.parse(target)
    views: list[CalibrationView] = []
    obj, img_a, img_b = [], [], []
    for name, a, b in pairs:
        v = CalibrationView(name=name)
        views.append(v)
        da, db = detect_board(a, spec), detect_board(b, spec)
        if da is None or db is None:
            v.reason = f"no {spec.kind} board found in the {'ToF' if da is None else 'other'} image"
            continue
        common, ia, ib = np.intersect1d(da.ids, db.ids, return_indices=True)
        v.corners = len(common)
        if len(common) < MIN_CORNERS:
            v.reason = f"only {len(common)} corners seen by both cameras"
            continue
        v.used = True
        obj.append(da.object_points[ia].astype(np.float32))
        img_a.append(da.image_points[ia].astype(np.float32))
        img_b.append(db.image_points[ib].astype(np.float32))
    if len(obj) < 1:
        raise TofhilError(f"no usable view pair of {len(views)}", field="SESSIONS",
                          expected="views where both cameras see the board")
    # (a fisheye's corners as its pinhole would see them: OpenCV's stereo solver is pinhole)
    img_a = [opencv_points(tof_camera, i)[0].astype(np.float32) for i in img_a]
    img_b = [opencv_points(other_camera, i)[0].astype(np.float32) for i in img_b]
    _, _, da_ = opencv_points(tof_camera, np.zeros((0, 2)))
    _, _, db_ = opencv_points(other_camera, np.zeros((0, 2)))
    out = cv2.stereoCalibrateExtended(obj, img_a, img_b, tof_camera.K, da_, other_camera.K, db_,
                                      (tof_camera.width, tof_camera.height), np.eye(3), np.zeros((3, 1)),
                                      flags=cv2.CALIB_FIX_INTRINSIC,
                                      criteria=(cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12))
    rms, R, t = out[0], out[5], out[6]
    per_view = np.asarray(out[-1]).reshape(len(obj), -1)
    for v, e in zip([v for v in views if v.used], per_view):
        v.rms_px = float(np.sqrt(np.mean(np.square(e))))
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, np.asarray(t).ravel()
    return StereoCalibration(tof_to_camera=T, rms_px=float(rms), views=views)


def calibrate_stereo_sessions(sessions: Sequence[str | Path], target: BoardSpec | str | dict, *,
                              tof_camera: CameraModel | None = None,
                              other_camera: CameraModel | None = None) -> StereoCalibration:
    """:func:`calibrate_stereo` on sessions with an ``rgb/`` group (one board pose each): the
    mean ToF amplitude beside the mean of the second camera's images (grey). The cameras
    default to the sessions' own (``camera`` and ``rgb.camera``)."""
    from tofhil.session_rgb import read_rgb

    pairs = []
    for path in sessions:
        amp, cam = mean_amplitude(path)
        rgb = read_rgb(path)
        imgs = rgb.images.astype(np.float64)
        grey = (imgs @ np.array([0.299, 0.587, 0.114]) if imgs.ndim == 4 else imgs).mean(axis=0)
        tof_camera = tof_camera or cam
        other_camera = other_camera or rgb.camera
        if grey.shape != other_camera.shape:
            raise TofhilError(f"rgb images are {grey.shape[1]}x{grey.shape[0]}, the camera "
                              f"{other_camera.width}x{other_camera.height}", file=path, field="rgb/images")
        if amp.shape != tof_camera.shape:
            raise TofhilError(f"amplitude is {amp.shape[1]}x{amp.shape[0]}, the ToF camera "
                              f"{tof_camera.width}x{tof_camera.height}", file=path, field="camera")
        pairs.append((str(path), amp, grey))
    return calibrate_stereo(pairs, target, tof_camera, other_camera)
