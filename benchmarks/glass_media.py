"""Glass and scattering media in the twin (issue 16): closed-form agreement at full resolution
and what they cost, in one run.

Printed: (1) a wall 1 m away through a 10 mm pane (n 1.5) at 0.3 m, emitter at the pinhole,
160 x 120 centre rays: the depth read against the plate formula per pixel, the centre pixel's
shift against (n-1) t, transmitted power against (1-R)^4 (D/(D-t+t/n))^2; (2) the benchmark
cover glass (benchmarks/glass_slab.py, emitter beside the glass) against opl_through_slab;
(3) single scattering of a 5 cm medium slab against quadrature; (4) the bundled glass_pane
scene (160 x 120, 4 spp, 1 bounce) with and without its pane: CPU seconds and rays per
sample (the cost of the split paths and of the slab links).

Run: python benchmarks/glass_media.py
"""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from tofhil import C_M_PER_S  # noqa: E402
from tofhil.demod import phase_to_distance, wrapped_phase  # noqa: E402
from tofhil.sim.render import render  # noqa: E402
from tofhil.sim.scene import load_scene, scene_from_dict  # noqa: E402

F = 44.0e6


def depth(ph: np.ndarray) -> np.ndarray:
    return phase_to_distance(wrapped_phase(ph), F)


def pane(n: float, t: float, z0: float, glass: bool = True) -> dict:
    objs = [{"name": "wall", "type": "plane", "size": [20, 20], "material": "white", "pose": {"position": [0, 0, 1.0]}}]
    if glass:
        objs.append({"name": "pane", "type": "box", "size": [3, 3, t], "material": "glass",
                     "pose": {"position": [0, 0, z0 + t / 2]}})
    return {"camera": {"preset": "holmlund_thesis", "f_number": 1.2},
            "emitter": {"power_w": 1.0, "offset_m": [0, 0, 0], "profile": {"type": "cos_n", "n": 1}},
            "materials": {"white": {"reflectance": 0.8}, "glass": {"ior": n}}, "objects": objs,
            "sensor": {"freq_hz": [F]}}


