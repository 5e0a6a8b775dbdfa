"""Generate the shared NDT test clouds in tests/data/pcl/ (seeded, reproducible).

A room corner (floor and two walls, 2 m x 2 m) with a sphere on the floor, sampled twice
independently: ``ref.pcd`` (6000 points, 4 mm noise) is the reference; ``cloud.pcd``
(4000 points, 8 mm noise, moved by a 1 degree yaw and a few centimetres, plus 5 % uniform
outliers) is the cloud to score. The scene is offset from the origin by a non-round
vector so no point sits on a cell boundary. Coordinates are float32 (PCL's PointXYZ) and
written with 9 significant digits, which round-trips float32 exactly.

Run: /work/venv/bin/python tools/pcl_reference/make_clouds.py tests/data/pcl
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

OFFSET = np.array([0.137, -0.291, 0.073])


def sample_scene(rng: np.random.Generator, n: int, noise_m: float) -> np.ndarray:
    """Points on the floor z=0, walls x=0 and y=0 (0..2 m) and a 0.3 m sphere."""
    kind = rng.choice(4, size=n, p=[0.35, 0.2, 0.2, 0.25])
    u, v = rng.uniform(0.0, 2.0, n), rng.uniform(0.0, 2.0, n)
    p = np.empty((n, 3))
    p[kind == 0] = np.c_[u, v, np.zeros(n)][kind == 0]
    p[kind == 1] = np.c_[np.zeros(n), u, v][kind == 1]
    p[kind == 2] = np.c_[u, np.zeros(n), v][kind == 2]
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    p[kind == 3] = (np.array([1.2, 1.1, 0.3]) + 0.3 * d)[kind == 3]
    return p + rng.normal(scale=noise_m, size=p.shape) + OFFSET


def write_pcd(path: Path, pts: np.ndarray) -> None:
    pts = np.asarray(pts, dtype=np.float32)
    header = ("# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\n"
              "TYPE F F F\nCOUNT 1 1 1\nWIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\n"
              "DATA ascii\n").format(n=len(pts))
    body = "\n".join(" ".join(f"{float(c):.9g}" for c in row) for row in pts)
    path.write_text(header + body + "\n")


def main(out_dir: str) -> None:
    rng = np.random.default_rng(20261122)
    out = Path(out_dir)
    ref = sample_scene(rng, 6000, 0.004)
    cloud = sample_scene(rng, 3800, 0.008)
    yaw = np.deg2rad(1.0)
    rot = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    cloud = (cloud - OFFSET) @ rot.T + OFFSET + np.array([0.02, -0.015, 0.01])
    outliers = rng.uniform(-0.2, 2.2, size=(200, 3)) + OFFSET
    cloud = np.concatenate([cloud, outliers])
    write_pcd(out / "ref.pcd", ref)
    write_pcd(out / "cloud.pcd", cloud)


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "tests/data/pcl")
