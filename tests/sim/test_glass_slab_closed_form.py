"""The glass-slab closed form (benchmarks/glass_slab.py) against physics: (n-1) t on the axis,
the textbook angle form of a plane-parallel plate, Fermat's principle, and n = 1; and the
Mitsuba benchmark skips cleanly where Mitsuba is not installed (as in CI)."""

from __future__ import annotations

import os
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from benchmarks.glass_slab import GlassSlab, _hit_plane, _through, opl_through_slab, opl_without_slab

ROOT = Path(__file__).resolve().parents[2]


def _rays(n: int = 200, max_deg: float = 40.0, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    th = np.radians(rng.uniform(0, max_deg, n))
    ph = rng.uniform(0, 2 * np.pi, n)
    return np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], axis=1)


@pytest.mark.parametrize("n, t", [(1.5, 0.01), (1.33, 0.004), (2.4, 0.02)])
def test_axis_reads_n_minus_1_times_t_farther(n: float, t: float) -> None:
    slab = GlassSlab(n=n, t_m=t)
    axis = np.array([[0.0, 0.0, 1.0]])
    extra = opl_through_slab(slab, axis) - opl_without_slab(slab, axis)
    assert extra[0] == pytest.approx((n - 1) * t, abs=1e-12)


def test_matches_the_plate_formula_in_angles() -> None:
    # Emitter at the pinhole, target perpendicular at D: camera leg
    # z0/cos + n t/cos_t + (D - z0 - t)/cos, the hit moved inward by t (tan - tan_t).
    slab = GlassSlab(n=1.6, t_m=0.012, z0_m=0.03, emitter_m=(0.0, 0.0, 0.0))
    D = slab.target_point_m[2]
    u = _rays()
    th = np.arccos(u[:, 2])
    th_t = np.arcsin(np.sin(th) / slab.n)
    cam = slab.z0_m / np.cos(th) + slab.n * slab.t_m / np.cos(th_t) + (D - slab.z0_m - slab.t_m) / np.cos(th)
    r = D * np.tan(th) - slab.t_m * (np.tan(th) - np.tan(th_t))
    expected = cam + np.hypot(r, D)
    np.testing.assert_allclose(opl_through_slab(slab, u), expected, rtol=0, atol=1e-12)


def test_refracted_path_is_stationary_fermat() -> None:
    # The optical path pinhole -> entry -> exit -> hit is stationary in the entry point: moving
    # the entry point and re-joining straight lines (fixed hit) never shortens it to first order.
    slab = GlassSlab(n=1.5, t_m=0.01, z0_m=0.02)
    u = _rays(20, 35.0, seed=1)
    base = opl_through_slab(slab, u)
    entry, exit_ = _through(u, slab.n, slab.t_m, slab.z0_m)
    hit = _hit_plane(exit_, u, np.array(slab.target_point_m), np.array(slab.target_normal))
    e = np.asarray(slab.emitter_m)

    def opl(entry_xy: np.ndarray, exit_xy: np.ndarray) -> np.ndarray:
        p1 = np.column_stack([entry_xy, np.full(len(u), slab.z0_m)])
        p2 = np.column_stack([exit_xy, np.full(len(u), slab.z0_m + slab.t_m)])
        return (np.linalg.norm(p1, axis=1) + slab.n * np.linalg.norm(p2 - p1, axis=1)
                + np.linalg.norm(hit - p2, axis=1) + np.linalg.norm(e - hit, axis=1))

    np.testing.assert_allclose(opl(entry[:, :2], exit_[:, :2]), base, atol=1e-12)
    rng = np.random.default_rng(2)
    h = 1e-5
    for _ in range(20):
        d1, d2 = rng.normal(size=(len(u), 2)) * h, rng.normal(size=(len(u), 2)) * h
        plus = opl(entry[:, :2] + d1, exit_[:, :2] + d2)
        minus = opl(entry[:, :2] - d1, exit_[:, :2] - d2)
        # No first-order change (a wrong refraction angle gives ~h, here 1e-6) ...
        assert np.all(np.abs(plus - minus) < 1e-9)        # third order: ~1e-10
        # ... and a minimum: the second-order change is positive.
        assert np.all(plus + minus - 2 * base > 0)


def test_index_one_changes_nothing() -> None:
    slab = replace(GlassSlab(), n=1.0)
    u = _rays()
    np.testing.assert_allclose(opl_through_slab(slab, u), opl_without_slab(slab, u), atol=1e-12)


def test_mitsuba_benchmark_skips_cleanly_without_mitsuba(tmp_path: Path) -> None:
    # A 'mitsuba' module that fails to import stands for a machine without Mitsuba.
    (tmp_path / "mitsuba.py").write_text("raise ImportError('No module named mitsuba')\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")])}
    r = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "bench_vs_mitsuba.py"), "--quick"],
                       capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "SKIPPED" in r.stdout and "tools/setup_mitsuba.sh" in r.stdout
    assert "Traceback" not in r.stderr