def main() -> int:
    n, t, z0, D = 1.5, 0.01, 0.3, 1.0
    sc = scene_from_dict(pane(n, t, z0))
    g, b = render(sc), render(scene_from_dict(pane(n, t, z0, glass=False)))
    rays = sc.camera.rays
    th = np.arccos(rays[..., 2])
    tht = np.arcsin(np.sin(th) / n)
    leg = z0 / np.cos(th) + n * t / np.cos(tht) + (D - z0 - t) / np.cos(th)
    dg = depth(g.phasor[0, 0])
    err = dg - leg
    H, W = dg.shape
    glint = np.zeros_like(err, bool)
    glint[H // 2 - 1:H // 2 + 1, W // 2 - 1:W // 2 + 1] = True
    r = ((n - 1) / (n + 1)) ** 2
    ratio = g.power_w / b.power_w / ((1 - r) ** 4 * (D / (D - t + t / n)) ** 2)
    near = (th < 0.05) & ~glint
    print(f"(1) wall through a pane (n {n}, t {t * 1e3:.0f} mm), {W}x{H}: depth - plate formula max "
          f"{1e3 * np.abs(err[~glint]).max():.4f} mm, RMS {1e3 * np.sqrt(np.mean(err[~glint] ** 2)):.4f} mm "
          f"(internal double reflections, R^2 = {r * r:.1e}, pull it); near-axis shift "
          f"{1e3 * np.mean((dg - depth(b.phasor[0, 0]))[near]):.4f} mm vs (n-1)t = {1e3 * (n - 1) * t:.4f} mm; "
          f"power / closed form near the axis {ratio[near].mean():.5f}")

    from glass_slab import GlassSlab, opl_through_slab, tofhil_scene_without_slab

    slab = GlassSlab()
    d = tofhil_scene_without_slab(slab)
    d["emitter"]["profile"] = {"type": "cos_n", "n": 0}
    d["materials"]["glass"] = {"ior": slab.n}
    d["objects"].append({"name": "cover", "type": "box", "material": "glass",
                         "size": [2 * slab.half_width_m, 2 * slab.half_width_m, slab.t_m],
                         "pose": {"position": [0.0, 0.0, slab.z0_m + slab.t_m / 2]}})
    s2 = scene_from_dict(d)
    e2 = depth(render(s2).phasor[0, 0]) - opl_through_slab(slab, s2.camera.rays) / 2
    print(f"(2) cover glass of benchmarks/glass_slab.py, {W}x{H}: depth - closed form max {1e3 * np.abs(e2).max():.4f} mm, "
          f"RMS {1e3 * np.sqrt(np.mean(e2 ** 2)):.4f} mm")

    sig_s, sig_a, hg, zf, tf = 4.0, 1.0, 0.3, 0.3, 0.05
    fog = {"camera": {"width": 16, "height": 12, "fx": 12.0, "fy": 12.0, "cx": 7.5, "cy": 5.5, "pixel_pitch_m": 96e-6,
                      "f_number": 1.2},
           "emitter": {"power_w": 1.0, "offset_m": [0, 0, 0], "profile": {"type": "cos_n", "n": 1}},
           "materials": {"fog": {"scattering_per_m": sig_s, "absorption_per_m": sig_a, "anisotropy": hg}},
           "objects": [{"name": "fog", "type": "box", "size": [3, 3, tf], "material": "fog",
                        "pose": {"position": [0, 0, zf + tf / 2]}}], "sensor": {"freq_hz": [F]}}
    c0 = time.process_time()
    res = render(scene_from_dict(fog), samples_per_pixel=16384, subpixel=False, bounces=0)
    cpu = time.process_time() - c0
    cam = scene_from_dict(fog).camera
    cos = cam.rays[..., 2]
    p_back = (1 - hg * hg) / (4 * math.pi * (1 + hg) ** 3)
    f = cam.fx * cam.pixel_pitch_m
    k = 2 * math.pi * F / C_M_PER_S
    P, Z = np.zeros_like(cos), np.zeros_like(cos, complex)
    for idx, c in np.ndenumerate(cos):
        ell = np.linspace(zf / c, (zf + tf) / c, 4001)
        rad = sig_s * p_back * (1 / math.pi) * c / ell ** 2 * np.exp(-2 * (sig_s + sig_a) * (ell - zf / c))
        to_pix = math.pi * (f / 2.4) ** 2 * c ** 4 * cam.pixel_pitch_m ** 2 / f ** 2
        P[idx], Z[idx] = np.trapezoid(rad, ell) * to_pix, np.trapezoid(rad * np.exp(2j * k * ell), ell) * to_pix
    rel = res.power_w / P - 1
    print(f"(3) single scattering of a medium slab (16x12, 16384 spp, {cpu:.1f} CPU-s): image power / quadrature "
          f"{res.power_w.sum() / P.sum():.5f} (Monte Carlo error {rel.std() / math.sqrt(rel.size):.5f}); per pixel "
          f"{rel.std():.4f} RMS; depth of the summed phasor - quadrature's "
          f"{1e3 * (depth(res.phasor[0, 0].sum()) - depth(Z.sum())):+.4f} mm")

    scene = load_scene("glass_pane")
    import dataclasses

    bare = dataclasses.replace(scene, objects=[o for o in scene.objects if o.name != "pane"])
    for label, s in (("without the pane", bare), ("with the pane", scene)):
        render(s, samples_per_pixel=1)                      # compile and build outside the timing
        c0 = time.process_time()
        r = render(s)
        cpu = time.process_time() - c0
        spp = r.samples_per_pixel
        print(f"(4) glass_pane {label}: {cpu:.2f} CPU-s, {r.rays_traced / (r.power_w.size * spp):.2f} rays per sample "
              f"({spp} spp, {r.bounces} bounce)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
