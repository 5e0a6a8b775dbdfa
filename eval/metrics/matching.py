"""Point-cloud matching: robust point-to-plane ICP (Open3D) and distance metrics.

Conventions (all distances Euclidean, metres; ``a`` is the measured / source cloud, ``b``
the reference / target):

- :func:`chamfer` -- the *symmetric mean of unsquared nearest-neighbour distances*:
  ``0.5 * (mean_a d(a, B) + mean_b d(b, A))``.
- :func:`hausdorff` -- ``max(max_a d(a, B), max_b d(b, A))`` and its robust version, the
  larger of the two directed 95th percentiles.
- :func:`fscore` -- harmonic mean of precision (fraction of ``a`` within ``threshold`` of
  ``b``) and recall (fraction of ``b`` within ``threshold`` of ``a``), as in Tanks and
  Temples (Knapitsch et al. 2017).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from tofhil.errors import TofhilError

KERNELS = ("tukey", "huber", "cauchy", "gm", "l1", "l2")


def _points(x: Any, name: str) -> np.ndarray:
    p = np.asarray(x, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise TofhilError(f"has shape {p.shape}", field=name, expected="an N x 3 array of points")
    p = p[np.all(np.isfinite(p), axis=1)]
    if p.shape[0] == 0:
        raise TofhilError("has no finite points", field=name, expected="a non-empty cloud")
    return p


def nn_distances(a: Any, b: Any, workers: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Nearest-neighbour distances ``d(a_i, B)`` and ``d(b_j, A)`` (scipy cKDTree)."""
    pa, pb = _points(a, "a"), _points(b, "b")
    dab = cKDTree(pb).query(pa, workers=workers)[0]
    dba = cKDTree(pa).query(pb, workers=workers)[0]
    return dab, dba


def chamfer(a: Any, b: Any) -> float:
    """Symmetric mean of unsquared NN distances, ``0.5 (mean d(a,B) + mean d(b,A))`` [m]."""
    dab, dba = nn_distances(a, b)
    return float(0.5 * (dab.mean() + dba.mean()))


def hausdorff(a: Any, b: Any, percentile: float = 95.0) -> tuple[float, float]:
    """Symmetric Hausdorff distance and the larger directed ``percentile`` (default p95)."""
    dab, dba = nn_distances(a, b)
    return (float(max(dab.max(), dba.max())),
            float(max(np.percentile(dab, percentile), np.percentile(dba, percentile))))


def precision_recall(a: Any, b: Any, threshold: float) -> tuple[float, float]:
    """Fraction of ``a`` within ``threshold`` of ``b`` and of ``b`` within it of ``a``."""
    dab, dba = nn_distances(a, b)
    return float(np.mean(dab <= threshold)), float(np.mean(dba <= threshold))


def _f(precision: float, recall: float) -> float:
    return 0.0 if precision + recall == 0 else 2.0 * precision * recall / (precision + recall)


def fscore(a: Any, b: Any, threshold: float) -> float:
    """F-score at ``threshold`` metres: harmonic mean of precision and recall."""
    if not threshold > 0:
        raise TofhilError(f"is {threshold}", field="threshold", expected="a positive distance in metres")
    return _f(*precision_recall(a, b, threshold))


@dataclass
class IcpResult:
    """ICP outcome: ``transformation`` maps source points onto the target (4x4)."""

    transformation: np.ndarray
    fitness: float        # fraction of source points with a correspondence within max_distance
    inlier_rmse: float    # RMS distance of those correspondences [m]
    kernel: str
    kernel_k: float

    def to_dict(self) -> dict[str, Any]:
        return {"transformation": self.transformation.tolist(), "fitness": self.fitness,
                "inlier_rmse": self.inlier_rmse, "kernel": self.kernel, "kernel_k": self.kernel_k}


def _loss(o3d: Any, kernel: str, k: float) -> Any:
    reg = o3d.pipelines.registration
    table = {"tukey": lambda: reg.TukeyLoss(k=k), "huber": lambda: reg.HuberLoss(k=k),
             "cauchy": lambda: reg.CauchyLoss(k=k), "gm": lambda: reg.GMLoss(k=k),
             "l1": lambda: reg.L1Loss(), "l2": lambda: reg.L2Loss()}
    if kernel not in table:
        raise TofhilError(f"is {kernel!r}", field="kernel", expected=" | ".join(KERNELS))
    return table[kernel]()


