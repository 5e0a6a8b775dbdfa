"""A twin scene built from a capture: camera, planar patches, the rest as a mesh, radiometry.

``tofhil scene-from-capture`` turns one depth (+ amplitude) frame of a session into a scene
file the twin renders:

- the camera block is the session's camera model (intrinsics, distortion, resolution); the
  modulation frequencies and wavelength come from the session (raw taps or a recorded
  sensor configuration), else from the caller (a device capture of depth only says neither);
- planar patches are segmented from the point cloud by iterated RANSAC (Open3D
  ``segment_plane``) and written as ``plane`` objects: the pose puts the plane's local z on
  the fitted normal and its centre at the middle of its inliers, the size spans the inliers
  (1st to 99th percentile along the plane's axes);
- what is not planar is a mesh triangulated from the range image itself (neighbouring pixels
  joined unless a depth step separates them; PLY written by Open3D beside the scene, read by
  trimesh). The organised cloud gives the connectivity for free and in linear time; a
  surface reconstruction (Poisson, ball pivoting) would invent surfaces where the camera saw
  none and takes unbounded time on half a million points;
- radiometry: the scene is rendered by the twin (inverse square, incidence, emitter profile,
  cos^4 lens fall-off, :mod:`tofhil.sim.radiometry`) and the amplitude image divided by the
  prediction, per object. The emitter's beam exponent is fitted on the largest plane (the
  log ratio against ``log cos`` of the emission angle is a line of slope ``n - n0``); the
  power and reflectances follow from the per-object ratios. Only their product is seen by
  an amplitude image: the largest surface is given reflectance ``ASSUMED_REFLECTANCE``
  (stated in the metadata) unless that would put another object above 1;
- the scene's pixels whose distance exceeds the unambiguous range of the frequencies are
  flagged (a warning and a ``valid`` mask beside the scene).

The metadata (``<scene>.capture.json`` beside the scene) says what was fitted and which
effects the scene cannot observe: the planes' poses were fitted to the same depth, so a
constant range offset (and the camera pose) is absorbed by them.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import yaml

from tofhil.outputs import refuse_existing
from tofhil.camera import CameraModel
from tofhil.depth import saturated_amplitude
from tofhil.errors import TofhilError
from tofhil.session import open_session
from tofhil.unwrap import frequency_plan

#: Reflectance given to the largest surface (amplitude sees only power x reflectance).
ASSUMED_REFLECTANCE = 0.5
#: Effects a scene whose planes were fitted to the capture's own depth cannot observe.
UNOBSERVABLE_FITTED_POSE = {
    "range_offset": "a constant range offset moves every fitted plane along its normal: the plane "
                    "poses were fitted to the same depth and absorb it (to first order)",
    "pose": "the camera pose relative to the scene was fitted from the same depth (the planes' poses)",
}
METADATA_SUFFIX = ".capture.json"
VALID_SUFFIX = "_valid.npy"
MESH_SUFFIX = "_rest.ply"
#: A plane's outline mesh: ``<scene>_<plane name>.ply``.
PLANE_GLOB = "_plane*.ply"


@dataclass
class PlanePatch:
    name: str
    normal: np.ndarray       # unit, pointing away from the camera
    offset_m: float          # n . X = offset_m
    centre: np.ndarray
    axes: np.ndarray         # [3, 3] columns: u, v, n
    size: tuple[float, float]
    pixels: np.ndarray       # bool [H, W]
    rms_m: float
    #: The patch's outline as a flat mesh on the fitted plane (file name beside the scene);
    #: None: the rectangle ``size`` is written.
    outline_file: str | None = None


@dataclass
class CaptureScene:
    """What :func:`scene_from_capture` made: the scene file, its sidecars and the figures."""

    scene_path: Path
    metadata_path: Path
    valid_path: Path
    mesh_path: Path | None
    planes: list[PlanePatch]
    metadata: dict[str, Any]
    warnings: list[str] = field(default_factory=list)


def metadata_path_for(scene_path: str | Path) -> Path:
    p = Path(scene_path)
    return p.with_name(p.stem + METADATA_SUFFIX)


def read_capture_metadata(scene_path: str | Path) -> dict[str, Any] | None:
    """The metadata of a scene made from a capture, or None for any other scene."""
    p = metadata_path_for(scene_path)
    if not p.is_file():
        return None
    try:
        return json.loads(p.read_text())
    except (OSError, json.JSONDecodeError):
        return None


def _preset_fact(cam: CameraModel, key: str) -> Any:
    """A fact of the camera preset the session's camera is named after (an importer that
    assumed a preset stores its name, not its extra facts such as the wavelength)."""
    from tofhil.camera import list_camera_presets, load_camera_preset

    if not cam.name or cam.name not in list_camera_presets():
        return None
    try:
        return dict(load_camera_preset(cam.name).extra).get(key)
    except TofhilError:
        return None


#: Board corners reprojecting worse than this (px rms) are refused: not the board of the spec.
MAX_BOARD_RMS_PX = 1.5


@dataclass
class BoardFit:
    """A board found in the amplitude image: its pose (photogrammetry) and the pixels it covers."""

    spec: Any                    # tofhil.boards.BoardSpec
    pose: Any                    # tofhil.targets.BoardPose
    plane_to_camera: np.ndarray  # 4x4: the twin's centred board plane -> camera
    pixels: np.ndarray           # bool [H, W]: the sheet's outline, one pixel wider (mixed pixels)

    def to_json(self) -> dict[str, Any]:
        return {"spec": self.spec.to_dict(), "corners": int(self.pose.detection.n),
                "reprojection_rms_px": float(self.pose.rms_px),
                "board_to_camera": [[float(x) for x in row] for row in self.pose.board_to_camera],
                "pixels": int(self.pixels.sum()), "pose_from": "the amplitude image (solvePnP), not the depth"}


def fit_board(amplitude: np.ndarray, cam: CameraModel, target: Any) -> BoardFit:
    """The board's pose from the amplitude image and the pixels its sheet covers."""
    import cv2

    from tofhil.boards import BoardSpec
    from tofhil.targets import board_pose_from_amplitude

    spec = BoardSpec.parse(target, source="--target", field="--target")
    pose = board_pose_from_amplitude(amplitude, cam, spec)
    if pose.rms_px > MAX_BOARD_RMS_PX:
        # a part of another board, or a camera model that does not fit: its pose would be wrong
        raise TofhilError(f"the {spec.kind} {spec.cols}x{spec.rows} corners found reproject with "
                          f"{pose.rms_px:.2f} px rms", field="--target",
                          expected=f"the printed board's spec (grid, square size) and a camera model under which "
                                   f"its corners reproject within {MAX_BOARD_RMS_PX:g} px")
    plane_to_camera = pose.board_to_camera @ np.linalg.inv(spec.board_to_plane())
    w, h = spec.size_m
    corners = np.array([[-w / 2, -h / 2, 0.0], [w / 2, -h / 2, 0.0], [w / 2, h / 2, 0.0], [-w / 2, h / 2, 0.0]])
    cam_pts = corners @ plane_to_camera[:3, :3].T + plane_to_camera[:3, 3]
    # the outline through the lens: each edge sampled, so distortion bends it as it bends the image
    edge = np.concatenate([cam_pts[i] + np.linspace(0, 1, 32, endpoint=False)[:, None] * (cam_pts[(i + 1) % 4] - cam_pts[i])
                           for i in range(4)])
    uv = cam.project(edge)
    mask = np.zeros(cam.shape, np.uint8)
    cv2.fillPoly(mask, [np.round(uv * 16).astype(np.int32)], 1, shift=4)
    pixels = cv2.dilate(mask, np.ones((3, 3), np.uint8)).astype(bool)
    return BoardFit(spec=spec, pose=pose, plane_to_camera=plane_to_camera, pixels=pixels)


