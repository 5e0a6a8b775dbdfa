"""The memory estimate made before a render matches what the render + sensor really allocate."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import pytest

from tofhil.errors import TofhilError
from tofhil.sim.memory import AVAILABLE_FRACTION, MemoryEstimate, check_memory, estimate_bytes

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
