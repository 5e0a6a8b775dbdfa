"""Multi-view models: register ToF views, fuse them (TSDF) and score the model against the truth.

Views are sessions (the temporal mean of their depth frames). The model's frame is the first
view's camera frame. Registration, coarse to fine (Open3D):

1. coarse: every consecutive pair (i -> i-1) by RANSAC on FPFH features of voxel-downsampled
   clouds; besides its result, no motion and turns of the camera about its x and y axes
   (``COARSE_TURNS_DEG``) are tried as starts (features of sparse, noisy ToF clouds of a room of
   planes are weak), each refined by ICP at the coarsest scale; the best two go to step 2 and
   the one with more inliers at the finest scale wins;
2. fine: point-to-plane ICP (robust Tukey kernel) at three scales, the last on the full clouds;
3. pairs up to ``LOOP_SPAN`` views apart that overlap (ICP at the finest scale from the chained
   poses, fitness >= ``LOOP_MIN_FITNESS``, and not moved far from them: point-to-plane ICP slides
   along a direction the overlap leaves free) add loop-closure edges, and a pose graph (Levenberg-Marquardt, line process) spreads the
   pairwise errors over the views.

Fusion: each view's z-depth image (re-projected into a distortion-free pinhole camera with the
same K, nearest point per pixel) goes into Open3D's scalable TSDF volume at its registered pose;
the model is the volume's surface points (with the mean amplitude as grey).

Truth (a simulated view's session embeds its resolved scene: camera pose and meshes): the
scene's surfaces sampled uniformly by area and kept where at least one view's camera sees them
(inside its image, first hit along the ray), so that recall counts what the views could see.
The model is put in the world with the first view's true pose (its anchor) and scored there,
without any further alignment: NDT (:mod:`tofhil.eval.metrics.ndt`) of the model points on the truth's
grid, Chamfer and F-score (:mod:`tofhil.eval.metrics.matching`). Per-view pose errors compare
``true_pose[0] @ estimated[i]`` with ``true_pose[i]`` (view 0 is exact by construction).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from tofhil.camera import CameraModel
from tofhil.errors import InputFileError, TofhilError
from tofhil.progress import Progress

#: A non-consecutive pair with at least this ICP fitness becomes a loop-closure edge.
LOOP_MIN_FITNESS = 0.3
#: A consecutive pair below this ICP fitness (the fraction of a view's points on the other's
#: surface after registration) is refused: its views do not overlap, and the best of the coarse
#: starts would be fused as if they did. Measured: the room's views 12 deg apart 0.58-0.74; an
#: O3R and a Kinect capture of unrelated scenes 0.135.
ODOMETRY_MIN_FITNESS = 0.3
#: Loop closures join views up to this many steps apart; one that moves more than these away
#: from the chained poses is not used.
LOOP_SPAN = 3
LOOP_MAX_SHIFT_M = 0.005
LOOP_MAX_TURN_DEG = 0.25
#: Coarse starts besides RANSAC and no motion: turns (deg) about the camera's y and x axes.
COARSE_TURNS_DEG = (-24.0, -12.0, 12.0, 24.0)
#: Truth sampling: one point per this area (m^2), i.e. ~1.5 cm spacing.
TRUTH_AREA_PER_POINT_M2 = 1.5e-2 ** 2
#: Default NDT cell (m) and F-score distance (m) of the model score.
NDT_CELL_M = 0.1
FSCORE_THRESHOLD_M = 0.02
#: The stated NDT threshold: a model passes when the mean likelihood of its points on the truth's
#: NDT grid (cell ``NDT_CELL_M``, the likelihood of each point's own cell) reaches this fraction of
#: the same figure for the model fused from the same views at their TRUE poses (the ceiling that
#: registration cannot beat: it carries the same noise and TSDF smoothing). Measured on the bundled
#: room (docs/calibration.md): registered 0.97 of it, shifted 1 cm 0.87, 2 cm 0.74, turned 1 deg 0.47.
NDT_PASS = 0.9


@dataclass
class View:
    """One view: camera-frame points, its z-depth image and (for simulated views) the truth."""

    name: str
    camera: CameraModel
    points: np.ndarray               # [N, 3] camera frame (valid pixels of the mean depth)
    grey: np.ndarray                 # [N] amplitude scaled to [0, 1] (for the model's colour)
    true_pose: np.ndarray | None     # 4x4 camera-to-world, when the session embeds its scene
    scene: Any = None                # the session's scene (truth geometry), when embedded


def load_view(path: str | Path) -> View:
    """The temporal mean of a session's depth frames as a :class:`View`."""
    from tofhil.eval.metrics.core import mean_depth_frame
    from tofhil.session import open_session

    path = Path(path)
    with open_session(path) as s:
        frame, _ = mean_depth_frame(s.depth_frames())   # a session without depth: InputFileError
        text = s.scene_text
    cam = frame.camera
    mask = cam.valid_mask(frame.distance_m, frame.valid)
    pts = cam.points(frame.distance_m, frame.kind, mask)
    if len(pts) < 100:
        raise InputFileError(f"has only {len(pts)} valid depth pixels", file=path, field="depth/valid",
                             expected="at least 100 valid pixels per view")
    amp = np.zeros(len(pts)) if frame.amplitude is None else np.nan_to_num(np.asarray(frame.amplitude)[mask])
    top = float(np.percentile(amp, 99.5)) if amp.size else 0.0
    grey = np.clip(amp / top, 0.0, 1.0) if top > 0 else np.full(len(pts), 0.5)
    scene = pose = None
    if text.strip():
        from tofhil.sim.scene import scene_from_yaml

        try:
            scene = scene_from_yaml(text, source=f"{path}:scene")
            pose = np.asarray(scene.camera_pose, dtype=np.float64)
        except TofhilError:
            scene = pose = None   # a capture's scene reference that is not a full scene: no truth
    return View(name=path.stem, camera=cam, points=pts, grey=grey, true_pose=pose, scene=scene)


