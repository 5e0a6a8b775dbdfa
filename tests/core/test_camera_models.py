"""OpenCV's rational (+ thin prism) and fisheye models beside plumb_bob: projection and
unprojection against OpenCV's own functions, round trips, closed forms, files and errors."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from tofhil.camera import CameraModel, check_distortion
from tofhil.errors import InputFileError
from tofhil.schema import Schema

TIGHT = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 1000, 1e-15)

#: A real wide rational lens: the Azure Kinect depth camera's factory coefficients (the
#: recording in shared/data/real: k1..k6 and p1, p2) on its 1024 x 1024 sensor.
KINECT = (0.5479397773742676, -0.020971370860934258, 2.0557534298859537e-05, -7.210415787994862e-05,
          -0.002652231603860855, 0.8896790742874146, 0.08613020926713943, -0.013910384848713875)
RATIONAL = CameraModel(1024, 1024, 504.6, 504.7, 511.3, 512.8, dist=KINECT, distortion_model="rational")
PRISM = CameraModel(1024, 1024, 504.6, 504.7, 511.3, 512.8, distortion_model="rational",
                    dist=KINECT + (0.0012, -0.0003, -0.0008, 0.0002))
PLUMB = CameraModel(640, 480, 320.0, 321.0, 319.2, 240.7, dist=(-0.28, 0.09, 0.0008, -0.0005, 0.002))
#: A fisheye of the kind cv2.fisheye.calibrate returns for a ~190 degree lens.
FISHEYE = CameraModel(1024, 1024, 300.0, 300.5, 511.3, 512.8, distortion_model="fisheye",
                      dist=(-0.0134, 0.0352, -0.0281, 0.0079))


def rays_up_to(deg: float, n_theta: int = 61) -> np.ndarray:
    """Unit rays on rings from the axis to ``deg`` off axis, every 15 degrees of azimuth."""
    th = np.radians(np.linspace(0.0, deg, n_theta))
    ph = np.radians(np.arange(0.0, 360.0, 15.0))
    t, p = np.meshgrid(th, ph)
    return np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1).reshape(-1, 3)


def px(cam: CameraModel, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Normalised coordinates as pixels (the unit the 1e-6 px requirement is stated in)."""
    return np.stack([cam.fx * x + cam.cx, cam.fy * y + cam.cy], axis=-1)


@pytest.mark.parametrize("cam", [PLUMB, RATIONAL, PRISM], ids=["plumb_bob", "rational", "thin_prism"])
def test_projection_matches_opencv_to_60_degrees(cam: CameraModel) -> None:
    pts = rays_up_to(60.0) * 2.5
    ref, _ = cv2.projectPoints(pts[:, None, :], np.zeros(3), np.zeros(3), cam.K, np.array(cam.dist))
    np.testing.assert_allclose(cam.project(pts), ref[:, 0], rtol=0, atol=1e-6)


@pytest.mark.parametrize("cam", [PLUMB, RATIONAL, PRISM], ids=["plumb_bob", "rational", "thin_prism"])
def test_unprojection_matches_opencv_and_round_trips(cam: CameraModel) -> None:
    """Pixels of rays up to 60 degrees off axis (the rational lens reaches them inside its
    image) and the whole image grid: our inverse against cv2.undistortPoints run to
    convergence, and both round trips, to 1e-6 px."""
    rays = rays_up_to(60.0 if cam is not PLUMB else 40.0)
    uv = cam.project(rays)
    v, u = np.mgrid[0:cam.height:16, 0:cam.width:16].astype(np.float64)
    grid = np.stack([u.ravel(), v.ravel()], axis=-1)
    # the image inside the field the rays reach (the 1024 px sensor's corners lie beyond the
    # Kinect lens's fold: no ray maps there; test_pixels_beyond_the_fold_have_no_ray)
    reach = np.hypot(*((uv - (cam.cx, cam.cy)) / (cam.fx, cam.fy)).T).max()
    grid = grid[np.hypot(*((grid - (cam.cx, cam.cy)) / (cam.fx, cam.fy)).T) <= reach]
    if cam is RATIONAL or cam is PRISM:
        assert np.all((uv >= -1.1) & (uv <= 1025.0))      # 60 deg is inside this lens's image
    for pix in (uv, grid):
        x, y = cam.undistort_normalized(pix[:, 0], pix[:, 1])
        assert np.all(np.isfinite(x))
        ref = cv2.undistortPoints(pix[:, None, :], cam.K, np.array(cam.dist), criteria=TIGHT)[:, 0]
        np.testing.assert_allclose(px(cam, x, y), px(cam, ref[:, 0], ref[:, 1]), rtol=0, atol=1e-6)
        # pixel -> ray -> pixel
        back = cam.project(cam.pixel_rays(pix[:, 0], pix[:, 1]))
        np.testing.assert_allclose(back, pix, rtol=0, atol=1e-6)
    # ray -> pixel -> ray: the normalised coordinates of the rays, in pixels
    x, y = cam.undistort_normalized(uv[:, 0], uv[:, 1])
    np.testing.assert_allclose(px(cam, x, y), px(cam, rays[:, 0] / rays[:, 2], rays[:, 1] / rays[:, 2]),
                               rtol=0, atol=1e-6)