def _frequencies(session: Any, freq_hz: Sequence[float] | None, wavelength_m: float | None
                 ) -> tuple[list[float], float, str]:
    sc = session.sensor_config or {}
    extra = dict(getattr(session.camera, "extra", {}) or {})
    if freq_hz:
        freqs, src = [float(f) for f in freq_hz], "--freq-hz"
    elif session.has_raw:
        freqs, src = [float(f) for f in session.freq_hz], "session raw/freq_hz"
    elif sc.get("freq_hz"):
        freqs, src = [float(f) for f in np.atleast_1d(sc["freq_hz"])], "session sensor_config"
    else:
        raise TofhilError("records no modulation frequency (a depth-only capture)", file=session.path,
                          field="--freq-hz", expected="the device's modulation frequencies, e.g. "
                          "--freq-hz 100e6 (comma-separated for several)")
    for f in freqs:
        if not (math.isfinite(f) and f > 0):
            raise TofhilError(f"got {f}", field="--freq-hz", expected="positive frequencies in Hz")
    wl = wavelength_m or sc.get("wavelength_m") or extra.get("wavelength_m") or _preset_fact(session.camera,
                                                                                            "wavelength_m")
    if wl is None:
        raise TofhilError("records no emitter wavelength", file=session.path, field="--wavelength-m",
                          expected="the emitter's wavelength, e.g. --wavelength-m 850e-9")
    return freqs, float(wl), src