# ---------------------------------------------------------------------------- registration


@dataclass
class PairResult:
    """One registered pair: ``transformation`` maps view ``source``'s points into ``target``'s frame."""

    source: int
    target: int
    transformation: np.ndarray
    fitness: float
    inlier_rmse_m: float
    coarse: str            # the start that won (loop closures start from the chained poses: "chain")
    loop: bool
    used: bool = True      # a loop closure is an edge only if it stays near the chain (LOOP_MAX_*)

    def to_dict(self) -> dict[str, Any]:
        return {"source": self.source, "target": self.target, "transformation": self.transformation.tolist(),
                "fitness": self.fitness, "inlier_rmse_m": self.inlier_rmse_m, "coarse": self.coarse,
                "loop": self.loop, "used": self.used}


@dataclass
class Registration:
    """Poses of every view in the model frame (view 0's camera frame) and the pairs behind them."""

    poses: list[np.ndarray]
    pairs: list[PairResult]
    voxel_m: float


def _cloud(o3d: Any, pts: np.ndarray, radius: float) -> Any:
    c = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(pts, dtype=np.float64)))
    c.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=30))
    # normals toward the camera (the origin of the view's frame): consistent across views
    c.orient_normals_towards_camera_location(np.zeros(3))
    return c


def register_views(views: Sequence[View], voxel_m: float = 0.04, *, seed: int = 0,
                   progress: Progress | None = None) -> Registration:
    """Register ``views`` into view 0's frame (see the module doc). ``voxel_m`` is the coarse
    voxel size: features at 2.5x, ICP scales at 2x, 1x and the full clouds."""
    from tofhil.open3d_loader import open3d

    if len(views) < 2:
        raise TofhilError(f"got {len(views)} view(s)", field="SESSIONS", expected="at least two views to register")
    if not voxel_m > 0:
        raise TofhilError(f"is {voxel_m}", field="voxel", expected="a positive size in metres")
    o3d = open3d()
    reg = o3d.pipelines.registration
    o3d.utility.random.seed(int(seed))   # RANSAC is random: the same views give the same model
    fine = 0.5 * voxel_m                 # final ICP correspondence distance
    scales = []                          # per view: clouds at 2*voxel, voxel, full resolution
    feats = []
    for v in views:
        full = _cloud(o3d, v.points, 2.0 * voxel_m)
        levels = [full.voxel_down_sample(2.0 * voxel_m), full.voxel_down_sample(voxel_m), full]
        for c in levels[:2]:
            c.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=4.0 * voxel_m, max_nn=30))
            c.orient_normals_towards_camera_location(np.zeros(3))
        scales.append(levels)
        feats.append(reg.compute_fpfh_feature(levels[1], o3d.geometry.KDTreeSearchParamHybrid(
            radius=5.0 * voxel_m, max_nn=100)))
    dist_scales = (2.0 * fine * 2, fine * 2, fine)   # 2 voxel, 1 voxel, half a voxel

    def icp(i: int, j: int, init: np.ndarray, levels: slice = slice(None)) -> tuple[np.ndarray, float, float]:
        return _icp_scales(o3d, scales[i][levels], scales[j][levels], dist_scales[levels], init)

    pairs: list[PairResult] = []
    odometry = [np.eye(4)]
    steps = range(1, len(views))
    it = progress(steps, len(views) - 1, "register") if progress is not None else steps
    for i in it:
        j = i - 1
        ransac = reg.registration_ransac_based_on_feature_matching(
            scales[i][1], scales[j][1], feats[i], feats[j], True, 1.5 * voxel_m,
            reg.TransformationEstimationPointToPoint(False), 3,
            [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(1.5 * voxel_m)],
            reg.RANSACConvergenceCriteria(20000, 0.999))
        # coarse starts: the features' RANSAC, no motion, and turns about the camera's x and y
        # axes (a pan or tilt between views moves far points beyond ICP's reach); each gets the
        # coarsest ICP scale, the best two all scales; the most inliers at the finest scale wins
        starts = [("ransac", np.asarray(ransac.transformation)), ("identity", np.eye(4))]
        starts += [(f"turn {a:+g} deg about {ax}", _turn(ax, a)) for a in COARSE_TURNS_DEG for ax in "yx"]
        coarse = sorted(((icp(i, j, t0, slice(0, 1))[1], k) for k, (_, t0) in enumerate(starts)), reverse=True)
        best = None
        for _, k in coarse[:2]:
            t, fit, rmse = icp(i, j, starts[k][1])
            if best is None or (fit, -rmse) > (best[1], -best[2]):
                best = (t, fit, rmse, starts[k][0])
        t, fit, rmse, label = best
        if fit < ODOMETRY_MIN_FITNESS:
            raise TofhilError(f"views {views[j].name} and {views[i].name} do not overlap enough to register "
                              f"(ICP fitness {fit:.3f} at best)", field="views",
                              expected=f"consecutive views of one scene that overlap (fitness >= "
                                       f"{ODOMETRY_MIN_FITNESS:g}: that share of a view's points on the other's surface)")
        pairs.append(PairResult(i, j, t, fit, rmse, label, loop=False))
        odometry.append(odometry[j] @ t)
    # loop closures: views two and three steps apart that overlap, from the chained poses (already
    # close: finest scale only; the coarse scales let a partial overlap slide along the walls)
    for i in range(2, len(views)):
        for j in range(max(0, i - LOOP_SPAN), i - 1):
            chained = np.linalg.inv(odometry[j]) @ odometry[i]
            t, fit, rmse = icp(i, j, chained, slice(2, 3))
            if fit < LOOP_MIN_FITNESS:
                continue
            # a loop that moved far from the chain slid along a degenerate direction (two walls
            # and a floor leave one translation free) rather than corrected it: not an edge
            dt, dr = pose_error(t, chained)
            used = dt <= LOOP_MAX_SHIFT_M and dr <= LOOP_MAX_TURN_DEG
            pairs.append(PairResult(i, j, t, fit, rmse, "chain", loop=True, used=used))
    graph = reg.PoseGraph()
    for pose in odometry:   # a node's pose maps its view into view 0's frame
        graph.nodes.append(reg.PoseGraphNode(pose))
    for p in pairs:
        if not p.used:
            continue
        info = reg.get_information_matrix_from_point_clouds(scales[p.source][2], scales[p.target][2], fine,
                                                            p.transformation)
        graph.edges.append(reg.PoseGraphEdge(p.source, p.target, p.transformation, info, uncertain=p.loop))
    if any(p.loop and p.used for p in pairs):
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            reg.global_optimization(graph, reg.GlobalOptimizationLevenbergMarquardt(),
                                    reg.GlobalOptimizationConvergenceCriteria(),
                                    reg.GlobalOptimizationOption(max_correspondence_distance=fine,
                                                                 edge_prune_threshold=0.25, reference_node=0))
    poses = [np.asarray(n.pose, dtype=np.float64) for n in graph.nodes]
    poses = [np.linalg.inv(poses[0]) @ p for p in poses]
    return Registration(poses=poses, pairs=pairs, voxel_m=float(voxel_m))


