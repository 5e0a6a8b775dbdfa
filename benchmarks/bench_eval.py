"""Benchmark: NDT scoring and ICP on 300k-point clouds, relative to a cKDTree NN query.

Prints, for a synthetic room (4 walls, floor, ceiling; 5 mm noise) of 300k reference
points and 300k measured points:
- NDT grid build and full ``ndt_score`` (PCL score, NVTL, cell + trilinear likelihood) at
  two cell sizes, as ratios to ONE scipy ``cKDTree.query`` of the same 300k points
  against the 300k reference (tree built beforehand), timed in the same run;
- robust point-to-plane ICP (Open3D, Tukey) time and its ratio to the same query.

Run: /work/venv/bin/python benchmarks/bench_eval.py [--points N] [--repeat K]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from scipy.spatial import cKDTree

from tofhil.eval.matching import apply_transform, icp
from tofhil.eval.ndt import NDTGrid, ndt_score


def room(rng: np.random.Generator, n: int) -> np.ndarray:
    """Points on the six faces of a 4 x 3 x 3 m box, 5 mm Gaussian noise."""
    face = rng.integers(0, 6, n)
    u, v = rng.uniform(0, 1, n), rng.uniform(0, 1, n)
    size = np.array([4.0, 3.0, 3.0])
    p = np.empty((n, 3))
    axis, side = face // 2, face % 2
    for a in range(3):
        m = axis == a
        b, c = [x for x in range(3) if x != a]
        p[m, a] = side[m] * size[a]
        p[m, b] = u[m] * size[b]
        p[m, c] = v[m] * size[c]
    return p + rng.normal(scale=0.005, size=p.shape)


def best_of(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--points", type=int, default=300_000)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    ref = room(rng, args.points)
    pts = room(rng, args.points)

    tree = cKDTree(ref)
    t_build_kd = best_of(lambda: cKDTree(ref), args.repeat)
    print(f"{args.points} points vs {args.points}-point reference (best of {args.repeat}; the baseline "
          f"query is re-timed next to each measurement so both see the same machine load)")
    print(f"cKDTree build {t_build_kd:.3f} s")
    for cell in (0.1, 0.25):
        grid = NDTGrid.from_points(ref, cell)
        tq, tg, ts = [], [], []
        for _ in range(args.repeat):
            tq.append(best_of(lambda: tree.query(pts), 1))
            tg.append(best_of(lambda: NDTGrid.from_points(ref, cell), 1))
            ts.append(best_of(lambda: ndt_score(grid, pts), 1))
        q, g, sc = min(tq), min(tg), min(ts)
        print(f"NDT cell {cell:4.2f} m ({grid.cells:6d} cells): cKDTree query {q:6.3f} s | grid {g:6.3f} s "
              f"({g / q:4.2f}x query) | ndt_score {sc:6.3f} s ({sc / q:4.2f}x query)")
    t_query = best_of(lambda: tree.query(pts), 1)

    yaw = np.radians(1.0)
    truth = np.eye(4)
    truth[:3, :3] = [[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]]
    truth[:3, 3] = [0.02, -0.01, 0.015]
    src = apply_transform(pts, np.linalg.inv(truth))
    t = time.perf_counter()
    res = icp(src, ref, max_distance=0.1, kernel="tukey")
    t_icp = time.perf_counter() - t
    err = np.linalg.norm((np.linalg.inv(truth) @ res.transformation)[:3, 3])
    t_query = min(t_query, best_of(lambda: tree.query(pts), 1))
    print(f"ICP point-to-plane Tukey (normals incl.) {t_icp:7.3f} s ({t_icp / t_query:4.2f}x query), "
          f"fitness {res.fitness:.3f}, rmse {res.inlier_rmse * 1e3:.2f} mm, translation error {err * 1e3:.2f} mm")


if __name__ == "__main__":
    main()