def _segment_planes(points: np.ndarray, pix: np.ndarray, shape: tuple[int, int], *, max_planes: int,
                    threshold_m: float, min_fraction: float, seed: int = 0) -> list[PlanePatch]:
    """Iterated RANSAC on a subsample; inliers then taken from every point within the threshold."""
    from tofhil.open3d_loader import open3d

    o3d = open3d()
    o3d.utility.random.seed(seed)
    rng = np.random.default_rng(seed)
    remaining = np.ones(len(points), bool)
    planes: list[PlanePatch] = []
    min_points = max(200, int(min_fraction * len(points)))
    for _ in range(3 * max_planes):
        if len(planes) >= max_planes:
            break
        idx = np.flatnonzero(remaining)
        if idx.size < min_points:
            break
        sub = idx if idx.size <= 30000 else rng.choice(idx, 30000, replace=False)
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points[sub]))
        model, _ = pc.segment_plane(distance_threshold=threshold_m, ransac_n=3, num_iterations=300)
        n = np.asarray(model[:3], float)
        norm = np.linalg.norm(n)
        n, d = n / norm, -float(model[3]) / norm
        if d < 0:  # normal away from the camera: n . X = d > 0 for points in front
            n, d = -n, -d
        dist = points[idx] @ n - d
        inl = idx[np.abs(dist) < threshold_m]
        if inl.size < min_points:
            break
        # least-squares refit on the inliers (RANSAC's plane is from 3 points)
        c = points[inl].mean(axis=0)
        _, _, vt = np.linalg.svd(points[inl] - c, full_matrices=False)
        n = vt[2] if vt[2] @ c > 0 else -vt[2]
        d = float(n @ c)
        dist = points[idx] @ n - d
        inl = idx[np.abs(dist) < threshold_m]
        if inl.size < min_points:
            break
        remaining[inl] = False
        # the same surface: a plane of nearly the same normal and offset, or one its inliers lie
        # on (RANSAC on the noisy leftovers of a fitted wall tilts; their points do not)
        twin = next((q for q in planes if (q.normal @ n > math.cos(math.radians(5.0))
                                           and abs(q.offset_m - d) < 3.0 * threshold_m)
                     or float(np.median(np.abs(points[inl] @ q.normal - q.offset_m))) < threshold_m), None)
        if twin is not None:
            # the same surface, a little curved: its pixels stay with the first fit, so the
            # curvature shows as a residual instead of as overlapping copies of one plane
            twin.pixels.reshape(-1)[pix[inl]] = True
            continue
        # in-plane axes: u along the camera's x projected on the plane, v = n x u
        u = np.array([1.0, 0.0, 0.0]) - n[0] * n
        if np.linalg.norm(u) < 1e-6:
            u = np.array([0.0, 1.0, 0.0]) - n[1] * n
        u /= np.linalg.norm(u)
        v = np.cross(n, u)
        q = points[inl] - c
        a, b = q @ u, q @ v
        a0, a1 = np.percentile(a, [1, 99])
        b0, b1 = np.percentile(b, [1, 99])
        centre = c + u * 0.5 * (a0 + a1) + v * 0.5 * (b0 + b1)
        centre = centre - n * (n @ centre - d)
        mask = np.zeros(shape, bool)
        mask.reshape(-1)[pix[inl]] = True
        planes.append(PlanePatch(name=f"plane{len(planes)}", normal=n, offset_m=d, centre=centre,
                                 axes=np.stack([u, v, n], axis=1), size=(float(a1 - a0), float(b1 - b0)),
                                 pixels=mask, rms_m=float(np.sqrt(np.mean((points[inl] @ n - d) ** 2)))))
    return planes


def occluding_fraction(cam: CameraModel, p: PlanePatch, radial: np.ndarray, valid: np.ndarray,
                       margin_m: float) -> float:
    """Fraction of the pixels that see the plane's rectangle where the camera saw something
    farther than it: there the rectangle would hide what was measured (a rectangle spanning
    an L-shaped patch, a plane beyond its real edge)."""
    rays = cam.rays
    cos = rays @ p.normal
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(cos > 1e-6, p.offset_m / cos, np.inf)
    q = rays * np.where(np.isfinite(t), t, 0.0)[..., None] - p.centre
    a, b = q @ p.axes[:, 0], q @ p.axes[:, 1]
    inside = np.isfinite(t) & (np.abs(a) <= p.size[0] / 2) & (np.abs(b) <= p.size[1] / 2)
    if not inside.any():
        return 1.0
    hides = inside & valid & (radial > t + margin_m)
    return float(hides.sum() / inside.sum())


#: A plane whose rectangle would hide more than this fraction of its pixels' measurements
#: is left to the mesh instead (exact geometry of what was seen).
MAX_OCCLUDING_FRACTION = 0.10
#: RANSAC's inlier threshold in sigmas of the frame's depth noise (when above 1 % of the distance).
PLANE_NOISE_SIGMAS = 3.0


def grid_mesh(points_hw: np.ndarray, mask: np.ndarray, *, stride: int = 2, max_step: float = 0.05
              ) -> tuple[np.ndarray, np.ndarray]:
    """Triangles joining neighbouring pixels of a range image (``points_hw [H, W, 3]``, ``mask``):
    a quad of pixels ``stride`` apart gives two triangles where all its corners are in ``mask``
    and no edge is longer than ``max_step`` times the distance (a depth step, not a surface)."""
    p = points_hw[::stride, ::stride]
    m = mask[::stride, ::stride]
    h, w = m.shape
    ids = np.arange(h * w).reshape(h, w)
    a, b, c, d = ids[:-1, :-1], ids[:-1, 1:], ids[1:, :-1], ids[1:, 1:]
    flat = p.reshape(-1, 3)
    mflat = m.reshape(-1)
    rng = np.linalg.norm(flat, axis=1)
    tris = []
    for t in (np.stack([a, c, b], -1), np.stack([b, c, d], -1)):
        t = t.reshape(-1, 3)
        ok = mflat[t].all(axis=1)
        for i, j in ((0, 1), (1, 2), (2, 0)):
            edge = np.linalg.norm(flat[t[:, i]] - flat[t[:, j]], axis=1)
            ok &= edge <= max_step * np.maximum(rng[t[:, i]], 1e-6)
        tris.append(t[ok])
    tri = np.concatenate(tris)
    used = np.unique(tri)
    remap = np.full(flat.shape[0], -1, np.int64)
    remap[used] = np.arange(used.size)
    return flat[used], remap[tri]