def _turn(axis: str, angle_deg: float) -> np.ndarray:
    """A 4x4 rotation about the camera's ``axis`` ("x" or "y") through its centre."""
    a = math.radians(angle_deg)
    c, s = math.cos(a), math.sin(a)
    t = np.eye(4)
    if axis == "y":
        t[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    else:
        t[:3, :3] = [[1, 0, 0], [0, c, -s], [0, s, c]]
    return t


def _icp_scales(o3d: Any, src: Sequence[Any], tgt: Sequence[Any], dists: Sequence[float], init: np.ndarray
                ) -> tuple[np.ndarray, float, float]:
    reg = o3d.pipelines.registration
    t = np.asarray(init, dtype=np.float64)
    for s, tc, d in zip(src, tgt, dists):
        est = reg.TransformationEstimationPointToPlane(reg.TukeyLoss(k=d))
        t = np.asarray(reg.registration_icp(s, tc, 2.0 * d, t, est,
                                            reg.ICPConvergenceCriteria(max_iteration=60)).transformation)
    ev = reg.evaluate_registration(src[-1], tgt[-1], dists[-1], t)
    return t, float(ev.fitness), float(ev.inlier_rmse)


# ---------------------------------------------------------------------------- fusion


def pinhole_depth(camera: CameraModel, points: np.ndarray, values: np.ndarray | None = None
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame points -> a z-depth image of a distortion-free pinhole camera with the same
    K (nearest point per pixel, 0 where none) and ``values`` at those points (0 elsewhere)."""
    h, w = camera.shape
    z = points[:, 2]
    ok = z > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.round(camera.fx * points[:, 0] / z + camera.cx)
        v = np.round(camera.fy * points[:, 1] / z + camera.cy)
    ok &= (u >= 0) & (u < w) & (v >= 0) & (v < h)
    iu, iv, zi = u[ok].astype(np.int64), v[ok].astype(np.int64), z[ok]
    depth = np.full((h, w), np.inf)
    np.minimum.at(depth, (iv, iu), zi)
    val = np.zeros((h, w))
    if values is not None:
        near = zi <= depth[iv, iu]
        val[iv[near], iu[near]] = np.asarray(values)[ok][near]
    return np.where(np.isfinite(depth), depth, 0.0), val


#: Most voxels per side of the fusion volume (Open3D's uniform TSDF volume is dense: 256^3
#: voxels of ~20 bytes is 340 MB); a larger extent coarsens the voxel, with a note.
MAX_TSDF_RESOLUTION = 256


def fuse_views(views: Sequence[View], poses: Sequence[np.ndarray], voxel_m: float = 0.02,
               trunc_m: float | None = None, notes: list[str] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """TSDF fusion of the views at ``poses`` (view -> model frame) in a uniform Open3D volume
    around the registered clouds: the model's surface points ``[M, 3]`` and their grey values
    ``[M]`` (weighted mean amplitude). (Open3D 0.20's scalable volume returns no surface here.)"""
    from tofhil.open3d_loader import open3d

    o3d = open3d()
    integ = o3d.pipelines.integration
    world = [v.points @ p[:3, :3].T + p[:3, 3] for v, p in zip(views, poses)]
    lo = np.min([w.min(axis=0) for w in world], axis=0)
    hi = np.max([w.max(axis=0) for w in world], axis=0)
    trunc = float(trunc_m or 4.0 * voxel_m)
    length = float(np.max(hi - lo)) + 4.0 * trunc
    res = int(math.ceil(length / voxel_m))
    if res > MAX_TSDF_RESOLUTION:
        voxel_m = length / MAX_TSDF_RESOLUTION
        res = MAX_TSDF_RESOLUTION
        trunc = max(trunc, 4.0 * voxel_m)
        if notes is not None:
            notes.append(f"model extent {length:.2f} m: TSDF voxel coarsened to {voxel_m * 1e3:.1f} mm")
    origin = 0.5 * (lo + hi) - 0.5 * res * voxel_m
    vol = integ.UniformTSDFVolume(length=res * voxel_m, resolution=res, sdf_trunc=trunc,
                                  color_type=integ.TSDFVolumeColorType.RGB8, origin=origin.reshape(3, 1))
    max_depth = float(np.max([np.max(v.points[:, 2]) for v in views])) + 1.0
    for v, pose in zip(views, poses):
        cam = v.camera
        depth, grey = pinhole_depth(cam, v.points, v.grey)
        rgb = np.repeat(np.round(grey * 255).astype(np.uint8)[..., None], 3, axis=2)
        img = o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(np.ascontiguousarray(rgb)), o3d.geometry.Image(depth.astype(np.float32)),
            depth_scale=1.0, depth_trunc=max_depth, convert_rgb_to_intensity=False)
        intr = o3d.camera.PinholeCameraIntrinsic(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy)
        vol.integrate(img, intr, np.linalg.inv(np.asarray(pose, dtype=np.float64)))
    cloud = vol.extract_point_cloud()
    pts = np.asarray(cloud.points, dtype=np.float64)
    if len(pts) == 0:
        raise TofhilError("the fused model is empty", field="views",
                          expected="views whose depth overlaps in a common frame")
    cols = np.asarray(cloud.colors, dtype=np.float64)
    grey = cols.mean(axis=1) if cols.shape == pts.shape else np.full(len(pts), 0.5)
    return pts, grey


# ---------------------------------------------------------------------------- truth and score


def sample_scene_surface(scene: Any, area_per_point_m2: float = TRUTH_AREA_PER_POINT_M2, seed: int = 0
                         ) -> np.ndarray:
    """Points uniformly distributed by area over every object's triangles (world frame)."""
    from tofhil.sim.geometry import object_mesh

    rng = np.random.default_rng(seed)
    out = []
    for obj in scene.objects:
        v_local, faces, _ = object_mesh(obj)
        v = v_local @ obj.pose[:3, :3].T + obj.pose[:3, 3]
        tri = v[np.asarray(faces)]
        area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        n = int(math.ceil(area.sum() / area_per_point_m2))
        if n == 0:
            continue
        k = rng.choice(len(tri), size=n, p=area / area.sum())
        r1, r2 = rng.random(n), rng.random(n)
        s = np.sqrt(r1)
        a, b, c = tri[k, 0], tri[k, 1], tri[k, 2]
        out.append(a * (1 - s)[:, None] + b * (s * (1 - r2))[:, None] + c * (s * r2)[:, None])
    return np.concatenate(out) if out else np.zeros((0, 3))


def visible_from(scene: Any, points: np.ndarray, cameras: Sequence[CameraModel], poses: Sequence[np.ndarray],
                 tolerance_m: float = 2e-3) -> np.ndarray:
    """Which world ``points`` at least one camera sees: inside its image, in front, and the first
    surface hit along the ray from the camera's centre (ray cast on the scene's geometry)."""
    from tofhil.sim.geometry import Geometry

    geo = Geometry.build(scene)
    seen = np.zeros(len(points), dtype=bool)
    for cam, pose in zip(cameras, poses):
        pc = (points - pose[:3, 3]) @ pose[:3, :3]       # world -> camera
        front = (pc[:, 2] > 1e-6) | cam.is_fisheye     # (a fisheye images points beside and behind it too)
        uv = np.full((len(points), 2), -1.0)
        uv[front] = cam.project(pc[front])
        inside = front & (uv[:, 0] > -0.5) & (uv[:, 0] < cam.width - 0.5) & (uv[:, 1] > -0.5) \
            & (uv[:, 1] < cam.height - 0.5) & ~seen
        idx = np.flatnonzero(inside)
        if idx.size == 0:
            continue
        d = points[idx] - pose[:3, 3]
        dist = np.linalg.norm(d, axis=1)
        hits = geo.intersect(np.asarray(pose[:3, 3], dtype=np.float64), d / dist[:, None])
        t = hits.full(hits.t, np.inf)
        seen[idx[t >= dist - tolerance_m]] = True
    return seen


def pose_error(estimated: np.ndarray, true: np.ndarray) -> tuple[float, float]:
    """Translation error (m) and rotation error (deg) between two camera-to-world poses."""
    e = np.linalg.inv(true) @ estimated
    c = np.clip((np.trace(e[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.linalg.norm(estimated[:3, 3] - true[:3, 3])), float(np.degrees(np.arccos(c)))


@dataclass
class ModelScore:
    """The model against the truth (world frame): NDT, Chamfer, F-score and the per-point likelihood."""

    ndt: dict[str, Any]
    chamfer_m: float
    fscore: float
    precision: float
    recall: float
    fscore_threshold_m: float
    truth_points: int
    truth_points_visible: int
    likelihood: np.ndarray = field(repr=False)    # [M] trilinear NDT likelihood of each model point

    def to_dict(self) -> dict[str, Any]:
        return {"ndt": self.ndt, "chamfer_m": self.chamfer_m, "fscore": self.fscore, "precision": self.precision,
                "recall": self.recall, "fscore_threshold_m": self.fscore_threshold_m,
                "truth_points": self.truth_points, "truth_points_visible": self.truth_points_visible}


def score_model(model_world: np.ndarray, truth: np.ndarray, *, cell_m: float = NDT_CELL_M,
                threshold_m: float = FSCORE_THRESHOLD_M, truth_total: int | None = None) -> ModelScore:
    """Score model points (world frame) against truth points: NDT on the truth's grid, Chamfer, F-score."""
    from tofhil.eval.metrics.matching import cloud_metrics
    from tofhil.eval.metrics.ndt import ndt_score

    s = ndt_score(truth, model_world, cell_size=cell_m)
    c = cloud_metrics(model_world, truth, threshold=threshold_m)
    return ModelScore(ndt=s.to_dict(), chamfer_m=c["chamfer"], fscore=c["fscore"], precision=c["precision"],
                      recall=c["recall"], fscore_threshold_m=threshold_m,
                      truth_points=int(truth_total if truth_total is not None else len(truth)),
                      truth_points_visible=len(truth), likelihood=s.likelihood_trilinear)


def ndt_ratio(score: ModelScore, ceiling: ModelScore) -> float:
    """The model's NDT mean likelihood over that of the true-pose model (see ``NDT_PASS``)."""
    top = float(ceiling.ndt["mean_likelihood"])
    return float(score.ndt["mean_likelihood"]) / top if top > 0 else 0.0


def ndt_verdict(score: ModelScore, ceiling: ModelScore, threshold: float = NDT_PASS) -> str:
    """One line: the model's NDT score against the stated threshold."""
    r = ndt_ratio(score, ceiling)
    word = "passes" if r >= threshold else "FAILS"
    return (f"{word} the NDT threshold: mean likelihood {score.ndt['mean_likelihood']:.4f} is {r:.3f} of the "
            f"true-pose model's {ceiling.ndt['mean_likelihood']:.4f} ({'>=' if r >= threshold else '<'} "
            f"{threshold:g}; cell {score.ndt['cell_size']:g} m)")


@dataclass
class ViewReport:
    name: str
    points: int
    pose: np.ndarray                       # estimated, view -> model frame
    translation_error_m: float | None = None
    rotation_error_deg: float | None = None

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "points": self.points, "pose": self.pose.tolist(),
                "translation_error_m": self.translation_error_m, "rotation_error_deg": self.rotation_error_deg}


@dataclass
class MultiViewModel:
    """The fused model (model frame = view 0's camera frame), its registration and its score."""

    points: np.ndarray
    grey: np.ndarray
    registration: Registration
    views: list[ViewReport]
    score: ModelScore | None = None
    ceiling: ModelScore | None = None      # the model fused at the true poses, scored the same way
    anchor_pose: np.ndarray | None = None  # model frame -> world (view 0's true pose)
    notes: list[str] = field(default_factory=list)

    def world_points(self) -> np.ndarray | None:
        if self.anchor_pose is None:
            return None
        a = self.anchor_pose
        return self.points @ a[:3, :3].T + a[:3, 3]

    def to_dict(self) -> dict[str, Any]:
        return {"model_points": len(self.points), "voxel_m": self.registration.voxel_m,
                "views": [v.to_dict() for v in self.views], "pairs": [p.to_dict() for p in self.registration.pairs],
                "score": None if self.score is None else self.score.to_dict(),
                "true_pose_model_score": None if self.ceiling is None else self.ceiling.to_dict(),
                "ndt_ratio": None if self.score is None else ndt_ratio(self.score, self.ceiling),
                "ndt_pass_ratio": NDT_PASS,
                "ndt_verdict": None if self.score is None else ndt_verdict(self.score, self.ceiling),
                "anchor_pose": None if self.anchor_pose is None else self.anchor_pose.tolist(), "notes": self.notes}


def build_model(views: Sequence[View], *, voxel_m: float = 0.04, tsdf_voxel_m: float = 0.02,
                cell_m: float = NDT_CELL_M, threshold_m: float = FSCORE_THRESHOLD_M,
                progress: Progress | None = None) -> MultiViewModel:
    """Register, fuse and (when the views carry their truth) score: see the module doc."""
    reg = register_views(views, voxel_m, progress=progress)
    notes: list[str] = []
    pts, grey = fuse_views(views, reg.poses, voxel_m=tsdf_voxel_m, notes=notes)
    reports = [ViewReport(v.name, len(v.points), p) for v, p in zip(views, reg.poses)]
    model = MultiViewModel(points=pts, grey=grey, registration=reg, views=reports, notes=notes)
    truths = [v.true_pose for v in views]
    if all(t is not None for t in truths) and views[0].scene is not None:
        anchor = truths[0]
        model.anchor_pose = anchor
        for r, t in zip(reports, truths):
            r.translation_error_m, r.rotation_error_deg = pose_error(anchor @ r.pose, t)
        scene = views[0].scene
        truth_all = sample_scene_surface(scene)
        seen = visible_from(scene, truth_all, [v.camera for v in views], truths)
        model.score = score_model(model.world_points(), truth_all[seen], cell_m=cell_m, threshold_m=threshold_m,
                                  truth_total=len(truth_all))
        inv = np.linalg.inv(anchor)
        top, _ = fuse_views(views, [inv @ t for t in truths], voxel_m=tsdf_voxel_m)
        model.ceiling = score_model(top @ anchor[:3, :3].T + anchor[:3, 3], truth_all[seen], cell_m=cell_m,
                                    threshold_m=threshold_m, truth_total=len(truth_all))
    else:
        model.notes.append("no true poses in the sessions (not simulated views): no pose errors or truth score")
    return model
