"""Colour a ToF point cloud from an RGB camera beside it, with occlusion.

Every ToF point is moved into the colour camera's frame (the ToF -> colour extrinsics) and
projected with the colour camera's lens model. Several ToF points can land on one colour
pixel when something in front hides something behind from the colour camera (it sees the
scene from a few centimetres away): a z-buffer over the colour image keeps, per colour pixel,
the nearest point's depth (splatted over ``splat_px`` pixels, since ToF points are sparser
than colour pixels), and a point takes a colour only if it is within ``tolerance`` of that
depth plus :data:`NOISE_SIGMAS` of its depth noise (a z-buffer's minimum over noisy points
lies below each of them: without the noise, a noisy flat wall's points hide one another);
the others are occluded (no colour). Colours are sampled bilinearly.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from tofhil.frames import DepthWithColor

#: Depth tolerance of the z-buffer: absolute (m) plus relative to the depth.
Z_TOLERANCE_M = 0.01
Z_TOLERANCE_REL = 0.01
#: Depth noise allowed on top (sigmas): the z-buffer keeps the least of about (2 splat + 1)^2
#: noisy depths, about 2 sigma below their mean, and the point itself may lie 2 sigma above it.
NOISE_SIGMAS = 4.0


def depth_noise(z_m: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Each valid pixel's depth noise ``[H, W]`` (m): the image's relative noise
    (:func:`tofhil.depth.relative_depth_noise`) times the pixel's depth (0 where invalid)."""
    from tofhil.depth import relative_depth_noise

    sigma_rel = relative_depth_noise(z_m, valid)
    return np.where(valid, sigma_rel * np.nan_to_num(np.asarray(z_m, np.float64), nan=0.0), 0.0)


def project(camera: Any, points: np.ndarray) -> np.ndarray:
    """Camera-frame points ``[N, 3]`` -> pixels ``[N, 2]`` with the camera's lens model: a
    :class:`tofhil.camera.CameraModel` (``project``) or a model with ``distort`` and fx, fy,
    cx, cy (the Azure Kinect's rational Brown-Conrady)."""
    if hasattr(camera, "project"):
        return camera.project(points)
    with np.errstate(divide="ignore", invalid="ignore"):
        x, y = points[:, 0] / points[:, 2], points[:, 1] / points[:, 2]
    xd, yd = camera.distort(x, y)
    return np.stack([camera.fx * xd + camera.cx, camera.fy * yd + camera.cy], axis=1)


@dataclass
class Colorized:
    """Colours of the ToF points and which of them the colour camera sees."""

    colors: np.ndarray     # [N, 3] uint8 (0 where not visible)
    visible: np.ndarray    # [N] bool: in the colour image, in front, not occluded
    occluded: np.ndarray   # [N] bool: in the colour image but hidden behind a nearer point
    uv: np.ndarray         # [N, 2] colour-image pixel of each point (NaN behind the camera)


def colorize_points(points: np.ndarray, tof_to_color: np.ndarray, color_camera: Any, color_rgb: np.ndarray, *,
                    splat_px: int = 1, noise_m: np.ndarray | float = 0.0) -> Colorized:
    """Colour ToF-frame points ``[N, 3]`` from an RGB image ``[H, W, 3]`` (uint8) of the colour
    camera, ``tof_to_color`` the 4x4 ToF -> colour transform (see the module doc); ``noise_m``
    each point's depth noise (``[N]`` or one number; :func:`depth_noise` of the image)."""
    pts = np.asarray(points, dtype=np.float64)
    pc = pts @ tof_to_color[:3, :3].T + tof_to_color[:3, 3]
    z = pc[:, 2]
    h, w = color_rgb.shape[:2]
    front = z > 1e-6
    uv = np.full((len(pts), 2), np.nan)
    uv[front] = project(color_camera, pc[front])
    inside = front & np.all(np.isfinite(uv), axis=1) & (uv[:, 0] > -0.5) & (uv[:, 0] < w - 0.5) \
        & (uv[:, 1] > -0.5) & (uv[:, 1] < h - 0.5)
    iu = np.clip(np.round(uv[inside, 0]).astype(np.int64), 0, w - 1)
    iv = np.clip(np.round(uv[inside, 1]).astype(np.int64), 0, h - 1)
    zi = z[inside]
    zbuf = np.full((h, w), np.inf)
    for dv in range(-splat_px, splat_px + 1):
        for du in range(-splat_px, splat_px + 1):
            np.minimum.at(zbuf, (np.clip(iv + dv, 0, h - 1), np.clip(iu + du, 0, w - 1)), zi)
    noise = np.broadcast_to(np.asarray(noise_m, np.float64), (len(pts),))[inside]
    near = zi <= zbuf[iv, iu] + Z_TOLERANCE_M + Z_TOLERANCE_REL * zi + NOISE_SIGMAS * noise
    visible = np.zeros(len(pts), dtype=bool)
    visible[np.flatnonzero(inside)[near]] = True
    occluded = inside & ~visible
    colors = np.zeros((len(pts), 3), dtype=np.uint8)
    if visible.any():
        colors[visible] = _bilinear(color_rgb, uv[visible])
    return Colorized(colors=colors, visible=visible, occluded=occluded, uv=uv)