def write_plane_outline(cam: CameraModel, p: PlanePatch, path: Path, stride: int) -> bool:
    """Write the plane patch as a flat mesh covering its pixels (closed over gaps of noise
    up to 2 pixels, ``stride`` pixels wider so the mesh through every ``stride``-th pixel
    centre still covers the edge pixels): each pixel's ray meets the fitted plane. False when nothing is left to write."""
    from scipy import ndimage

    from tofhil.open3d_loader import open3d

    mask = ndimage.binary_closing(p.pixels, np.ones((5, 5), bool)) | p.pixels
    mask = ndimage.binary_dilation(mask, np.ones((2 * stride + 1, 2 * stride + 1), bool))
    cos = cam.rays @ p.normal
    mask &= cos > 1e-3
    pts = cam.rays * np.where(mask, p.offset_m / np.where(mask, cos, 1.0), 0.0)[..., None]
    verts, tris = grid_mesh(pts, mask, stride=stride, max_step=1e6)
    if not len(tris):
        return False
    o3d = open3d()
    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(verts), o3d.utility.Vector3iVector(tris))
    o3d.io.write_triangle_mesh(str(path), m, write_ascii=False)
    return True


def _camera_block(cam: CameraModel) -> dict[str, Any]:
    d = {k: v for k, v in cam.to_dict().items() if k in ("width", "height", "fx", "fy", "cx", "cy", "model", "dist",
                                                           "pixel_pitch_m")}
    d["f_number"] = 1.2  # ASSUMED (no lens data in a depth capture); scales with the fitted power
    return d


def _pose_matrix(p: PlanePatch) -> list[list[float]]:
    m = np.eye(4)
    m[:3, :3] = p.axes
    m[:3, 3] = p.centre
    return [[round(float(x), 9) for x in row] for row in m]


def _scene_dict(name: str, cam: CameraModel, freqs: list[float], wavelength_m: float, planes: list[PlanePatch],
                mesh_file: str | None, reflectance: dict[str, float], power_w: float, profile: dict[str, Any],
                description: str, board: "BoardFit | None" = None) -> dict[str, Any]:
    objects: list[dict[str, Any]] = []
    materials: dict[str, Any] = {}
    for p in planes:
        materials[p.name] = {"reflectance": round(float(reflectance[p.name]), 6)}
        if p.outline_file:
            objects.append({"name": p.name, "type": "mesh", "file": p.outline_file, "material": p.name})
        else:
            objects.append({"name": p.name, "type": "plane", "size": [round(p.size[0], 6), round(p.size[1], 6)],
                            "material": p.name, "pose": {"matrix": _pose_matrix(p)}})
    if mesh_file:
        materials["rest"] = {"reflectance": round(float(reflectance["rest"]), 6)}
        objects.append({"name": "rest", "type": "mesh", "file": mesh_file, "material": "rest"})
    if board is not None:
        objects.append({"name": "board", "type": "board", "target": board.spec.to_dict(),
                        "pose": {"matrix": [[round(float(x), 9) for x in row] for row in board.plane_to_camera]}})
    return {
        "name": name, "description": description,
        "camera": _camera_block(cam),
        "emitter": {"offset_m": [0.0, 0.0, 0.0], "power_w": float(power_w),
                    "profile": profile,
                    "waveform": {"harmonics": [[1, 1.0, 0.0]]}},
        "ambient_irradiance_w_m2": 0.0,
        "materials": materials, "objects": objects,
        # A linear, unclipped sensor: the fitted power maps the twin's amplitude onto the
        # device's amplitude counts (whatever their gain); noise comes from the capture itself.
        "sensor": {"taps": 4, "theta_deg": [0, 90, 180, 270], "freq_hz": [float(f) for f in freqs],
                   "integration_time_s": 1.0e-3, "wavelength_m": float(wavelength_m),
                   "quantum_efficiency": 0.3, "modulation_contrast": 1.0, "conversion_gain_dn_per_e": 1.0,
                   "full_well_e": 1.0e15, "read_noise_e": 0.0, "dark_current_e_per_s": 0.0, "adc_bits": 32,
                   "black_level_dn": 0.0, "fixed_pattern": {"dsnu_e": 0.0, "prnu": 0.0, "seed": 1}},
        "effects": {},
        "render": {"samples_per_pixel": 1, "bounces": 0},
    }


#: Emission-angle step of a fitted table profile (deg), and the even polynomial's degree in theta^2.
PROFILE_STEP_DEG = 2.5
PROFILE_DEGREE = 4


