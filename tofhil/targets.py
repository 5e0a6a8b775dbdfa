"""Calibration boards in amplitude images: detection, sub-pixel corners and the board's pose.

A ToF camera's amplitude image is a NIR photograph lit by the camera's own emitter: the
printed board (:mod:`tofhil.boards`) shows as dark ink on bright paper, fading towards the
corners (beam profile, cos^4, 1/r^2). :func:`to_8bit` stretches it robustly (percentiles,
so a few hot pixels or specular glints do not flatten the board); the detectors are
OpenCV's: ``findChessboardCornersSB`` (sub-pixel corners of its own; ``findChessboardCorners``
plus ``cornerSubPix`` when it finds nothing) for checkerboards, ``CharucoDetector`` for
ChArUco and ``ArucoDetector`` for ArUco grids. :func:`board_pose` solves the board-to-camera
transform with ``solvePnP`` (IPPE for a plane, then Levenberg-Marquardt) in the camera model
of :mod:`tofhil.camera` (OpenCV's distortion) and reports every corner's reprojection error.

Pixel coordinates follow ARCHITECTURE.md and OpenCV: pixel centres at integers.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from tofhil.boards import BoardSpec
from tofhil.camera import CameraModel
from tofhil.errors import TofhilError

#: Percentiles of the valid amplitudes mapped to 0 and 255 by :func:`to_8bit`.
STRETCH_PERCENTILES = (0.5, 99.5)


@dataclass
class BoardDetection:
    """Board corners found in one image: ``image_points[i]`` (px) sees ``object_points[i]``
    (board frame, m); ``ids[i]`` indexes :meth:`BoardSpec.corner_points`."""

    spec: BoardSpec
    image_points: np.ndarray   # [N, 2] float64
    object_points: np.ndarray  # [N, 3] float64
    ids: np.ndarray            # [N] int
    image_size: tuple[int, int]  # (width, height)

    @property
    def n(self) -> int:
        return len(self.ids)


@dataclass
class BoardPose:
    """The board's pose in the camera frame and how well it explains the corners."""

    board_to_camera: np.ndarray       # 4x4: board frame -> camera frame
    errors_px: np.ndarray             # [N] reprojection error per detected corner
    detection: BoardDetection
    residuals_px: np.ndarray = field(repr=False, default=None)  # type: ignore[assignment]  # [N, 2]

    @property
    def rms_px(self) -> float:
        return float(np.sqrt(np.mean(self.errors_px ** 2)))

    @property
    def rvec(self) -> np.ndarray:
        import cv2

        return cv2.Rodrigues(self.board_to_camera[:3, :3])[0].ravel()

    @property
    def tvec(self) -> np.ndarray:
        return self.board_to_camera[:3, 3].copy()


# --------------------------------------------------------------------------- images
def amplitude_image(frame_or_amplitude: Any) -> np.ndarray:
    """The amplitude of a :class:`tofhil.frames.DepthFrame` (or an array as it is), float64
    with invalid pixels (NaN, masked by the frame's validity) set to NaN."""
    amp = getattr(frame_or_amplitude, "amplitude", frame_or_amplitude)
    if amp is None:
        raise TofhilError("the depth frame has no amplitude image", field="amplitude",
                          expected="a frame with amplitude (a session with depth/amplitude or raw taps)")
    a = np.array(amp, dtype=np.float64)
    if a.ndim != 2:
        raise TofhilError(f"amplitude has shape {a.shape}", field="amplitude", expected="a 2-D image")
    return a


def to_8bit(image: np.ndarray) -> np.ndarray:
    """A grey image (any range, NaN = unknown) -> uint8, percentiles ``STRETCH_PERCENTILES``
    of the finite values to 0 and 255; unknown pixels become black."""
    img = np.asarray(image, dtype=np.float64)
    finite = np.isfinite(img)
    if not finite.any():
        return np.zeros(img.shape, dtype=np.uint8)
    lo, hi = np.percentile(img[finite], STRETCH_PERCENTILES)
    if hi <= lo:
        hi = lo + 1.0
    out = np.clip((np.where(finite, img, lo) - lo) / (hi - lo), 0.0, 1.0)
    return np.round(out * 255.0).astype(np.uint8)