def test_opencv_default_undistortion_is_far_off_at_wide_angles() -> None:
    """Why the inverse runs to convergence: OpenCV's default (5 fixed-point steps) misses the
    rational lens's 60 degree rays by pixels; ours does not."""
    rays = rays_up_to(60.0)
    uv = RATIONAL.project(rays)
    ref = cv2.undistortPoints(uv[:, None, :], RATIONAL.K, np.array(RATIONAL.dist))[:, 0]
    truth = px(RATIONAL, rays[:, 0] / rays[:, 2], rays[:, 1] / rays[:, 2])
    assert np.abs(px(RATIONAL, ref[:, 0], ref[:, 1]) - truth).max() > 1.0
    x, y = RATIONAL.undistort_normalized(uv[:, 0], uv[:, 1])
    assert np.abs(px(RATIONAL, x, y) - truth).max() < 1e-6


def test_fisheye_projection_and_unprojection_match_opencv() -> None:
    d = np.array(FISHEYE.dist)
    rays = rays_up_to(85.0, 86)
    pts = rays * 2.0
    ref, _ = cv2.fisheye.projectPoints(pts[:, None, :], np.zeros(3), np.zeros(3), FISHEYE.K, d)
    uv = FISHEYE.project(pts)
    np.testing.assert_allclose(uv, ref[:, 0], rtol=0, atol=1e-6)
    und = cv2.fisheye.undistortPoints(uv[:, None, :], FISHEYE.K, d, criteria=TIGHT)[:, 0]
    x, y = FISHEYE.undistort_normalized(uv[:, 0], uv[:, 1])
    # 1e-6 px in the image: compare the distorted images of both answers (x/z itself grows as
    # tan: 11 at 85 degrees) and the answers themselves on the sphere.
    ours = FISHEYE.project(np.stack([x, y, np.ones_like(x)], -1))
    theirs = FISHEYE.project(np.stack([und[:, 0], und[:, 1], np.ones_like(x)], -1))
    np.testing.assert_allclose(ours, theirs, rtol=0, atol=1e-6)
    np.testing.assert_allclose(ours, uv, rtol=0, atol=1e-6)
    r = FISHEYE.pixel_rays(uv[:, 0], uv[:, 1])
    np.testing.assert_allclose(r, rays, rtol=0, atol=1e-12)
    theirs_ray = np.stack([und[:, 0], und[:, 1], np.ones(len(und))], -1)
    theirs_ray /= np.linalg.norm(theirs_ray, axis=1, keepdims=True)
    assert np.linalg.norm(r - theirs_ray, axis=1).max() < 1e-9      # rad (the chord)