def fit_profile_table(theta_deg: np.ndarray, amp: np.ndarray, pred: np.ndarray, oid: np.ndarray, mask: np.ndarray,
                      beam_n: float, *, min_gain: float = 0.01) -> tuple[dict[str, Any] | None, float]:
    """The emitter profile ``cos^n (theta) exp(g(theta))`` as a table, ``g`` an even polynomial
    (theta^2 .. theta^(2 PROFILE_DEGREE), ``g(0) = 0``) fitted by least squares to the log
    ratio of measured to predicted amplitude after each object's own median level (its
    reflectance). Returns None when ``g`` changes the amplitude by less than ``min_gain``
    (rms in log amplitude): cos^n is then the profile. Also returns that rms."""
    if mask.sum() < 200:
        return None, 0.0
    th = np.radians(theta_deg[mask])
    lr = np.log(amp[mask] / pred[mask])
    ids = oid[mask]
    level = np.zeros_like(lr)
    g = np.zeros_like(lr)
    X = np.stack([th ** (2 * k) for k in range(1, PROFILE_DEGREE + 1)], axis=1)
    coef = np.zeros(PROFILE_DEGREE)
    for _ in range(3):  # alternate: each object's level, then the common angular shape
        for i in np.unique(ids):
            sel = ids == i
            level[sel] = np.median(lr[sel] - g[sel])
        coef = np.linalg.lstsq(X, lr - level, rcond=None)[0]
        g = X @ coef
    rms = float(np.sqrt(np.mean(g ** 2)))
    if rms < min_gain:
        return None, rms
    top = float(min(89.0, np.degrees(th.max()) + PROFILE_STEP_DEG))
    knots = np.append(np.arange(0.0, top, PROFILE_STEP_DEG), top)
    kr = np.radians(knots)
    gk = np.stack([kr ** (2 * k) for k in range(1, PROFILE_DEGREE + 1)], axis=1) @ coef
    values = np.cos(kr) ** beam_n * np.exp(gk)
    # beyond the field of view the emitter's light reaches nothing the camera sees: the last value up to 90 deg
    knots = np.append(knots, 90.0)
    values = np.append(values, values[-1])
    return {"type": "table", "theta_deg": [round(float(k), 4) for k in knots],
            "relative_intensity": [round(float(v), 6) for v in values]}, rms