def icp(source: Any, target: Any, max_distance: float, kernel: str = "tukey",
        init: np.ndarray | None = None, kernel_k: float | None = None, max_iterations: int = 50,
        normal_radius: float | None = None) -> IcpResult:
    """Point-to-plane ICP of ``source`` onto ``target`` with a robust kernel (Open3D).

    ``max_distance`` is the correspondence cut-off [m]; the kernel scale ``kernel_k``
    defaults to ``max_distance / 2`` (safe for convergence from a start up to
    ``max_distance`` off); to reject near-surface outliers such as multipath ghosts, set it
    to 2-3 times the noise standard deviation. Target normals are estimated from neighbours within
    ``normal_radius`` (default ``2 * max_distance``, at most 30 points). Fitness and inlier
    RMSE are Open3D's, evaluated at the final transformation.
    """
    from tofhil.open3d_loader import open3d

    if not max_distance > 0:
        raise TofhilError(f"is {max_distance}", field="max_distance", expected="a positive distance in metres")
    o3d = open3d()
    reg = o3d.pipelines.registration
    k = float(kernel_k if kernel_k is not None else max_distance / 2.0)
    loss = _loss(o3d, kernel, k)
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(_points(source, "source")))
    tgt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(_points(target, "target")))
    radius = float(normal_radius if normal_radius is not None else 2.0 * max_distance)
    tgt.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=30))
    t0 = np.eye(4) if init is None else np.asarray(init, dtype=np.float64)
    if t0.shape != (4, 4):
        raise TofhilError(f"has shape {t0.shape}", field="init", expected="a 4x4 matrix")
    res = reg.registration_icp(src, tgt, float(max_distance), t0,
                               reg.TransformationEstimationPointToPlane(loss),
                               reg.ICPConvergenceCriteria(max_iteration=int(max_iterations)))
    # Open3D sums its normal equations over threads in no fixed order, so the last digits of
    # its transformation (and of the fitness and RMSE it evaluates) change from run to run.
    # The transformation is rounded to ICP_ROUND (far below any distance that matters), and
    # fitness and inlier RMSE are evaluated at it here with a deterministic nearest-neighbour
    # search and reduction, so that the same clouds give the same figures, bit for bit.
    t = np.round(np.asarray(res.transformation, dtype=np.float64), ICP_DECIMALS)
    fitness, rmse = _icp_fit_quality(_points(source, "source"), _points(target, "target"), t, float(max_distance))
    return IcpResult(t, fitness, rmse, kernel, k)


#: Decimals the ICP transformation is rounded to (1e-9 rad, 1e-9 m): see :func:`icp`.
ICP_DECIMALS = 9


def _icp_fit_quality(source: np.ndarray, target: np.ndarray, t: np.ndarray, max_distance: float) -> tuple[float, float]:
    """Open3D's fitness (share of source points with a target point within ``max_distance``)
    and inlier RMSE (of those distances), computed in a fixed order."""
    moved = apply_transform(source, t)
    d = cKDTree(target).query(moved, workers=1)[0]
    inl = d <= max_distance
    n = int(inl.sum())
    if n == 0 or len(moved) == 0:
        return 0.0, 0.0
    return n / len(moved), float(np.sqrt(np.sum(np.sort(d[inl] ** 2)) / n))


def apply_transform(points: Any, transformation: np.ndarray) -> np.ndarray:
    """Apply a 4x4 rigid transform to [N, 3] points."""
    p = np.asarray(points, dtype=np.float64)
    t = np.asarray(transformation, dtype=np.float64)
    return p @ t[:3, :3].T + t[:3, 3]


def cloud_metrics(a: Any, b: Any, threshold: float = 0.01, align: bool = False,
                  max_distance: float | None = None, kernel: str = "tukey",
                  percentile: float = 95.0) -> dict[str, Any]:
    """All distance metrics of ``a`` (measured) against ``b`` (reference) in one dict.

    Keys: ``chamfer``, ``hausdorff``, ``hausdorff_p95``, ``precision``, ``recall``,
    ``fscore``, ``threshold``, ``n_a``, ``n_b``. With ``align=True``, ``a`` is first
    registered onto ``b`` by :func:`icp` (``max_distance`` default ``5 * threshold``), the
    metrics are computed after alignment, and ``icp`` holds :meth:`IcpResult.to_dict`.
    """
    pa, pb = _points(a, "a"), _points(b, "b")
    out: dict[str, Any] = {}
    if align:
        r = icp(pa, pb, max_distance if max_distance is not None else 5.0 * threshold, kernel=kernel)
        pa = apply_transform(pa, r.transformation)
        out["icp"] = r.to_dict()
    dab, dba = nn_distances(pa, pb)
    p, rc = float(np.mean(dab <= threshold)), float(np.mean(dba <= threshold))
    out.update({"chamfer": float(0.5 * (dab.mean() + dba.mean())),
                "hausdorff": float(max(dab.max(), dba.max())),
                "hausdorff_p95": float(max(np.percentile(dab, percentile), np.percentile(dba, percentile))),
                "precision": p, "recall": rc, "fscore": _f(p, rc), "threshold": float(threshold),
                "n_a": int(pa.shape[0]), "n_b": int(pb.shape[0])})
    return out