def _bilinear(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``img [H, W, C]`` at pixel positions ``uv [N, 2]`` (edges clamped)."""
    h, w = img.shape[:2]
    u = np.clip(uv[:, 0], 0, w - 1)
    v = np.clip(uv[:, 1], 0, h - 1)
    u0 = np.minimum(np.floor(u).astype(np.int64), w - 2)
    v0 = np.minimum(np.floor(v).astype(np.int64), h - 2)
    fu, fv = (u - u0)[:, None], (v - v0)[:, None]
    im = img.astype(np.float64)
    out = (im[v0, u0] * (1 - fu) * (1 - fv) + im[v0, u0 + 1] * fu * (1 - fv)
           + im[v0 + 1, u0] * (1 - fu) * fv + im[v0 + 1, u0 + 1] * fu * fv)
    return np.clip(np.round(out), 0, 255).astype(np.uint8)


def write_ply(path: str | Path, points: np.ndarray, colors: np.ndarray) -> Path:
    """A binary little-endian PLY of points (float32 x, y, z) with uint8 red, green, blue."""
    path = Path(path)
    pts = np.asarray(points, dtype=np.float64)
    rec = np.empty(len(pts), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"),
                                    ("blue", "u1")])
    rec["x"], rec["y"], rec["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    rec["red"], rec["green"], rec["blue"] = colors[:, 0], colors[:, 1], colors[:, 2]
    header = ("ply\nformat binary_little_endian 1.0\ncomment written by tofhil colorize\n"
              f"element vertex {len(pts)}\nproperty float x\nproperty float y\nproperty float z\n"
              "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n")
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(rec.tobytes())
    return path


def grey_to_rgb(img: np.ndarray) -> np.ndarray:
    """A float grey image (e.g. the twin's radiance) as uint8 RGB, scaled to its 99.5th percentile."""
    g = np.nan_to_num(np.asarray(img, dtype=np.float64))
    top = float(np.percentile(g, 99.5)) if g.size else 0.0
    g8 = np.clip(np.round(255.0 * g / top), 0, 255).astype(np.uint8) if top > 0 else np.zeros(g.shape, np.uint8)
    return np.repeat(g8[..., None], 3, axis=2)


def session_inputs(path: str | Path, frame: int = 0, tof_to_color: np.ndarray | None = None) -> DepthWithColor:
    """Depth frame ``frame`` of a session and its ``rgb/`` group's image taken with that frame
    (``tof_to_color`` default: the group's ``tof_to_camera``, as calibrate-stereo finds it)."""
    from tofhil.errors import InputFileError
    from tofhil.session import open_session
    from tofhil.session_rgb import read_rgb

    path = Path(path)
    rgb = read_rgb(path)
    where = np.flatnonzero(np.asarray(rgb.frame_index) == frame)
    if where.size == 0:
        raise InputFileError(f"has no second-camera image taken with frame {frame}", file=path,
                             field="rgb/frame_index", expected="--frame one of " + ", ".join(
                                 str(int(i)) for i in np.unique(rgb.frame_index)))
    t = rgb.tof_to_camera if tof_to_color is None else np.asarray(tof_to_color, dtype=np.float64)
    if t is None:
        raise InputFileError("missing", file=path, field="rgb.tof_to_camera",
                             expected="the ToF -> camera extrinsics (or --extrinsics from tofhil calibrate-stereo)")
    with open_session(path) as s:
        d = s.requested_depth_frame(frame)
    cam = d.camera
    valid = cam.valid_mask(d.distance_m, d.valid)
    z = np.asarray(d.distance_m if d.kind != "radial" else cam.radial_to_z(d.distance_m), dtype=np.float64)

    def pixel_to_ray(u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        x, y = cam.undistort_normalized(np.asarray(u, dtype=np.float64), np.asarray(v, dtype=np.float64))
        return x, y, np.isfinite(x) & np.isfinite(y)      # (no ray, or a fisheye's beyond 90 degrees)

    img = rgb.images[int(where[0])]
    img = img if img.ndim == 3 and img.dtype == np.uint8 else grey_to_rgb(img)
    return DepthWithColor(z_m=np.where(valid, z, np.nan), valid=valid, pixel_to_ray=pixel_to_ray, tof_to_color=t,
                          color_camera=rgb.camera, rgb=img)