def _predicted_amplitude(scene: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The twin's amplitude per pixel, its radial distance and object id (one render)."""
    from tofhil.demod import phasor
    from tofhil.sim.twin import Twin

    twin = Twin(scene)
    taps = twin.expected_taps().astype(np.float64)
    amp = np.abs(phasor(taps, twin.config.theta_rad)).mean(axis=0)
    result = twin.render()[1]
    return amp, np.asarray(result.radial_m), np.asarray(result.object_id)


def scene_from_capture(session_path: str | Path, out_path: str | Path, *, frame: int = 0, max_planes: int = 4,
                       freq_hz: Sequence[float] | None = None, wavelength_m: float | None = None,
                       mesh: bool = True, threshold_m: float | None = None, force: bool = False,
                       target: Any = None, progress: Callable[[str], None] | None = None) -> CaptureScene:
    """Build the twin scene of one frame of a session and write it (plus its sidecars).

    ``target``: a board the capture shows (:class:`tofhil.boards.BoardSpec` or its text): its
    pose comes from the amplitude image (photogrammetry, :func:`tofhil.targets.board_pose_from_amplitude`),
    not from the depth, and it is written as a ``board`` object; the range offset and the
    pose are then observable (the board is truth the depth did not decide).

    The steps: the capture's frame; a known target's pose (:func:`_target_of`); planes
    segmented from the cloud and the rest (:func:`_planes_and_rest`), written as outlines and
    a mesh (:func:`_write_geometry`); the emitter profile, power and reflectances fitted to
    the amplitude image (:func:`_fit_radiometry`); the pixels beyond the unambiguous range
    (:func:`_beyond_unambiguous_range`); the scene and its metadata written."""
    from tofhil.sim.scene import load_scene, scene_from_yaml

    t0 = time.perf_counter()
    say = progress or (lambda _m: None)
    out_path = Path(out_path)
    sidecars = _outputs(out_path, force)

    with open_session(session_path) as s:
        df = s.requested_depth_frame(frame)
        freqs, wl, freq_src = _frequencies(s, freq_hz, wavelength_m)
        cam = s.camera
    radial = np.asarray(df.radial_m, np.float64)
    valid = np.asarray(df.valid, bool) & np.isfinite(radial) & (radial > 0)
    amp = None if df.amplitude is None else np.asarray(df.amplitude, np.float64)
    has_amp = amp is not None and np.isfinite(amp[valid]).any()
    warnings: list[str] = []
    if valid.sum() < 500:
        raise TofhilError(f"has {int(valid.sum())} valid depth pixels in frame {frame}", file=session_path,
                          field="depth/valid", expected="at least 500 to fit a scene")
    board = _target_of(target, amp, has_amp, cam, session_path, warnings, say)
    pts_hw, planes, rest, thr = _planes_and_rest(cam, radial, valid, board, threshold_m, max_planes, say)
    mesh_path = out_path.with_name(out_path.stem + MESH_SUFFIX)
    written: list[Path] = []
    try:
        mesh_file = _write_geometry(out_path, cam, planes, pts_hw, rest, mesh=mesh, written=written, say=say)
        if not planes and mesh_file is None:
            raise TofhilError("no planar patch and no surface to mesh was found", file=session_path,
                              field="depth/radial_m", expected="a frame showing surfaces")

        # ---- radiometry: render with unit power, compare with the amplitude image
        names = [p.name for p in planes] + (["rest"] if mesh_file else []) + (["board"] if board else [])
        base_dir = out_path.resolve().parent
        desc = f"twin of {Path(session_path).name} frame {frame} (tofhil scene-from-capture)"

        def build(power_w: float, prof: dict[str, Any], r: dict[str, float]) -> Any:
            d = _scene_dict(out_path.stem, cam, freqs, wl, planes, mesh_file, r, power_w, prof, desc, board)
            return d, scene_from_yaml(yaml.safe_dump(d, sort_keys=False), source=str(out_path), base_dir=base_dir)

        if has_amp:
            power, profile, refl, radiometry = _fit_radiometry(build, names, cam, amp, valid, board, say)
        else:
            refl = {n: ASSUMED_REFLECTANCE for n in names}
            power, profile = 1.0, {"type": "cos_n", "n": 1.0}
            radiometry = {"amplitude": "absent: reflectances and power are assumed"}
            warnings.append("the session has no amplitude image: reflectances and emitter power are assumed")
        scene_d, sc = build(power, profile, refl)
        inside, r_u = _beyond_unambiguous_range(sc, freqs, radial, valid, has_amp, warnings)
        n_out = int((~inside).sum())

        meta = {"source_session": str(session_path), "frame": frame, "frequencies_hz": freqs,
                "frequencies_from": freq_src, "wavelength_m": wl, "unambiguous_range_m": r_u,
                "valid_mask": sidecars[2].name, "pixels_beyond_unambiguous_range": n_out,
                "planes": [{"name": p.name, "outline_mesh": p.outline_file,
                            "normal": p.normal.round(6).tolist(), "offset_m": p.offset_m,
                            "size_m": list(p.size), "pixels": int(p.pixels.sum()), "rms_m": p.rms_m}
                           for p in planes],
                "mesh": mesh_file, "mesh_pixels": int(rest.sum()) if mesh_file else 0,
                "ransac_threshold_m": thr, "radiometry": radiometry,
                "geometry_from_depth": board is None,
                "target": None if board is None else board.to_json(),
                "unobservable": dict(UNOBSERVABLE_FITTED_POSE) if board is None else {},
                "warnings": warnings, "seconds": round(time.perf_counter() - t0, 2)}
        written += [out_path, sidecars[1], sidecars[2]]
        out_path.write_text("# " + desc + "\n# made by tofhil scene-from-capture; metadata in "
                            + sidecars[1].name + "\n" + yaml.safe_dump(scene_d, sort_keys=False))
        np.save(sidecars[2], inside)
        sidecars[1].write_text(json.dumps(meta, indent=2))
        load_scene(out_path)  # the written file must load
    except BaseException:
        for p in written:
            p.unlink(missing_ok=True)
        raise
    return CaptureScene(scene_path=out_path, metadata_path=sidecars[1], valid_path=sidecars[2],
                        mesh_path=mesh_path if mesh_file else None, planes=planes, metadata=meta, warnings=warnings)


def _outputs(out_path: Path, force: bool) -> list[Path]:
    """The files scene-from-capture writes (scene, metadata, valid mask, mesh); refuses a
    directory, a missing directory and, without ``force``, any of them existing."""
    if out_path.is_dir():
        raise TofhilError("is a directory", file=out_path, field="--out", expected="a scene file name (.yaml)")
    if not out_path.parent.is_dir():
        raise TofhilError("directory does not exist", file=out_path.parent, field="--out")
    sidecars = [out_path, metadata_path_for(out_path), out_path.with_name(out_path.stem + VALID_SUFFIX),
                out_path.with_name(out_path.stem + MESH_SUFFIX)]
    existing = [p for p in sidecars if p.exists()] + sorted(out_path.parent.glob(out_path.stem + PLANE_GLOB))
    if existing:
        refuse_existing(existing[0], force, field="--out")
    return sidecars


def _target_of(target: Any, amp: np.ndarray | None, has_amp: bool, cam: CameraModel, session_path: str | Path,
               warnings: list[str], say: Callable[[str], None]) -> BoardFit | None:
    """A known target: its pose from the amplitude image (its pixels are then not segmented)."""
    if target is None:
        return None
    if not has_amp:
        raise TofhilError("has no amplitude image", file=session_path, field="--target",
                          expected="a capture with amplitude (the board is found in it)")
    board = fit_board(amp, cam, target)
    say(f"target: {board.spec.kind} {board.spec.cols}x{board.spec.rows} found ({board.pose.detection.n} corners, "
        f"reprojection {board.pose.rms_px:.3f} px rms); pose from the amplitude image, not from depth")
    if board.pose.rms_px > 1.0:
        warnings.append(f"the board's corners reproject with {board.pose.rms_px:.2f} px rms: its pose is "
                        "uncertain (blur, a bent board, or a camera model that does not fit)")
    return board


def _planes_and_rest(cam: CameraModel, radial: np.ndarray, valid: np.ndarray, board: BoardFit | None,
                     threshold_m: float | None, max_planes: int, say: Callable[[str], None]
                     ) -> tuple[np.ndarray, list[PlanePatch], np.ndarray, float]:
    """The cloud ``[H, W, 3]``, the planes segmented from it (less those whose rectangle would
    hide what the camera saw behind them), the pixels left for the mesh and the inlier
    threshold used."""
    pts_hw = cam.rays * radial[..., None]
    seg = valid if board is None else valid & ~board.pixels
    pix = np.flatnonzero(seg)
    points = pts_hw.reshape(-1, 3)[pix]
    med = float(np.median(radial[valid]))
    if threshold_m is None:
        # 1 % of the distance, or 3 sigma of the frame's own depth noise where it is larger: a
        # threshold below the noise splits one noisy wall into a plane and a mesh of the rest
        from tofhil.depth import relative_depth_noise

        noise = relative_depth_noise(radial, valid) * med
        thr = float(np.clip(max(0.01 * med, PLANE_NOISE_SIGMAS * noise), 0.004, 0.1))
    else:
        thr = threshold_m
    say(f"segmenting planes (RANSAC, inlier threshold {thr * 1e3:.1f} mm) in {len(points)} points")
    planes = _segment_planes(points, pix, cam.shape, max_planes=max_planes, threshold_m=thr, min_fraction=0.02)
    kept = []
    for p in planes:
        frac = occluding_fraction(cam, p, radial, valid, 3.0 * thr)
        if frac > MAX_OCCLUDING_FRACTION:
            say(f"{p.name}: its rectangle would hide {100 * frac:.0f}% of what the camera saw behind it; "
                "left to the mesh")
        else:
            kept.append(p)
    planes = [dataclasses.replace(p, name=f"plane{i}") for i, p in enumerate(kept)]
    on_plane = np.zeros(cam.shape, bool)
    for p in planes:
        on_plane |= p.pixels
    rest = valid & ~on_plane if board is None else valid & ~on_plane & ~board.pixels
    return pts_hw, planes, rest, thr


def _write_geometry(out_path: Path, cam: CameraModel, planes: list[PlanePatch], pts_hw: np.ndarray,
                    rest: np.ndarray, *, mesh: bool, written: list[Path], say: Callable[[str], None]) -> str | None:
    """Each plane's outline beside the scene (its ``outline_file`` set) and, with ``mesh``,
    the non-planar rest as a triangle mesh; every file written is added to ``written``.
    Returns the mesh's file name (None: no mesh)."""
    mesh_file: str | None = None
    mesh_path = out_path.with_name(out_path.stem + MESH_SUFFIX)
    stride = max(1, int(round(math.sqrt(cam.width * cam.height / 65536))))
    for p in planes:
        # the patch's own outline (holes where something else was seen in front of it), not
        # the rectangle around it: pixels a rectangle would cover beyond the patch are not the plane
        plane_file = out_path.with_name(f"{out_path.stem}_{p.name}.ply")
        written.append(plane_file)
        if write_plane_outline(cam, p, plane_file, stride):
            p.outline_file = plane_file.name
        else:
            plane_file.unlink(missing_ok=True)
    if mesh and rest.sum() >= 200:
        from tofhil.open3d_loader import open3d

        verts, tris = grid_mesh(pts_hw, rest, stride=stride)
        if len(tris):
            o3d = open3d()
            m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(verts), o3d.utility.Vector3iVector(tris))
            written.append(mesh_path)
            o3d.io.write_triangle_mesh(str(mesh_path), m, write_ascii=False)
            mesh_file = mesh_path.name
            say(f"the non-planar rest: {len(tris)} triangles from {int(rest.sum())} pixels -> {mesh_path.name}")
    return mesh_file