def test_equidistant_fisheye_closed_form_beyond_90_degrees() -> None:
    """k = 0: the pixel ``rho`` px from the centre sees the ray ``theta = rho / f`` off axis,
    also behind the lens plane (a 200 degree field)."""
    cam = CameraModel(801, 801, 200.0, 200.0, 400.0, 400.0, distortion_model="fisheye", dist=(0, 0, 0, 0))
    rho = np.linspace(0.0, 340.0, 35)                           # up to 97.4 degrees
    az = np.radians(30.0)
    u, v = cam.cx + rho * np.cos(az), cam.cy + rho * np.sin(az)
    r = cam.pixel_rays(u, v)
    theta = rho / 200.0
    want = np.stack([np.sin(theta) * np.cos(az), np.sin(theta) * np.sin(az), np.cos(theta)], -1)
    np.testing.assert_allclose(r, want, rtol=0, atol=1e-14)
    np.testing.assert_allclose(cam.project(r * 3.0), np.stack([u, v], -1), rtol=0, atol=1e-9)
    x, _ = cam.undistort_normalized(u, v)                       # no x/z at or beyond 90 degrees
    assert np.all(np.isfinite(x[theta < np.pi / 2 - 1e-9])) and np.all(np.isnan(x[theta >= np.pi / 2]))
    # the field of view the fisheye mapping gives: the image edge at hfov / 2
    wide = CameraModel.from_fov(640, 480, 150.0, distortion_model="fisheye", dist=(0.0, 0.0, 0.0, 0.0))
    edge = wide.pixel_rays(np.array(-0.5), np.array(wide.cy))
    assert np.degrees(np.arccos(edge[2])) == pytest.approx(75.0, abs=1e-9)


def test_compiled_and_numpy_inversions_agree(monkeypatch: pytest.MonkeyPatch) -> None:
    """Many points run compiled, few through numpy: the same Newton steps (bit-identical for
    the Brown-Conrady family, to rounding for the fisheye's sin/cos)."""
    import tofhil.camera as camera_module

    rng = np.random.default_rng(3)
    u, v = rng.uniform(-0.5, 1023.5, (2, 80, 80))
    radial = CameraModel(1024, 1024, 504.6, 504.7, 511.3, 512.8, distortion_model="rational",
                         dist=(KINECT[0], KINECT[1], 0.0, 0.0) + tuple(KINECT[4:8]))
    for cam in (RATIONAL, PRISM, FISHEYE, radial):
        compiled = cam.pixel_rays(u, v)
        cx, cy = cam.undistort_normalized(u, v)
        monkeypatch.setattr(camera_module, "_COMPILED_UNDISTORT_MIN", 10 ** 12)
        plain = cam.pixel_rays(u, v)
        px_, py_ = cam.undistort_normalized(u, v)
        monkeypatch.undo()
        if cam.is_fisheye:
            np.testing.assert_allclose(compiled, plain, rtol=0, atol=1e-15)
        else:
            np.testing.assert_array_equal(cx, px_)
            np.testing.assert_array_equal(cy, py_)


def test_pixels_beyond_the_fold_have_no_ray() -> None:
    """Radial only, k1 < 0: ``rd = r (1 + k1 r^2)`` peaks at ``r* = 1/sqrt(-3 k1)`` with
    ``rd* = 2 r* / 3``; a pixel farther out than rd* has no ray (NaN), one inside does and
    round-trips (the root inside the fold, not the one beyond it)."""
    k1 = -0.3
    cam = CameraModel(400, 400, 100.0, 100.0, 0.0, 0.0, dist=(k1, 0, 0, 0, 0))
    r_star = 1 / np.sqrt(-3 * k1)
    rd_star = 2 * r_star / 3
    inside, outside = 100.0 * rd_star * 0.999, 100.0 * rd_star * 1.001
    x, _ = cam.undistort_normalized(np.array([inside, outside]), np.array([0.0, 0.0]))
    assert np.isfinite(x[0]) and x[0] < r_star and np.isnan(x[1])
    assert x[0] * (1 + k1 * x[0] ** 2) * 100.0 == pytest.approx(inside, abs=1e-9)
    assert np.isnan(cam.pixel_rays(np.array(outside), np.array(0.0))).all()
    # the compiled path says the same
    big = np.full(5000, outside)
    assert np.isnan(cam.undistort_normalized(big, np.zeros(5000))[0]).all()