# --------------------------------------------------------------------------- detection
def detect_board(image: np.ndarray, spec: BoardSpec | str | dict) -> BoardDetection | None:
    """Find the board's corners in a grey image (any range, NaN allowed); None when the board
    is not found (or too few corners for a pose)."""
    spec = BoardSpec.parse(spec)
    img8 = image if np.asarray(image).dtype == np.uint8 else to_8bit(image)
    h, w = img8.shape
    if spec.kind == "checkerboard":
        pts = _chessboard_corners(img8, spec, np.asarray(image, dtype=np.float64))
        if pts is None:
            return None
        ids = np.arange(len(pts))
    elif spec.kind == "charuco":
        import cv2

        det = cv2.aruco.CharucoDetector(spec.cv_board())
        corners, cid, _, _ = det.detectBoard(img8)
        if cid is None or len(cid) < 4:
            return None
        pts, ids = corners.reshape(-1, 2).astype(np.float64), cid.ravel().astype(int)
    else:
        pts, ids = _aruco_corners(img8, spec)
        if pts is None:
            return None
    obj = spec.corner_points()[ids]
    return BoardDetection(spec=spec, image_points=pts, object_points=obj, ids=ids, image_size=(w, h))


def _chessboard_corners(img8: np.ndarray, spec: BoardSpec, image: np.ndarray) -> np.ndarray | None:
    import cv2

    size = (spec.cols - 1, spec.rows - 1)
    # The image is stretched already; histogram equalisation (NORMALIZE_IMAGE) loses boards
    # in dim corners of the view more often than it finds them, so it is the second try.
    ok, corners = False, None
    for flags in (cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY,
                  cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY):
        ok, corners = cv2.findChessboardCornersSB(img8, size, flags=flags)
        if ok:
            break
    if not ok:
        ok, corners = cv2.findChessboardCorners(img8, size, flags=cv2.CALIB_CB_ADAPTIVE_THRESH |
                                                cv2.CALIB_CB_NORMALIZE_IMAGE)
        if not ok:
            return None
        corners = cv2.cornerSubPix(img8, corners, (3, 3), (-1, -1),
                                   (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3))
    grid = _orient_grid(corners.reshape(size[1], size[0], 2).astype(np.float64), img8)
    return refine_saddle_grid(image, grid).reshape(-1, 2)


def _orient_grid(grid: np.ndarray, img8: np.ndarray) -> np.ndarray:
    """Reorder a detected corner grid ``[rows-1, cols-1, 2]`` so that corner (0, 0) is the one
    next to the board's top-left (ink) square and board x, y appear right-handed (x cross y
    into the image), as a board seen from its printed side does. The detectors' own order
    depends on the view."""
    best = grid
    for g in (grid, grid[::-1, ::-1], grid[::-1, :], grid[:, ::-1]):
        ex = g[0, 1] - g[0, 0]
        ey = g[1, 0] - g[0, 0]
        if ex[0] * ey[1] - ex[1] * ey[0] <= 0:
            continue  # mirrored: not the printed side's order
        # the square diagonally outside corner (0, 0) is the top-left square: ink
        outer = g[0, 0] - 0.5 * ex - 0.5 * ey
        inner = g[0, 0] + 0.5 * ex - 0.5 * ey  # its neighbour along x: paper
        if _sample(img8, outer) < _sample(img8, inner):
            return g
        best = g
    return best


# --------------------------------------------------------------------------- corner model fit
#: Largest half-width of the window a corner is fitted in (px).
MAX_FIT_RADIUS_PX = 6