def _fit_radiometry(build: Callable[[float, dict[str, Any], dict[str, float]], Any], names: list[str],
                    cam: CameraModel, amp: np.ndarray, valid: np.ndarray, board: BoardFit | None,
                    say: Callable[[str], None]) -> tuple[float, dict[str, Any], dict[str, float], dict[str, Any]]:
    """The emitter's profile (cos^n, then a table over the emission angle where cos^n cannot
    follow), power and each object's reflectance fitted to the amplitude image by rendering
    the twin (``build(power, profile, reflectances)`` -> (scene dict, scene)); returns them and
    the radiometry report."""
    refl = {n: ASSUMED_REFLECTANCE for n in names}
    beam_n, power = 1.0, 1.0
    profile: dict[str, Any] = {"type": "cos_n", "n": beam_n}
    usable = valid & np.isfinite(amp) & (amp > 0) & ~saturated_amplitude(amp, valid)
    say("rendering the twin for the radiometry fit")
    _, sc = build(power, profile, refl)
    pred, _, oid = _predicted_amplitude(sc)
    biggest = max(range(len(names)), key=lambda i: int(((oid == i) & usable).sum()))
    sel = (oid == biggest) & usable & (pred > 0)
    cos_e = cam.rays[..., 2]
    if sel.sum() > 100 and np.ptp(np.log(cos_e[sel])) > 0.05:
        x, y = np.log(cos_e[sel]), np.log(amp[sel] / pred[sel])
        slope = float(np.polyfit(x, y, 1)[0])
        beam_n = float(np.clip(1.0 + slope, 0.0, 30.0))
        profile = {"type": "cos_n", "n": round(beam_n, 4)}
        _, sc = build(power, profile, refl)
        pred, _, oid = _predicted_amplitude(sc)
        # What cos^n cannot follow (a diffuser flatter than cos^0, vignetting beyond
        # cos^4): an even polynomial in the emission angle, fitted to every object's
        # log ratio after its own level; written as a table profile.
        m = usable & (pred > 0) & (oid >= 0)
        table, g_rms = fit_profile_table(np.degrees(np.arccos(np.clip(cos_e, -1, 1))), amp, pred, oid, m,
                                         beam_n)
        if table is not None:
            profile = table
            _, sc = build(power, profile, refl)
            pred, _, oid = _predicted_amplitude(sc)
            say(f"emitter profile: cos^{beam_n:.2f} corrected by a table over the emission angle "
                f"({g_rms:.2f} rms in log amplitude)")
    ratio = {}
    for i, n in enumerate(names):
        m = (oid == i) & usable & (pred > 0)
        ratio[n] = float(np.median(amp[m] / pred[m])) if m.sum() >= 20 else float("nan")
    ref = ratio[names[biggest]]
    top = max(v for k, v in ratio.items() if math.isfinite(v) and k != "board")
    # The render had power 1 W and reflectance R0 everywhere; amplitude is linear in
    # power x reflectance, so object n needs P r_n / R0 = ratio_n. Only the product is
    # seen: the largest surface gets R0 unless another would then exceed 1. A board's
    # ink and paper reflectances are known, so its ratio is the power itself.
    if board is not None and math.isfinite(ratio.get("board", float("nan"))):
        power = ratio["board"]
    else:
        power = max(ref, ASSUMED_REFLECTANCE * top)
    refl = {n: float(np.clip(ASSUMED_REFLECTANCE * v / power, 1e-4, 1.0)) if math.isfinite(v)
            else ASSUMED_REFLECTANCE for n, v in ratio.items() if n != "board"}
    _, sc = build(power, profile, refl)
    pred, _, oid = _predicted_amplitude(sc)
    m = usable & (pred > 0)
    lr = np.log(amp[m] / pred[m])
    radiometry = {"amplitude": "fitted", "beam_exponent_n": beam_n, "profile": profile["type"],
                  "power_w": power,
                  "reflectance": refl, "reflectance_of_largest_surface_assumed": ASSUMED_REFLECTANCE,
                  "log_amplitude_residual_median": float(np.median(lr)),
                  "log_amplitude_residual_mad": float(1.4826 * np.median(np.abs(lr - np.median(lr)))),
                  "pixels": int(m.sum())}
    say(f"radiometry: beam cos^{beam_n:.2f}" + (" + table" if profile["type"] == "table" else "")
        + f", power {power:.4g} W, reflectances " + ", ".join(f"{k} {v:.3f}" for k, v in refl.items()))
    return power, profile, refl, radiometry