@pytest.mark.parametrize("cam", [RATIONAL, PRISM, FISHEYE])
def test_point_cloud_of_a_plane_is_planar(cam: CameraModel) -> None:
    n = np.array([0.1, -0.2, 1.0])
    n /= np.linalg.norm(n)
    rays = cam.rays
    ok = np.isfinite(rays).all(-1) & (rays @ n > 0.2)
    radial = np.where(ok, 1.2 / np.where(ok, rays @ n, 1.0), np.nan)
    pts = cam.points(radial)
    assert len(pts) == ok.sum() > 0.5 * ok.size
    np.testing.assert_allclose(pts @ n, 1.2, atol=1e-9)


def test_dict_and_json_round_trip_and_old_files() -> None:
    for cam in (RATIONAL, PRISM, FISHEYE, PLUMB):
        d = cam.to_dict()
        assert d["model"] == cam.distortion_model and len(d["dist"]) == len(cam.dist)
        assert CameraModel.from_json(cam.to_json()) == cam
    old = {"width": 4, "height": 3, "fx": 2.0, "fy": 2.0, "cx": 1.5, "cy": 1.0, "dist": [0.1, 0, 0, 0, 0]}
    assert CameraModel.from_dict(old).distortion_model == "plumb_bob"
    # ROS CameraInfo names of the same models
    ros = CameraModel.from_dict(old | {"model": "equidistant", "dist": [0.1, 0, 0, 0]})
    assert ros.distortion_model == "fisheye"
    assert CameraModel.from_dict(old | {"model": "rational_polynomial", "dist": list(KINECT)}).distortion_model == "rational"
    no_dist = {k: v for k, v in old.items() if k != "dist"}
    assert CameraModel.from_dict(no_dist | {"model": "fisheye"}).dist == (0.0,) * 4


def test_bad_model_or_dist_names_the_field() -> None:
    base = {"width": 4, "height": 3, "fx": 2.0, "fy": 2.0, "cx": 1.5, "cy": 1.0}
    with pytest.raises(InputFileError, match=r"cam\.yaml: field 'model': got 'fishey' \(expected one of 'plumb_bob'"):
        CameraModel.from_dict(base | {"model": "fishey"}, source="cam.yaml")
    with pytest.raises(InputFileError, match=r"field 'dist'.*4 finite numbers \(k1, k2, k3, k4\) for model 'fisheye'"):
        CameraModel.from_dict(base | {"model": "fisheye", "dist": [0, 0, 0, 0, 0]})
    with pytest.raises(InputFileError, match=r"field 'camera.dist'.*8 or 12"):
        check_distortion(Schema("s.yaml"), base | {"model": "rational", "dist": [0] * 5}, "camera.")
    with pytest.raises(ValueError, match="dist has 5 numbers"):
        CameraModel(4, 3, 2.0, 2.0, 1.5, 1.0, dist=(0,) * 5, distortion_model="fisheye")


