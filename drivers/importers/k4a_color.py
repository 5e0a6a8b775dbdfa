"""The Azure Kinect's colour camera: its MJPEG frames, factory intrinsics and the depth ->
colour extrinsics, from a k4arecorder Matroska file (``calibration.json`` attachment).

Intrinsics: the ``CALIBRATION_CameraPurposePhotoVideo`` camera (4096 x 3072 sensor,
unitised Brown-Conrady parameters in the order of :data:`tofhil.drivers.importers.k4a.PARAM_NAMES`),
converted to one colour resolution as the SDK does: scaled to the mode's calibration image
(4:3) and cropped to 16:9 where the mode is 16:9, pixel centres at integers.

Extrinsics: each camera's ``Rt`` in ``calibration.json`` maps depth-camera coordinates into
that camera's frame (``x_cam = R x_depth + t``, metres; the depth camera's own ``Rt`` is the
identity), as the SDK's ``k4a_calibration_get_extrinsics(DEPTH, COLOR)`` returns it.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from tofhil.drivers.importers.k4a import PARAM_NAMES, K4AIntrinsics, read_k4a_recording
from tofhil.drivers.importers.mkv import open_mkv
from tofhil.errors import InputFileError
from tofhil.frames import DepthWithColor

#: Colour resolutions: (calibration image size the 4096 x 3072 sensor is scaled to, crop offset).
COLOR_MODES: dict[tuple[int, int], tuple[tuple[int, int], tuple[int, int]]] = {
    (1280, 720): ((1280, 960), (0, 120)),
    (1920, 1080): ((1920, 1440), (0, 180)),
    (2560, 1440): ((2560, 1920), (0, 240)),
    (3840, 2160): ((3840, 2880), (0, 360)),
    (2048, 1536): ((2048, 1536), (0, 0)),
    (4096, 3072): ((4096, 3072), (0, 0)),
}

_COLOR = "CALIBRATION_CameraPurposePhotoVideo"


def _camera(calib: dict[str, Any], purpose: str, source: Path) -> dict[str, Any]:
    try:
        cams = calib["CalibrationInformation"]["Cameras"]
    except (KeyError, TypeError):
        raise InputFileError("missing", file=source, field="calibration.json:CalibrationInformation.Cameras",
                             expected="the Azure Kinect factory calibration") from None
    found = [c for c in cams if isinstance(c, dict) and c.get("Purpose") == purpose]
    if not found:
        raise InputFileError(f"no camera with Purpose {purpose}", file=source,
                             field="calibration.json:Cameras[].Purpose", expected=f"a {purpose} entry")
    return found[0]


def color_intrinsics(calib: dict[str, Any], width: int, height: int, *, source: Path) -> K4AIntrinsics:
    """The colour camera in pixels of a ``width`` x ``height`` colour mode."""
    cam = _camera(calib, _COLOR, source)
    params = cam.get("Intrinsics", {}).get("ModelParameters")
    field = "calibration.json:Cameras[color].Intrinsics.ModelParameters"
    try:
        p = dict(zip(PARAM_NAMES, (float(v) for v in params[:14])))
    except (TypeError, ValueError):
        p = {}
    if len(p) != 14 or not all(math.isfinite(v) for v in p.values()) or p["fx"] <= 0 or p["fy"] <= 0:
        raise InputFileError(f"has unusable values {params!r}", file=source, field=field,
                             expected="14 finite numbers (cx cy fx fy k1..k6 codx cody p2 p1) with fx, fy > 0")
    if (width, height) not in COLOR_MODES:
        raise InputFileError(f"colour resolution {width}x{height}", file=source, field="COLOR",
                             expected="one of " + ", ".join(f"{w}x{h}" for w, h in COLOR_MODES))
    (bw, bh), (ox, oy) = COLOR_MODES[(width, height)]
    return K4AIntrinsics(width=width, height=height, fx=p["fx"] * bw, fy=p["fy"] * bh,
                         cx=p["cx"] * bw - ox - 0.5, cy=p["cy"] * bh - oy - 0.5,
                         k=(p["k1"], p["k2"], p["k3"], p["k4"], p["k5"], p["k6"]), p1=p["p1"], p2=p["p2"],
                         codx=p["codx"], cody=p["cody"], metric_radius=float(cam.get("MetricRadius") or math.inf))


def depth_to_color(calib: dict[str, Any], *, source: Path) -> np.ndarray:
    """4x4 transform from depth-camera to colour-camera coordinates (m)."""
    cam = _camera(calib, _COLOR, source)
    rt = cam.get("Rt", {})
    try:
        R = np.asarray(rt["Rotation"], dtype=np.float64).reshape(3, 3)
        t = np.asarray(rt["Translation"], dtype=np.float64).reshape(3)
    except (KeyError, TypeError, ValueError):
        raise InputFileError("missing or malformed", file=source, field="calibration.json:Cameras[color].Rt",
                             expected="Rotation (9 numbers) and Translation (3 numbers, m)") from None
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or not np.all(np.isfinite(t)):
        raise InputFileError("is not a rotation", file=source, field="calibration.json:Cameras[color].Rt.Rotation",
                             expected="an orthonormal 3x3 matrix")
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def read_color_frame(path: str | Path, index: int = 0) -> tuple[np.ndarray, K4AIntrinsics, np.ndarray]:
    """(RGB image uint8 [H, W, 3], colour intrinsics, depth->colour 4x4) of frame ``index``."""
    import cv2

    path = Path(path)
    with open_mkv(path) as mkv:
        track = mkv.track_by_name("COLOR")
        if track is None:
            raise InputFileError("has no track named COLOR", file=path, field="Tracks.TrackEntry.Name",
                                 expected="an Azure Kinect recording with colour")
        if track.codec_id != "mjpeg":
            raise InputFileError(f"colour codec is {track.codec_id!r}", file=path, field="COLOR.CodecID",
                                 expected="MJPEG (the recorder's default colour format)")
        blocks = mkv.frames(track)
        if not 0 <= index < len(blocks):
            raise InputFileError(f"has {len(blocks)} colour frames", file=path, field="COLOR",
                                 expected=f"a frame index below {len(blocks)}")
        bgr = cv2.imdecode(np.frombuffer(mkv.payload(blocks[index]), np.uint8), cv2.IMREAD_COLOR)
        if bgr is None:
            raise InputFileError(f"colour frame {index} is not a JPEG image", file=path, field="COLOR")
        name = "calibration.json"
        try:
            calib = json.loads(mkv.attachments[name].decode("utf-8"))
        except (KeyError, UnicodeDecodeError, json.JSONDecodeError):
            raise InputFileError("has no readable calibration.json", file=path, field="Attachments",
                                 expected="the factory calibration attachment") from None
    h, w = bgr.shape[:2]
    return bgr[..., ::-1].copy(), color_intrinsics(calib, w, h, source=path), depth_to_color(calib, source=path)


def read_depth_with_color(path: str | Path, frame: int = 0) -> DepthWithColor:
    """Depth and colour frame ``frame`` of an Azure Kinect recording with the factory calibration."""
    rgb, color_cam, depth_to_color = read_color_frame(path, frame)
    with read_k4a_recording(path) as rec:
        if frame >= len(rec):
            raise InputFileError(f"has {len(rec)} depth frames", file=path, field="--frame",
                                 expected=f"an index below {len(rec)}")
        _, z_mm, _ = rec.frame(frame)
        intr = rec.intrinsics
        v, u = np.mgrid[0:intr.height, 0:intr.width].astype(np.float64)
        ok = intr.undistort(u, v)[2]    # the exact factory rays (z-depth: point = (x z, y z, z))
    valid = (z_mm > 0) & ok
    return DepthWithColor(z_m=z_mm * 1e-3, valid=valid, pixel_to_ray=intr.undistort, tof_to_color=depth_to_color,
                          color_camera=color_cam, rgb=rgb)