def refine_saddle_grid(image: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """Refine checkerboard corners ``[R, C, 2]`` by fitting each corner's neighbourhood with
    the image of an ideal corner: two straight edges through ``(x0, y0)``, ink and paper
    levels and a linear shading, every pixel integrating the pattern over its square area.

    OpenCV's corner estimators lock towards pixel centres by several hundredths of a pixel
    (worse on small, low-resolution boards); the area model is unbiased for straight edges,
    so the fitted corners are not pulled to the pixel grid. A corner whose fit moves by more
    than a pixel, or whose window leaves the image, keeps the detector's position. The
    window's half-width is a little under half the corner spacing (2 to
    ``MAX_FIT_RADIUS_PX`` px); the edges start along the grid's directions. All corners are
    fitted in one sparse least-squares problem (each corner's parameters touch only its
    window's residuals)."""
    from scipy.optimize import least_squares
    from scipy.sparse import lil_matrix

    img = np.asarray(image, dtype=np.float64)
    finite = np.isfinite(img)
    if not finite.any():
        return grid
    scale = np.nanpercentile(img, 99.5)
    img = img / (scale if scale > 0 else 1.0)
    rows, cols = grid.shape[:2]
    h, w = img.shape
    windows, starts, where = [], [], []
    for i in range(rows):
        for j in range(cols):
            x, y = grid[i, j]
            ex = (grid[i, min(j + 1, cols - 1)] - grid[i, max(j - 1, 0)]) / (min(j + 1, cols - 1) - max(j - 1, 0))
            ey = (grid[min(i + 1, rows - 1), j] - grid[max(i - 1, 0), j]) / (min(i + 1, rows - 1) - max(i - 1, 0))
            r = int(np.clip(np.floor(0.5 * min(np.linalg.norm(ex), np.linalg.norm(ey)) - 1.0), 2, MAX_FIT_RADIUS_PX))
            xi, yi = int(round(x)), int(round(y))
            if xi - r < 0 or yi - r < 0 or xi + r >= w or yi + r >= h:
                continue
            ok = finite[yi - r:yi + r + 1, xi - r:xi + r + 1]
            if ok.sum() < 12:
                continue
            Y, X = np.mgrid[yi - r:yi + r + 1, xi - r:xi + r + 1].astype(np.float64)
            v = img[yi - r:yi + r + 1, xi - r:xi + r + 1][ok]
            X, Y = X[ok], Y[ok]
            # edge normals perpendicular to the grid directions; which quadrants are ink: the
            # start that explains the window better
            t1, t2 = np.arctan2(ex[0], -ex[1]), np.arctan2(ey[0], -ey[1])
            lo, hi = float(v.min()), float(v.max())
            cands = [np.array([x, y, t1, t2, a, b, 0.0, 0.0]) for a, b in ((lo, hi), (hi, lo))]
            p0 = min(cands, key=lambda p: float(np.sum((_corner_model(p, X, Y) - v) ** 2)))
            windows.append((X, Y, v))
            starts.append(p0)
            where.append((i, j))
    if not windows:
        return grid
    n_par = 8
    offsets = np.cumsum([0] + [len(wv[2]) for wv in windows])
    sparsity = lil_matrix((offsets[-1], n_par * len(windows)), dtype=int)
    for k in range(len(windows)):
        sparsity[offsets[k]:offsets[k + 1], n_par * k:n_par * (k + 1)] = 1

    corner = np.repeat(np.arange(len(windows)), np.diff(offsets))
    X_all, Y_all, v_all = (np.concatenate([wv[c] for wv in windows]) for c in range(3))

    def residuals(p: np.ndarray) -> np.ndarray:
        return _corner_model(p.reshape(-1, n_par)[corner].T, X_all, Y_all) - v_all

    fit = least_squares(residuals, np.concatenate(starts), jac_sparsity=sparsity, method="trf",
                        x_scale="jac", max_nfev=200)
    out = grid.copy()
    for k, (i, j) in enumerate(where):
        xy = fit.x[n_par * k:n_par * k + 2]
        if np.all(np.isfinite(xy)) and np.all(np.abs(xy - grid[i, j]) < 1.0):
            out[i, j] = xy
    return out


def _corner_model(p: np.ndarray, X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """Pixel values of an ideal corner: edges with normals at angles ``t1``, ``t2`` through
    ``(x0, y0)``; level ``a`` where the pixel is on equal sides of both, ``b`` elsewhere;
    times a linear shading ``1 + gx dx + gy dy``. ``p`` is one parameter vector or ``[8, N]``
    (one per pixel)."""
    x0, y0, t1, t2, a, b, gx, gy = p
    dx, dy = X - x0, Y - y0
    c1 = _box_edge_fraction(np.cos(t1) * dx + np.sin(t1) * dy, np.cos(t1), np.sin(t1))
    c2 = _box_edge_fraction(np.cos(t2) * dx + np.sin(t2) * dy, np.cos(t2), np.sin(t2))
    same = c1 * c2 + (1 - c1) * (1 - c2)   # the two pixel fractions taken as independent
    return (b + (a - b) * same) * (1 + gx * dx + gy * dy)


def _box_edge_fraction(d: np.ndarray, nx: np.ndarray, ny: np.ndarray) -> np.ndarray:
    """Fraction of a unit pixel on the positive side of a straight edge with unit normal
    ``(nx, ny)`` at signed distance ``d`` from the pixel centre: the distribution of
    ``n . (u, v)`` over the pixel is the sum of two uniforms of widths ``|nx|``, ``|ny|``
    (a trapezoid), and the fraction is its CDF at ``d``."""
    big = np.maximum(np.abs(nx), np.abs(ny))
    small = np.maximum(np.minimum(np.abs(nx), np.abs(ny)), 1e-6)
    low = d + (big + small) / 2
    high = (big + small) / 2 - d
    f_low = np.where(low <= 0, 0.0, low ** 2 / (2 * big * small))
    f_high = np.where(high <= 0, 1.0, 1 - high ** 2 / (2 * big * small))
    f_mid = (d + big / 2) / big
    half = (big - small) / 2
    return np.where(d < -half, f_low, np.where(d > half, f_high, f_mid))


def _sample(img8: np.ndarray, p: np.ndarray) -> float:
    h, w = img8.shape
    x = int(np.clip(round(p[0]), 0, w - 1))
    y = int(np.clip(round(p[1]), 0, h - 1))
    return float(img8[y, x])


def _aruco_corners(img8: np.ndarray, spec: BoardSpec) -> tuple[np.ndarray | None, np.ndarray]:
    import cv2

    board = spec.cv_board()
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    det = cv2.aruco.ArucoDetector(board.getDictionary(), params)
    corners, mid, _ = det.detectMarkers(img8)
    if mid is None or len(mid) == 0:
        return None, np.zeros(0, dtype=int)
    board_ids = list(np.asarray(board.getIds()).ravel())
    pts, ids = [], []
    for c, m in zip(corners, mid.ravel()):
        if m in board_ids:
            k = board_ids.index(m)
            pts.append(np.asarray(c, dtype=np.float64).reshape(4, 2))
            ids.extend(range(4 * k, 4 * k + 4))
    if not pts:
        return None, np.zeros(0, dtype=int)
    return np.concatenate(pts), np.asarray(ids, dtype=int)


# --------------------------------------------------------------------------- pose
def opencv_points(camera: CameraModel, image_points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(image points, K, dist) for OpenCV's pinhole solvers (solvePnP, stereoCalibrate): the
    camera's own for plumb_bob and rational (OpenCV takes 5, 8 or 12 coefficients); a
    fisheye's points undistorted to the pinhole with the same K and no distortion (OpenCV's
    pinhole solvers have no fisheye model; the points must lie less than 90 degrees off axis)."""
    img = np.asarray(image_points, dtype=np.float64)
    if not camera.is_fisheye:
        return img, camera.K, np.asarray(camera.dist, dtype=np.float64)
    x, y = camera.undistort_normalized(img[..., 0], img[..., 1])
    pin = np.stack([camera.fx * x + camera.cx, camera.fy * y + camera.cy], axis=-1)
    return pin, camera.K, np.zeros(5)


def board_pose(detection: BoardDetection, camera: CameraModel) -> BoardPose:
    """The board's pose from its detected corners (solvePnP, IPPE then LM refinement)."""
    import cv2

    if detection.n < 4:
        raise TofhilError(f"only {detection.n} board corners", field="target", expected="at least 4 corners")
    if detection.image_size != (camera.width, camera.height):
        raise TofhilError(f"image is {detection.image_size[0]}x{detection.image_size[1]}, camera is "
                          f"{camera.width}x{camera.height}", field="camera", expected="the image's camera")
    obj = detection.object_points.astype(np.float64)
    img = detection.image_points.astype(np.float64)
    pin, K, dist = opencv_points(camera, img)
    ok, rvec, tvec = cv2.solvePnP(obj, pin, K, dist, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        ok, rvec, tvec = cv2.solvePnP(obj, pin, K, dist, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        raise TofhilError("solvePnP found no pose", field="target", expected="a board seen in the image")
    rvec, tvec = cv2.solvePnPRefineLM(obj, pin, K, dist, rvec, tvec)
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = tvec.ravel()
    proj = camera.project(obj @ T[:3, :3].T + T[:3, 3])
    res = proj - img
    return BoardPose(board_to_camera=T, errors_px=np.linalg.norm(res, axis=1), detection=detection,
                     residuals_px=res)


def board_pose_from_amplitude(frame_or_amplitude: Any, camera: CameraModel,
                              target: BoardSpec | str | dict) -> BoardPose:
    """The board's pose from an amplitude image (a DepthFrame or a 2-D array) and the camera:
    the independent truth a capture's range errors are measured against. Raises
    :class:`TofhilError` when the board is not found."""
    spec = BoardSpec.parse(target)
    amp = amplitude_image(frame_or_amplitude)
    det = detect_board(amp, spec)
    if det is None:
        raise TofhilError(f"no {spec.kind} {spec.cols}x{spec.rows} board found in the amplitude image",
                          field="target", expected="the whole board in view with contrast")
    return board_pose(det, camera)