def test_point_clouds_leave_out_pixels_without_a_ray() -> None:
    """The Azure Kinect lens over a 120 degree field (its WFOV mode): the corners beyond the
    model's fold have no ray and no point, whatever distance the image holds there."""
    from tofhil.camera import load_camera_preset

    cam = load_camera_preset("azure_kinect_wfov")
    no_ray = ~np.isfinite(cam.ray_z)
    assert 0.02 < no_ray.mean() < 0.1 and no_ray[0, 0] and not no_ray[cam.height // 2, cam.width // 2]
    pts = cam.points(np.full(cam.shape, 2.0))
    assert len(pts) == (~no_ray).sum() and np.all(np.isfinite(pts))


def _reach_by_numpy(model: str, c: np.ndarray) -> float:
    """The reach found independently: the radial function's slope in numpy over a dense
    grid (its first non-positive value), then 200 bisections."""
    with np.errstate(all="ignore"):
        if model == "fisheye":
            def slope(t):
                t2 = t * t
                return 1 + t2 * (3 * c[0] + t2 * (5 * c[1] + t2 * (7 * c[2] + t2 * 9 * c[3])))
            grid = np.linspace(0.0, np.pi, 400001)
        else:
            def slope(r):   # d/dr of r g(r^2) by the quotient rule, written out
                r2 = r * r
                num, den = 1 + c[0] * r2 + c[1] * r2 ** 2 + c[4] * r2 ** 3, 1 + c[5] * r2 + c[6] * r2 ** 2 + c[7] * r2 ** 3
                dnum = 2 * r * (c[0] + 2 * c[1] * r2 + 3 * c[4] * r2 ** 2)
                dden = 2 * r * (c[5] + 2 * c[6] * r2 + 3 * c[7] * r2 ** 2)
                return np.where(den > 0, num / den + r * (dnum * den - num * dden) / den ** 2, -1.0)
            grid = np.concatenate([np.linspace(0.0, 10.0, 400001), np.linspace(10.0, 100.0, 40001)[1:]])
        bad = np.flatnonzero(~(slope(grid) > 0))
        if bad.size == 0:
            return np.pi if model == "fisheye" else np.inf
        lo, hi = grid[bad[0] - 1], grid[bad[0]]
        for _ in range(200):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if slope(np.array(mid)) > 0 else (lo, mid)
    return lo if model == "fisheye" else lo * lo


@pytest.mark.parametrize("model", ["plumb_bob", "rational", "fisheye"])
def test_model_reach_agrees_with_an_independent_scan(model: str) -> None:
    """The compiled scan and bisection of the reach against a numpy scan on a grid twice as
    fine, on random lenses, some folding inside the range searched and some not."""
    rng = np.random.default_rng(7)
    folds = 0
    for _ in range(40):
        if model == "fisheye":
            dist = tuple(rng.normal(0.0, [0.1, 0.05, 0.02, 0.01]))
        elif model == "plumb_bob":
            dist = tuple(rng.normal(0.0, [0.3, 0.1, 0.01, 0.01, 0.05]))
        else:
            dist = tuple(rng.normal(0.0, [0.3, 0.1, 0.01, 0.01, 0.05, 0.3, 0.1, 0.05]))
        cam = CameraModel(100, 100, 50.0, 50.0, 49.5, 49.5, dist=dist, distortion_model=model)
        got, want = cam.kernel_coeffs[12], _reach_by_numpy(model, cam.kernel_coeffs)
        folds += bool(np.isfinite(want) and want < (np.pi if model == "fisheye" else 1e4))
        if np.isinf(want):
            assert np.isinf(got)
        else:
            # (the grid points differ: both bisect one sign change to rounding)
            assert got == pytest.approx(want, rel=1e-9)
    assert 5 <= folds < 40         # (both kinds)


def test_model_reach_is_the_first_fold_and_rays_beyond_it_are_refused() -> None:
    """The reach is the first fold of the radial function (closed form for ``r (1 + k1 r^2)``:
    ``r*^2 = 1 / (3 |k1|)``); the Azure Kinect lens folds at 72.7 degrees (its calibration is
    good to 60): a 73 or 76 degree ray still projects into the WFOV image, but the pixel it lands
    on sees the ray of the lens's own branch, or none, never the far branch's."""
    from tofhil.camera import load_camera_preset

    barrel = CameraModel(400, 400, 100.0, 100.0, 0.0, 0.0, dist=(-0.3, 0, 0, 0, 0))
    assert barrel.kernel_coeffs[12] == pytest.approx(1 / 0.9, rel=1e-12)
    assert np.isinf(PLUMB.kernel_coeffs[12]) and FISHEYE.kernel_coeffs[12] == pytest.approx(np.pi)
    cam = load_camera_preset("azure_kinect_wfov")
    reach_deg = np.degrees(np.arctan(np.sqrt(cam.kernel_coeffs[12])))
    assert 70.0 < reach_deg < 75.0
    for deg in (73.0, 76.0):                 # beyond the reach, towards the image corner
        t, az = np.radians(deg), np.pi / 4
        uv = cam.project(np.array([np.sin(t) * np.cos(az), np.sin(t) * np.sin(az), np.cos(t)]))
        assert 0 <= uv[0] < cam.width and 0 <= uv[1] < cam.height
        seen = cam.pixel_rays(uv[0], uv[1])
        assert np.isnan(seen).all() or np.degrees(np.arccos(seen[2])) < reach_deg


def _inverted_at_radii(rd: np.ndarray, rng: np.random.Generator, c: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Points at distorted radii ``rd`` and random azimuths, inverted by the compiled inversion
    (the renderer's sub-pixel rays) after checking that the numpy one agrees bit for bit:
    ``(xd, yd, x, y)``."""
    from tofhil.camera_kernels import undistort_arrays
    from tofhil.lens_models import brown_undistort

    az = rng.uniform(0, 2 * np.pi, rd.size)
    xd, yd = rd * np.cos(az), rd * np.sin(az)
    x, y = undistort_arrays(xd, yd, c)
    xn, yn = brown_undistort(xd, yd, c)
    np.testing.assert_array_equal(x, xn)
    np.testing.assert_array_equal(y, yn)
    return xd, yd, x, y


def test_a_barrel_lens_has_no_ray_beyond_the_image_of_its_reach_and_every_ray_inside() -> None:
    """``r (1 + k1 r^2)`` with ``k1 < 0`` rises to ``r*^2 = 1 / (3 |k1|)`` and no further: a
    distorted radius above ``r* (1 + k1 r*^2)`` (closed form) has no inverse on the lens's
    branch, one below it has exactly one. The compiled inversion (the renderer's sub-pixel
    rays) and the numpy one agree bit for bit on both sides, and every ray found distorts back
    to its point."""
    k1 = -0.25
    cam = CameraModel(400, 400, 100.0, 100.0, 0.0, 0.0, dist=(k1, 0, 0, 0, 0))
    c = np.asarray(cam.kernel_coeffs)
    r_star = np.sqrt(1 / (3 * abs(k1)))
    rd_max = r_star * (1 + k1 * r_star ** 2)
    rng = np.random.default_rng(5)
    rd = np.concatenate([rng.uniform(0.0, 0.999 * rd_max, 500), rng.uniform(1.001 * rd_max, 3 * rd_max, 500)])
    xd, yd, x, y = _inverted_at_radii(rd, rng, c)
    inside = rd < rd_max
    assert np.isnan(x[~inside]).all() and np.isfinite(x[inside]).all()
    g = 1 + k1 * (x[inside] ** 2 + y[inside] ** 2)
    np.testing.assert_allclose(x[inside] * g, xd[inside], atol=1e-12)
    np.testing.assert_allclose(y[inside] * g, yd[inside], atol=1e-12)
    assert (x[inside] ** 2 + y[inside] ** 2 <= 1 / (3 * abs(k1))).all()


def test_a_radially_symmetric_lens_is_inverted_along_the_radius_to_the_closed_form() -> None:
    """``rd = r (1 + k1 r^2)`` with ``k1 > 0`` has one real root (Cardano); the inversion along
    each point's radius (the compiled one and the numpy one, bit for bit) finds it to rounding,
    keeps the point's direction, and maps the axis to itself."""
    from tofhil.lens_models import kernel_coeffs

    k1 = 0.21
    c = kernel_coeffs("plumb_bob", (k1, 0.0, 0.0, 0.0, 0.0))
    rng = np.random.default_rng(11)
    rd = np.concatenate([[0.0], rng.uniform(0.0, 2.0, 2000)])
    xd, yd, x, y = _inverted_at_radii(rd, rng, c)
    p, q = 1 / (3 * k1), rd / (2 * k1)                  # r^3 + 3 p r - 2 q = 0
    w = np.sqrt(q * q + p ** 3)
    r_closed = np.cbrt(q + w) + np.cbrt(q - w)
    np.testing.assert_allclose(np.hypot(x, y), r_closed, rtol=1e-13, atol=1e-15)
    assert x[0] == 0.0 and y[0] == 0.0
    np.testing.assert_allclose(np.arctan2(y[1:], x[1:]), np.arctan2(yd[1:], xd[1:]), atol=1e-13)