def _beyond_unambiguous_range(sc: Any, freqs: list[float], radial: np.ndarray, valid: np.ndarray, has_amp: bool,
                              warnings: list[str]) -> tuple[np.ndarray, float]:
    """The valid mask of the twin (False where the capture or the twin sees beyond the
    frequencies' unambiguous range: the twin wraps there) and that range; a warning when
    there are such pixels."""
    plan = frequency_plan(np.asarray(freqs))
    r_u = float(plan.unambiguous_range_m)
    _, twin_r, oid = _predicted_amplitude(sc) if has_amp else (None, *_render_range(sc))
    inside = ~(np.isfinite(twin_r) & (twin_r >= r_u)) & ~(valid & (radial >= r_u))
    n_out = int((~inside).sum())
    if n_out:
        warnings.append(f"{n_out} pixels ({100.0 * n_out / inside.size:.1f}%) see the scene beyond the "
                        f"unambiguous range {r_u:.3f} m of {', '.join(f'{f / 1e6:g} MHz' for f in freqs)}: "
                        "the twin wraps there; they are outside the valid mask")
    return inside, r_u


def _render_range(scene: Any) -> tuple[np.ndarray, np.ndarray]:
    from tofhil.sim.twin import Twin

    r = Twin(scene).render()[1]
    return np.asarray(r.radial_m), np.asarray(r.object_id)


@dataclass
class CaptureFacts:
    """What diagnosis needs to know of a scene made from a capture (empty for other scenes)."""

    unobservable: dict[str, str] = field(default_factory=dict)
    valid_mask: np.ndarray | None = None
    #: Relative scatter of the capture's amplitude about the scene's (log-amplitude MAD).
    amplitude_model_error: float | None = None
    #: The planes were fitted to the capture's own depth (no known target).
    geometry_from_depth: bool = False


def capture_scene_facts(scene: Any) -> CaptureFacts:
    """For a scene made by :func:`scene_from_capture` (its metadata beside its file): the
    effects it cannot observe, its valid mask (full capture resolution) and how well it
    knows the amplitude; else nothing."""
    src = getattr(scene, "source", None)
    if not src or str(src).startswith("<"):
        return CaptureFacts()
    meta = read_capture_metadata(src)
    if not meta:
        return CaptureFacts()
    mask = None
    name = meta.get("valid_mask")
    if name:
        p = Path(src).with_name(str(name))
        if p.is_file():
            mask = np.load(p).astype(bool)
    err = (meta.get("radiometry") or {}).get("log_amplitude_residual_mad")
    return CaptureFacts(dict(meta.get("unobservable") or {}), mask, float(err) if err else None,
                        bool(meta.get("geometry_from_depth", False)))
