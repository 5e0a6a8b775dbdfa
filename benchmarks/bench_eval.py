"""Benchmark: NDT scoring and ICP on 300k-point clouds, relative to a cKDTree NN query.

Prints, for a synthetic room (4 walls, floor, ceiling; 5 mm noise) of 300k reference
points and 300k measured points:
- NDT grid build and full ``ndt_score`` (PCL score, NVTL, cell + trilinear likelihood) at
  two cell sizes, as ratios to ONE scipy ``cKDTree.query`` of the same 300k points
  against the 300k reference (tree built beforehand), timed in the same run;
- robust point-to-plane ICP (Open3D, Tukey) time and its ratio to the same query.

- with ``--pcl BIN`` (``tools/pcl_reference/ndt_time.cpp`` built against Debian's libpcl-dev,
  see its header): the whole process, from two binary PCD files to the printed score, of
  ``tofhil ndt --score-only`` (PCL's score alone, as PCL computes it), of ``tofhil ndt``
  (all its scores) and of PCL 1.13's ``NormalDistributionsTransform`` (score at the
  identity), as CPU time of each child process (interpreter start-up and imports included),
  the three alternated; the scores printed (they agree to ~1e-8: same cells, same d1, d2).
  ``--before-python PY`` adds ``tofhil ndt --score-only`` run by another interpreter (one with
  an older tofhil installed, e.g. main's) to the alternation, for a before/after in one run.

Run: /work/venv/bin/python benchmarks/bench_eval.py [--points N] [--repeat K] [--pcl BIN [--only-pcl]
     [--before-python PY]]
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from tofhil.eval.metrics.matching import apply_transform, icp
from tofhil.eval.metrics.ndt import NDTGrid, ndt_score


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


def child_cpu_s(cmd: list[str], cwd: str | None = None) -> tuple[float, str]:
    """CPU time (user + system) of one child process run to its end, and its output."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    out = subprocess.run(cmd, check=True, capture_output=True, text=True, cwd=cwd).stdout
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime), out


def whole_process_vs_pcl(ref: np.ndarray, pts: np.ndarray, pcl_bin: str, repeat: int,
                         cells: tuple[float, ...] = (0.25, 0.5), before_python: str | None = None) -> None:
    """``tofhil ndt`` and PCL's NDT score from the same binary PCD files, whole processes."""
    from tofhil.open3d_loader import open3d

    o3d = open3d()          # (libusb from its wheel where the system has none)

    with tempfile.TemporaryDirectory() as tmp:
        files = []
        for name, p in (("ref", ref), ("cloud", pts)):
            path = Path(tmp) / f"{name}.pcd"
            pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p.astype(np.float32).astype(np.float64)))
            o3d.io.write_point_cloud(str(path), pc, write_ascii=False)
            files.append(str(path))
        env_py = [sys.executable, "-m", "tofhil.cli", "ndt", *files, "--json"]
        before_py = [before_python, "-m", "tofhil.cli", "ndt", *files, "--json", "--score-only"]
        print(f"whole process, {len(ref)} vs {len(pts)} points from binary PCD, CPU time of the child "
              f"(median of {repeat}, alternated):")
        for cell in cells:
            t_only, t_all, t_pcl, t_before = [], [], [], []
            for _ in range(repeat):
                # cwd: the temporary directory, so that `-m` does not import a tofhil from the
                # current directory (a source tree) instead of the one each interpreter has
                t, out_only = child_cpu_s(env_py + ["--cell-size", str(cell), "--score-only"], cwd=tmp)
                t_only.append(t)
                t, out_pcl = child_cpu_s([pcl_bin, *files, str(cell), "0.55", "6"], cwd=tmp)
                t_pcl.append(t)
                if before_python:
                    t, _ = child_cpu_s(before_py + ["--cell-size", str(cell)], cwd=tmp)
                    t_before.append(t)
                t, out = child_cpu_s(env_py + ["--cell-size", str(cell)], cwd=tmp)
                t_all.append(t)
            only, ours = json.loads(out_only)["score_per_point"], json.loads(out)["score_per_point"]
            theirs = float(out_pcl.split()[1])
            a, c, b = float(np.median(t_only)), float(np.median(t_all)), float(np.median(t_pcl))
            print(f"  cell {cell:4.2f} m: PCL {b:5.2f} CPU-s | tofhil ndt --score-only {a:5.2f} CPU-s -> {a / b:4.2f}x "
                  f"PCL (aim <= 0.5) | tofhil ndt, all scores {c:5.2f} CPU-s -> {c / b:4.2f}x; score per point "
                  f"{only:.10g} / {ours:.10g} vs PCL {theirs:.10g} (diff {max(abs(only - theirs), abs(ours - theirs)):.1e})")
            if t_before:
                z = float(np.median(t_before))
                print(f"             before ({before_python}): --score-only {z:5.2f} CPU-s -> {z / b:4.2f}x PCL")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--points", type=int, default=300_000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--pcl", default=None, help="tools/pcl_reference/ndt_time built: also the whole-process "
                                                 "comparison with PCL")
    ap.add_argument("--only-pcl", action="store_true")
    ap.add_argument("--before-python", default=None, help="with --pcl: also time tofhil ndt --score-only run by "
                                                          "this interpreter (an older tofhil), alternated")
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    ref = room(rng, args.points)
    pts = room(rng, args.points)
    if args.pcl:
        whole_process_vs_pcl(ref, pts, args.pcl, args.repeat, before_python=args.before_python)
        if args.only_pcl:
            return

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
