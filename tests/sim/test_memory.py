"""The memory estimate made before a render matches what the render + sensor really allocate."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import pytest

from tofhil.errors import TofhilError
from tofhil.sim.memory import AVAILABLE_FRACTION, BVH_BYTES_PER_TRIANGLE, MemoryEstimate, check_memory, estimate_bytes

MEASURE = textwrap.dedent("""
    import json, resource, tracemalloc
    from tofhil.sim.memory import render_memory
    from tofhil.sim.pipeline import simulate
    from tofhil.sim.twin import render_arguments
    from tofhil.sim.scene import load_scene

    w, h, frames = 320, 240, 3
    ov = {"camera": {"preset": "holmlund_thesis", "width": w, "height": h, "fx": 0.73 * w, "fy": 0.73 * w,
                     "cx": (w - 1) / 2, "cy": (h - 1) / 2},
          "sensor": {"freq_hz": [20e6, 44e6]}, "render": {"samples_per_pixel": 2, "bounces": 1},
          "effects": {"stray_light": {"weight": 0.02, "sigma_px": 5.0}}}
    scene = load_scene("bench_demo", overrides=ov)
    simulate(load_scene("bench_demo", overrides={"render": {"bounces": 1}}), 1)   # compile the kernels first
    est = render_memory(scene, render_arguments(scene, scene.effects), frames_kept=frames, signal_effects=True)
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    tracemalloc.start()
    simulate(scene, frames)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    rss1 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    print(json.dumps({"estimate": est.total_bytes, "traced_peak": peak, "rss_growth": (rss1 - rss0) * 1024}))
""")


def test_estimate_is_within_a_factor_two_of_the_measured_peak() -> None:
    out = subprocess.run([sys.executable, "-c", MEASURE], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    m = json.loads(out.stdout.strip().splitlines()[-1])
    ratio = m["estimate"] / m["traced_peak"]
    print(m, ratio)
    assert 0.5 <= ratio <= 2.0, m


def test_estimate_scales_with_the_job() -> None:
    base = dict(width=100, height=100, render_freqs=1, harmonics=1, sensor_freqs=1, taps=4)
    e = estimate_bytes(**base).total_bytes
    assert estimate_bytes(**(base | {"width": 1000, "height": 1000})).total_bytes > 50 * e
    assert estimate_bytes(**(base | {"render_freqs": 4, "sensor_freqs": 4})).total_bytes > e
    assert estimate_bytes(**(base | {"transient_bins": 200})).total_bytes > 4 * e
    one = estimate_bytes(**(base | {"kept_frames": 1}))
    many = estimate_bytes(**(base | {"kept_frames": 101}))
    assert many.total_bytes - one.total_bytes == 100 * 100 * 100 * 4 * 4     # float32 taps [F, K, H, W]


def test_check_refuses_past_the_available_fraction() -> None:
    est = MemoryEstimate(render_bytes=3 << 30, sensor_bytes=1 << 30, frames_bytes=0)
    check_memory(est, available=int((3 << 30) / AVAILABLE_FRACTION) + 1)
    with pytest.raises(TofhilError) as e:
        check_memory(est, available=4 << 30, source="s.yaml")
    assert "3.00 GiB" in str(e.value) and "4.00 GiB is available" in str(e.value) and e.value.file == "s.yaml"


GEOMETRY = textwrap.dedent("""
    import json, os, sys, tempfile, textwrap
    import trimesh
    from tofhil.sim.memory import BVH_BYTES_PER_TRIANGLE, GEOMETRY_BYTES_PER_TRIANGLE, bvh_count, scene_triangles
    from tofhil.sim.render import scene_geometry
    from tofhil.sim.scene import load_scene

    def rss():
        with open("/proc/self/status") as f:
            return next(int(line.split()[1]) * 1024 for line in f if line.startswith("VmRSS:"))

    path = os.path.join(tempfile.mkdtemp(), "shapes.yaml")
    with open(path, "w") as f:
        f.write(textwrap.dedent('''
            name: shapes
            camera: {preset: holmlund_thesis}
            emitter: {power_w: 0.3}
            materials: {m: {reflectance: 0.5}}
            objects:
              - {name: s, type: sphere, radius: 0.3, subdivisions: 6, material: m, pose: {position: [0, 0, 2]}}
              - {name: c, type: cylinder, radius: 0.1, height: 0.3, sections: 24, material: m, pose: {position: [0.5, 0, 2]}}
              - {name: b, type: box, size: [0.1, 0.1, 0.1], material: m, pose: {position: [-0.5, 0, 2]}}
              - {name: p, type: plane, size: [1, 1], material: m, pose: {position: [0, 0, 3]}}
        '''))
    scene = load_scene(path)
    trimesh.creation.icosphere(subdivisions=1)      # trimesh's own import and tables first
    r0 = rss()
    geom = scene_geometry(scene)
    grown = rss() - r0
    n = scene_triangles(scene)
    print(json.dumps({"counted": n, "built": geom.n_triangles, "bvhs": bvh_count(), "grown": grown,
                      "estimate": n * (GEOMETRY_BYTES_PER_TRIANGLE + bvh_count() * BVH_BYTES_PER_TRIANGLE)}))
""")


def test_geometry_and_both_bvhs_are_counted() -> None:
    """A scene of 80k triangles: the triangles are counted without building them, and the
    estimate (float64 tables plus one BVH per Embree scene: embreex's and the compiled
    kernels' own) is within a factor two of what building them adds to the process."""
    out = subprocess.run([sys.executable, "-c", GEOMETRY], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    m = json.loads(out.stdout.strip().splitlines()[-1])
    assert m["counted"] == m["built"] == 20 * 4 ** 6 + 4 * 24 + 12 + 2
    assert 0.5 <= m["estimate"] / m["grown"] <= 2.0, m


def test_estimate_counts_a_bvh_per_embree_scene() -> None:
    base = dict(width=100, height=100, render_freqs=1, harmonics=1, sensor_freqs=1, taps=4)
    none = estimate_bytes(**base).total_bytes
    one = estimate_bytes(**(base | {"triangles": 10_000, "bvhs": 1})).total_bytes
    two = estimate_bytes(**(base | {"triangles": 10_000, "bvhs": 2})).total_bytes
    assert one > none and two - one == 10_000 * BVH_BYTES_PER_TRIANGLE
