"""tofhil against Mitsuba 3 + mitransient: the same scene rendered by both, in one run.

Scenes: the bundled room corner (multipath) and a tilted plane (direct light only), both at
160 x 120 with the holmlund_thesis field of view, diffuse albedo 0.8, an isotropic point
emitter at the camera centre, 44 MHz. ``B`` indirect bounces in tofhil are Mitsuba's
``max_depth = B + 2`` (depth 1: the emitter seen directly, 2: direct light).

Conventions bridged here (nowhere else):
  * mitransient's ``phasor_hdr_film`` accumulates ``w exp(-i 2 pi nu L)`` (nu in cycles per
    metre of optical path); tofhil's phasor is ``w exp(+i 2 pi f L / c)``: we store
    ``nu = f / c`` and take the complex conjugate.
  * Mitsuba's camera looks along its local +z with x left and y up; OpenCV's (tofhil's) has
    x right and y down: Mitsuba's camera-to-world is tofhil's pose times diag(-1, -1, 1).

Printed:
  (1) agreement: per pixel, the difference of the two renderers' depth (equivalently of
      their multipath depth errors: the geometry cancels) against the Monte Carlo noise
      each renderer's own sample variance predicts (from independent passes): the RMS of
      the difference, the RMS predicted noise and their ratio (1 = agreement within noise),
      the mean difference in standard errors (a bias test over all pixels) and the
      correlation of the two depth-error maps; plus each renderer's direct-only error.
  (2) issue 16: Mitsuba and tofhil through a glass slab over the lens against the closed-form
      extra optical path (benchmarks/glass_slab.py).
  (4) issue 16: a scattering cube (homogeneous medium, HG phase function) before a wall, as in
      (1): per-pixel depth difference against both renderers' Monte Carlo noise.
  (3) CPU time (process CPU seconds, all threads) to 1 mm RMS depth error against the
      converged image, for tofhil (its default Sobol sampler) and for Mitsuba's samplers
      (independent = its default, multijitter, ...), on the corner and on the tilted plane
      (over the pixels seen whole: :func:`interior_pixels`; on the plane with B bounces
      too, where no bounce returns light, so its error is the direct light's over the
      sub-pixel positions). A "sample" is one path in both renderers (tofhil's paths may
      share camera rays, see docs/scene-format.md; the CPU time to 1 mm does not depend on
      what a sample is). The error of one render of N samples
      per pixel is measured from two renders with different seeds,
      ``rms = sqrt(mean (d1 - d2)^2 / 2)``; the spp for 1 mm comes from a power-law fit
      ``rms = a N^-alpha`` over the measured N (measured where it brackets 1 mm).

Set-up: ``bash tools/setup_mitsuba.sh`` (pip packages + libLLVM 19 for Dr.Jit's CPU backend);
without Mitsuba this script says so and exits 0 (skipped).

Run: python benchmarks/bench_vs_mitsuba.py [--quick] [--figures docs/figures]
    [--before DIR [--rounds 2]]   # the same with an older tofhil, alternately (before_after.py)
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from tofhil import C_M_PER_S
from tofhil.demod import phase_to_distance, wrapped_phase

if TYPE_CHECKING:
    from tofhil.sim.scene import Scene
# tofhil.sim (numba, Embree) is imported where it is used: without Mitsuba the script says so
# and exits before paying for those imports.

FREQ_HZ = 44.0e6
ALBEDO = 0.8
#: Where tools/setup_mitsuba.sh unpacks libLLVM 19 by default.
DEFAULT_LLVM = Path.home() / ".cache/tofhil/llvm19/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1"
#: The emitter radiates uniformly over the whole sphere (Mitsuba's ``point``); tofhil's
#: tabulated beam profile, flat from 0 to 180 degrees, is the same source.
ISOTROPIC = {"type": "table", "theta_deg": [0.0, 180.0], "relative_intensity": [1.0, 1.0]}
#: Forward hemisphere only (tofhil cos^0, Mitsuba's spot light with a 90 degree cut-off).
HEMISPHERE = {"type": "cos_n", "n": 0.0}

#: Mitsuba 3's ray-spawn offset scale for float32 variants: math::RayEpsilon = 2^-24 * 1500.
MITSUBA_RAY_EPS = 1500 * 2.0 ** -24

SETUP_HINT = ("Mitsuba 3 + mitransient are not set up: run `bash tools/setup_mitsuba.sh` "
              "(pip install mitsuba mitransient; libLLVM 19 unpacked from the distribution's "
              "libllvm19 package) and export DRJIT_LIBLLVM_PATH as it prints.")


# --------------------------------------------------------------------------- scenes
def corner_scene(emitter: dict) -> Scene:
    from tofhil.sim.scene import load_scene

    return load_scene("corner", overrides={"params": {"wall_reflectance": ALBEDO},
                                           "emitter": {"offset_m": [0.0, 0.0, 0.0], "profile": emitter},
                                           "sensor": {"freq_hz": [FREQ_HZ]}})


def tilted_plane_scene(emitter: dict) -> Scene:
    """A 4 m x 4 m plane 1 m in front of the camera, turned 35 deg about the vertical and
    10 deg about the horizontal axis: it fills the view, depth 0.6 .. 2.3 m, no multipath."""
    from tofhil.sim.scene import scene_from_dict

    return scene_from_dict({
        "name": "tilted_plane",
        "camera": {"preset": "holmlund_thesis",
                   "pose": {"position": [0.0, 0.0, 0.0], "look_at": [0.0, 0.0, 1.0], "up": [0.0, -1.0, 0.0]}},
        "emitter": {"offset_m": [0.0, 0.0, 0.0], "power_w": 0.3, "profile": emitter},
        "materials": {"white": {"reflectance": ALBEDO}},
        "objects": [{"name": "plane", "type": "plane", "size": [4.0, 4.0], "material": "white",
                     "pose": {"position": [0.0, 0.0, 1.0], "rotation_deg": [10.0, 35.0, 0.0]}}],
        "sensor": {"freq_hz": [FREQ_HZ]},
    })


# --------------------------------------------------------------------------- renderers
@dataclass
class Pass:
    phasor: np.ndarray      # complex [H, W], tofhil's sign convention
    cpu_s: float            # process CPU time (all threads)


def cpu_timed(fn, *args, **kw):
    c0 = time.process_time()
    out = fn(*args, **kw)
    return out, time.process_time() - c0


class Tofhil:
    name = "tofhil"

    def __init__(self, scene: Scene, bounces: int, threads: int, sampler: str = "sobol",
                 wavefront: bool = False) -> None:
        self.scene, self.bounces, self.threads, self.sampler = scene, bounces, threads, sampler
        self.wavefront = wavefront                    # the bounce-by-bounce loop instead of the fused one
        self.label = f"tofhil ({sampler}{', wavefront loop' if wavefront else ''})"
        self.render(1, seed=0)                        # JIT warm-up and geometry build

    def render(self, spp: int, seed: int) -> Pass:
        from tofhil.sim.render import render

        old = os.environ.get("TOFHIL_RENDER_WAVEFRONT")
        os.environ["TOFHIL_RENDER_WAVEFRONT"] = "1" if self.wavefront else "0"
        try:
            res, cpu = cpu_timed(render, self.scene, samples_per_pixel=spp, bounces=self.bounces, seed=seed,
                                 threads=self.threads, sampler=self.sampler, freq_hz=[FREQ_HZ])
        finally:
            if old is None:
                del os.environ["TOFHIL_RENDER_WAVEFRONT"]
            else:
                os.environ["TOFHIL_RENDER_WAVEFRONT"] = old
        return Pass(res.phasor[0, 0], cpu)

    def geometry_radial_m(self) -> np.ndarray:
        from tofhil.sim.render import render

        return render(self.scene, samples_per_pixel=1, bounces=0, freq_hz=[FREQ_HZ]).radial_m


def load_mitsuba():
    """Import Mitsuba (llvm_ad_mono) and mitransient, or return None with the reason printed."""
    if "DRJIT_LIBLLVM_PATH" not in os.environ and DEFAULT_LLVM.is_file():
        os.environ["DRJIT_LIBLLVM_PATH"] = str(DEFAULT_LLVM)
    try:
        import mitsuba as mi
        mi.set_variant("llvm_ad_mono")
        import mitransient  # noqa: F401  (registers phasor_hdr_film and transient_path)
    except Exception as exc:                          # ImportError, or no LLVM for the variant
        print(f"SKIPPED: {SETUP_HINT}\n  ({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})")
        return None
    return mi


class Mitsuba:
    def __init__(self, mi, scene: Scene, bounces: int, sampler: str, workdir: Path,
                 extra_shapes: dict | None = None, max_depth: int | None = None,
                 integrator: str = "transient_path") -> None:
        from tofhil.sim.geometry import object_mesh

        self.mi, self.sampler = mi, sampler
        self.label = f"Mitsuba ({sampler})"
        cam = scene.camera
        H, W = cam.shape
        # 2 pi nu L with nu = f/c cycles per metre; the film picks its frequencies from the
        # FFT grid of temporal_bins x bin_width_opl, so make one wavelength the whole window:
        # then index 1 of the stored frequencies is exactly nu.
        wavelength_m = C_M_PER_S / FREQ_HZ
        bins = 1024
        flip = np.diag([-1.0, -1.0, 1.0, 1.0])
        to_world = mi.ScalarTransform4f(np.asarray(scene.camera_pose @ flip, dtype=np.float64).tolist())
        fov_x = math.degrees(2 * math.atan((W / 2) / cam.fx))
        shapes = {}
        for i, obj in enumerate(scene.objects):
            if scene.materials[obj.material].ior is not None:
                shapes[f"shape{i}"] = mitsuba_box(mi, obj, scene.materials[obj.material])
                continue
            v, f, _ = object_mesh(obj)
            v = v @ obj.pose[:3, :3].T + obj.pose[:3, 3]
            path = workdir / f"{scene.name}_{i}.ply"
            write_ply(path, v, np.asarray(f))
            rho = scene.materials[obj.material].reflectance
            # tofhil's surfaces reflect on both sides; Mitsuba's diffuse BSDF on the front only.
            shapes[f"shape{i}"] = {"type": "ply", "filename": str(path), "face_normals": True,
                                   "bsdf": {"type": "twosided", "bsdf": {
                                       "type": "diffuse", "reflectance": {"type": "uniform", "value": rho}}}}
        emitter_pos = scene.emitter_position_world().tolist()
        if scene.emitter.profile.kind == "table":       # isotropic over the sphere
            emitter = {"type": "point", "position": emitter_pos, "intensity": {"type": "uniform", "value": 1.0}}
        else:                                            # forward hemisphere, flat
            axis = (scene.camera_pose[:3, :3] @ scene.emitter.axis)
            emitter = {"type": "spot", "cutoff_angle": 90.0, "beam_width": 90.0,
                       "intensity": {"type": "uniform", "value": 1.0},
                       "to_world": mi.ScalarTransform4f().look_at(origin=emitter_pos,
                                                                  target=(np.array(emitter_pos) + axis).tolist(),
                                                                  up=_any_perpendicular(axis).tolist())}
        self.scene = mi.load_dict({
            "type": "scene",
            "integrator": {"type": integrator, "max_depth": max_depth or bounces + 2, "rr_depth": 1000,
                           "camera_unwarp": False},
            "sensor": {"type": "perspective", "fov": fov_x, "fov_axis": "x", "to_world": to_world,
                       # Mitsuba starts camera rays on the near-clip plane and mitransient
                       # counts the path from there: the default 1 cm would shorten every path.
                       "near_clip": 1e-6, "far_clip": 1e3,
                       "sampler": {"type": sampler, "sample_count": 1},
                       "film": {"type": "phasor_hdr_film", "width": W, "height": H,
                                "temporal_bins": bins, "bin_width_opl": wavelength_m / bins, "start_opl": 0.0,
                                "wl_mean": wavelength_m, "wl_sigma": wavelength_m,
                                "rfilter": {"type": "box"}}},
            "emitter": emitter,
            **shapes,
            **(extra_shapes or {}),
        })
        freqs = np.array(self.scene.sensors()[0].film().frequencies, dtype=np.float64).ravel()
        self.index = int(np.argmin(np.abs(freqs - 1.0 / wavelength_m)))
        if abs(freqs[self.index] * wavelength_m - 1.0) > 1e-5:
            raise RuntimeError(f"phasor film has no frequency at 1/{wavelength_m:.4f} m: {freqs}")
        self.render(4, seed=0)                            # JIT compile outside the timings

    def render(self, spp: int, seed: int) -> Pass:
        import drjit as dr

        def go():
            _steady, ph = self.mi.render(self.scene, spp=spp, seed=seed)
            dr.eval(ph)
            return np.array(ph)

        ph, cpu = cpu_timed(go)
        # [H, W, n_freq, 2] (re, im) of exp(-i 2 pi nu L): conjugate to tofhil's sign.
        return Pass(ph[:, :, self.index, 0] - 1j * ph[:, :, self.index, 1], cpu)


def mitsuba_box(mi, obj, mat) -> dict:
    """A tofhil glass or medium box as a Mitsuba cube: ``dielectric`` (glass), or a ``null``
    boundary around a ``homogeneous`` medium (index-matched, HG phase function)."""
    half = np.asarray(obj.params["size"], dtype=np.float64) / 2
    M = obj.pose @ np.diag([half[0], half[1], half[2], 1.0])
    shape = {"type": "cube", "to_world": mi.ScalarTransform4f(M.tolist())}
    if mat.scattering_per_m > 0 or mat.ior == 1.0:
        sig_t = mat.scattering_per_m + mat.absorption_per_m
        shape["bsdf"] = {"type": "null"}
        shape["interior"] = {"type": "homogeneous", "sigma_t": sig_t,
                             "albedo": mat.scattering_per_m / sig_t if sig_t > 0 else 0.0,
                             "phase": {"type": "hg", "g": mat.anisotropy}}
    else:
        shape["bsdf"] = {"type": "dielectric", "int_ior": mat.ior, "ext_ior": 1.0}
    return shape


def _any_perpendicular(a: np.ndarray) -> np.ndarray:
    t = np.array([1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    return np.cross(a, t)


def write_ply(path: Path, v: np.ndarray, f: np.ndarray) -> None:
    """Binary little-endian PLY of a triangle mesh (what Mitsuba's ``ply`` shape reads)."""
    head = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(v)}\n"
            "property float x\nproperty float y\nproperty float z\n"
            f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n").encode()
    faces = np.zeros(len(f), dtype=[("n", "u1"), ("i", "<i4", 3)])
    faces["n"], faces["i"] = 3, f
    path.write_bytes(head + np.asarray(v, dtype="<f4").tobytes() + faces.tobytes())


# --------------------------------------------------------------------------- statistics
def depth_m(s: np.ndarray) -> np.ndarray:
    return phase_to_distance(wrapped_phase(s), FREQ_HZ)


def mean_and_sigma(passes: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Depth of the mean phasor of independent passes and its standard error per pixel.

    Linearised: a pass's phase deviation from the mean is Im(P conj(S)) / |S|^2, so the
    standard error of the mean's phase is std(those) / sqrt(m), in metres via the demod
    phase -> distance scale.
    """
    P = np.stack(passes)
    S = P.mean(axis=0)
    with np.errstate(invalid="ignore"):               # pixels without light: NaN, masked later
        dev = (P * np.conj(S)).imag / np.abs(S) ** 2
    sig_phase = dev.std(axis=0, ddof=1) / math.sqrt(len(passes))
    return depth_m(S), phase_to_distance(sig_phase, FREQ_HZ)


def rms_error_one_render(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    """RMS depth error of ONE render from two independent ones: E (d1 - d2)^2 = 2 var
    (over the pixels of ``mask``, default all)."""
    d = depth_m(a) - depth_m(b)
    half = C_M_PER_S / (4 * FREQ_HZ)                 # wrap jumps (a pixel near 0 or 2 pi)
    d = (d + half) % (2 * half) - half
    if mask is not None:
        d = d[mask]
    return float(np.sqrt(np.mean(d ** 2) / 2))


def interior_pixels(radial_m: np.ndarray) -> np.ndarray:
    """Pixels whose centre ray and its 8 neighbours' all hit the scene (the image border
    counts as a hit): a pixel on an object's outline that sees it over a sliver of its area
    has a tiny phasor and a depth error of centimetres to metres (the tilted plane's image
    corner: 0.5 m in one pixel at 64 spp), which would be the whole of an RMS over pixels."""
    hit = np.pad(np.isfinite(radial_m), 1, constant_values=True)
    H, W = radial_m.shape
    return np.all([hit[1 + dy:1 + dy + H, 1 + dx:1 + dx + W] for dy in (-1, 0, 1) for dx in (-1, 0, 1)], axis=0)


# --------------------------------------------------------------------------- parts
def agreement(name: str, tf: Tofhil, ms: Mitsuba, geom_radial: np.ndarray, passes: int, spp: int,
              direct: tuple[Tofhil, Mitsuba] | None, figures: Path | None) -> dict:
    P_t = [tf.render(spp, seed=100 + k).phasor for k in range(passes)]
    P_m = [ms.render(spp, seed=100 + k).phasor for k in range(passes)]
    d_t, s_t = mean_and_sigma(P_t)
    d_m, s_m = mean_and_sigma(P_m)
    ok = np.isfinite(geom_radial) & (np.abs(P_t[0]) > 0)
    e_t, e_m = (d_t - geom_radial)[ok], (d_m - geom_radial)[ok]
    diff = (d_t - d_m)[ok]
    noise2 = (s_t ** 2 + s_m ** 2)[ok]
    out = {
        "scene": name, "pixels": int(ok.sum()), "spp": passes * spp,
        "err_t_mm": 1e3 * float(np.mean(e_t)), "err_m_mm": 1e3 * float(np.mean(e_m)),
        "err_max_t_mm": 1e3 * float(np.max(e_t)), "err_max_m_mm": 1e3 * float(np.max(e_m)),
        "diff_mean_mm": 1e3 * float(np.mean(diff)),
        "diff_rms_mm": 1e3 * float(np.sqrt(np.mean(diff ** 2))),
        "noise_rms_mm": 1e3 * float(np.sqrt(np.mean(noise2))),
        # The mean difference over N pixels has standard error ~ noise / sqrt(N): a bias test.
        "bias_z": float(np.mean(diff) / math.sqrt(np.mean(noise2) / len(diff))),
        "corr": float(np.corrcoef(e_t, e_m)[0, 1]) if np.std(e_t) > 0 and np.std(e_m) > 0 else float("nan"),
    }
    print(f"  {name}: {out['pixels']} pixels, {out['spp']} spp each ({passes} passes): multipath depth error "
          f"mean {out['err_t_mm']:.2f} mm (tofhil) vs {out['err_m_mm']:.2f} mm (Mitsuba), max "
          f"{out['err_max_t_mm']:.1f} vs {out['err_max_m_mm']:.1f} mm")
    print(f"    per-pixel difference: RMS {out['diff_rms_mm']:.3f} mm (mean {out['diff_mean_mm']:+.3f} mm); "
          f"noise predicted from the two renderers' own sample variance {out['noise_rms_mm']:.3f} mm RMS; "
          f"ratio {out['diff_rms_mm'] / out['noise_rms_mm']:.3f}; mean difference {out['bias_z']:+.1f} standard "
          f"errors; error maps correlate at {out['corr']:.4f}")
    if direct is not None:
        dt = depth_m(direct[0].render(4, seed=1).phasor)[ok] - geom_radial[ok]
        dm = depth_m(direct[1].render(4, seed=1).phasor)[ok] - geom_radial[ok]
        out["direct_t_mm"], out["direct_m_mm"] = 1e3 * float(np.mean(dt)), 1e3 * float(np.mean(dm))
        out["direct_t_rms_mm"] = 1e3 * float(np.sqrt(np.mean(dt ** 2)))
        out["direct_m_rms_mm"] = 1e3 * float(np.sqrt(np.mean(dm ** 2)))
        print(f"    direct light only (4 spp): depth - geometry mean {out['direct_t_mm']:+.4f} mm "
              f"(RMS {out['direct_t_rms_mm']:.4f}) tofhil, {out['direct_m_mm']:+.4f} mm "
              f"(RMS {out['direct_m_rms_mm']:.4f}) Mitsuba")
    if figures is not None:
        save_maps(figures / f"validation_{name}.png", name, d_t - geom_radial, d_m - geom_radial, d_t - d_m,
                  np.sqrt(s_t ** 2 + s_m ** 2), ok, out)
    return out


def save_maps(path: Path, name: str, e_t, e_m, diff, noise, ok, out) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    def masked(a):
        return np.where(ok, a * 1e3, np.nan)

    vmax = float(np.nanpercentile(np.abs(masked(e_t)), 99.5)) or 1.0
    fig, ax = plt.subplots(1, 3, figsize=(12, 3.2), constrained_layout=True)
    for a, img, title in ((ax[0], masked(e_t), "tofhil: depth - geometry"),
                          (ax[1], masked(e_m), "Mitsuba 3 + mitransient")):
        im = a.imshow(img, cmap="viridis", vmin=min(0.0, -vmax * 0.05), vmax=vmax)
        a.set_title(title, fontsize=9)
        a.axis("off")
    fig.colorbar(im, ax=ax[:2], shrink=0.85, label="mm")
    z = masked(diff) / np.where(ok, noise * 1e3, np.nan)
    im2 = ax[2].imshow(z, cmap="RdBu_r", vmin=-4, vmax=4)
    ax[2].set_title(f"difference / predicted noise (RMS diff {out['diff_rms_mm']:.2f} mm,\n"
                    f"noise {out['noise_rms_mm']:.2f} mm)", fontsize=9)
    ax[2].axis("off")
    fig.colorbar(im2, ax=ax[2], shrink=0.85, label="sigma")
    fig.suptitle(f"{name}: multipath depth error, {out['spp']} spp per renderer", fontsize=10)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=72)
    plt.close(fig)
    shrink_png(path)


def shrink_png(path: Path) -> None:
    """An adaptive 256-colour palette: the noise map does not compress; this halves the file."""
    from PIL import Image

    Image.open(path).convert("RGB").convert("P", palette=Image.ADAPTIVE, colors=256).save(path, optimize=True)


def time_to_1mm(r, spps: list[int], mask: np.ndarray | None = None, target_m: float = 1e-3) -> dict:
    """Measure the one-render RMS error at each N and fit rms = a N^-alpha; CPU s per spp from
    the timings (the fit's N for 1 mm, or ``target_m``, times the measured CPU cost per sample
    per pixel)."""
    rows = []
    for n in spps:
        a, b = r.render(n, seed=1), r.render(n, seed=2)
        rows.append((n, rms_error_one_render(a.phasor, b.phasor, mask), (a.cpu_s + b.cpu_s) / 2))
    N = np.array([x[0] for x in rows], float)
    E = np.array([x[1] for x in rows])
    T = np.array([x[2] for x in rows])
    slope, icpt = np.polyfit(np.log(N), np.log(E), 1)
    n_1mm = math.exp((math.log(target_m) - icpt) / slope)
    # CPU time is affine in N (a fixed cost per call plus a cost per sample): fit and evaluate.
    tb, ta = np.polyfit(N, T, 1) if len(N) > 1 else (T[0] / N[0], 0.0)
    t_1mm = ta + tb * n_1mm
    bracket = E.min() <= target_m <= E.max()
    pts = ", ".join(f"{int(n)} spp: {e * 1e3:.2f} mm / {t:.1f} CPU-s" for n, e, t in rows)
    print(f"  {r.label:24s} {pts}")
    print(f"  {'':24s} -> {target_m * 1e3:g} mm at {n_1mm:.0f} spp, {t_1mm:.1f} CPU-s (error ~ spp^{slope:.2f}; "
          f"{'interpolated' if bracket else 'EXTRAPOLATED'}); {tb / (120 * 160) * 1e9:.0f} CPU-ns per path sample")
    return {"label": r.label, "spp_1mm": n_1mm, "cpu_1mm": t_1mm, "alpha": -slope, "ns_per_sample": tb / 19200 * 1e9}


def glass_slab_check(mi, work: Path, spp: int) -> dict:
    """Issue 16: Mitsuba and tofhil through a cover glass against the closed form. The slab
    adds 2 specular interfaces: Mitsuba max_depth 2 + 2 (direct light)."""
    from glass_slab import GlassSlab, mitsuba_slab_shape, opl_through_slab, opl_without_slab, tofhil_scene_without_slab

    from tofhil.sim.scene import scene_from_dict

    slab = GlassSlab()
    scene = scene_from_dict(tofhil_scene_without_slab(slab, freq_hz=FREQ_HZ))
    rays = scene.camera.rays
    assert slab.covers_view(rays)
    ms = Mitsuba(mi, scene, 0, "independent", work,
                 extra_shapes={"slab": mitsuba_slab_shape(slab, scene.camera_pose)}, max_depth=4)
    plain = Mitsuba(mi, scene, 0, "independent", work)
    # Same seed: the same sub-pixel positions in both renders, so the pixel-area averaging
    # cancels in the difference and the per-pixel extra path is compared almost noise-free.
    d_glass = depth_m(ms.render(spp, seed=3).phasor)
    d_plain = depth_m(plain.render(spp, seed=3).phasor)
    extra_ms = d_glass - d_plain
    extra_cf = (opl_through_slab(slab, rays) - opl_without_slab(slab, rays)) / 2
    # Mitsuba spawns each continuing ray RAY_EPS (1 + max|p|) off the surface along the
    # normal and mitransient sums si.t from there: per crossing, the path loses that offset
    # along the ray (x n inside the glass). Predicted loss of the two crossings, as depth:
    u = rays / np.linalg.norm(rays, axis=-1, keepdims=True)
    cos_t = np.sqrt(1 - (1 - u[..., 2] ** 2) / slab.n ** 2)
    eps_in, eps_out = (MITSUBA_RAY_EPS * (1 + z) for z in (slab.z0_m, slab.z0_m + slab.t_m))
    spawn_loss = (slab.n * eps_in / cos_t + eps_out / u[..., 2]) / 2
    H, W = d_glass.shape
    c = (H // 2, W // 2)
    out = {"n": slab.n, "t_mm": slab.t_m * 1e3,
           "extra_centre_closed_mm": 1e3 * float(extra_cf[c]),
           "extra_centre_mitsuba_mm": 1e3 * float(extra_ms[c]),
           "extra_range_mm": (1e3 * float(extra_cf.min()), 1e3 * float(extra_cf.max())),
           "diff_rms_mm": 1e3 * float(np.sqrt(np.mean((extra_ms - extra_cf) ** 2))),
           "diff_mean_mm": 1e3 * float(np.mean(extra_ms - extra_cf)),
           "spawn_loss_mm": 1e3 * float(np.mean(spawn_loss)),
           "diff_corrected_mean_mm": 1e3 * float(np.mean(extra_ms - extra_cf + spawn_loss)),
           "diff_corrected_rms_mm": 1e3 * float(np.sqrt(np.mean((extra_ms - extra_cf + spawn_loss) ** 2)))}
    # tofhil's refraction (issue 16) on the same scene: its emitter beam is the compiled
    # loop's cos^n (flat ahead, cos^0); the emitter is beside the glass, its power does not
    # enter the depth.
    d = tofhil_scene_without_slab(slab, freq_hz=FREQ_HZ)
    d["emitter"]["profile"] = HEMISPHERE
    plain_t = Tofhil(scene_from_dict(d), 0, 2)
    d["materials"]["glass"] = {"ior": slab.n}
    d["objects"].append({"name": "cover", "type": "box", "material": "glass",
                         "size": [2 * slab.half_width_m, 2 * slab.half_width_m, slab.t_m],
                         "pose": {"position": [0.0, 0.0, slab.z0_m + slab.t_m / 2]}})
    glass_t = Tofhil(scene_from_dict(d), 0, 2)
    extra_t = depth_m(glass_t.render(spp, seed=3).phasor) - depth_m(plain_t.render(spp, seed=3).phasor)
    corrected = extra_ms + spawn_loss
    # Mitsuba with four more events (max_depth 8): the cover's internal echo on the camera
    # leg, and the target's light that the cover reflects onto the target again, off its back
    # face (2 events) and off its front face from inside (4 events: in, reflect, out, target);
    # tofhil with one bounce has all of them (its splitting follows the echo; the bounce off
    # the target meets the cover and its reflected branches return). Mitsuba picks reflection
    # or refraction at random, so its 4 % branches are noisy: 8x the samples, the image mean.
    ms6 = Mitsuba(mi, scene, 0, "independent", work,
                  extra_shapes={"slab": mitsuba_slab_shape(slab, scene.camera_pose)}, max_depth=8)
    plain6 = Mitsuba(mi, scene, 0, "independent", work, max_depth=8)
    extra6_ms = depth_m(ms6.render(8 * spp, seed=5).phasor) - depth_m(plain6.render(8 * spp, seed=5).phasor) + spawn_loss
    glass_t1, plain_t1 = Tofhil(glass_t.scene, 1, 2), Tofhil(plain_t.scene, 1, 2)
    extra6_t = depth_m(glass_t1.render(spp, seed=5).phasor) - depth_m(plain_t1.render(spp, seed=5).phasor)
    out.update(echo_tofhil_centre_mm=1e3 * float(extra_t[c] - extra_cf[c]),
               b1_mitsuba_mean_mm=1e3 * float(np.mean(extra6_ms - extra_cf)),
               b1_tofhil_mean_mm=1e3 * float(np.mean(extra6_t - extra_cf)),
               b1_diff_mean_mm=1e3 * float(np.mean(extra6_t - extra6_ms)),
               b1_diff_rms_mm=1e3 * float(np.sqrt(np.mean((extra6_t - extra6_ms) ** 2))))
    out.update(tofhil_centre_mm=1e3 * float(extra_t[c]),
               tofhil_vs_closed_rms_mm=1e3 * float(np.sqrt(np.mean((extra_t - extra_cf) ** 2))),
               tofhil_vs_closed_max_mm=1e3 * float(np.abs(extra_t - extra_cf).max()),
               tofhil_vs_mitsuba_rms_mm=1e3 * float(np.sqrt(np.mean((extra_t - corrected) ** 2))),
               tofhil_vs_mitsuba_mean_mm=1e3 * float(np.mean(extra_t - corrected)))
    print(f"(2) glass slab (n {slab.n}, t {slab.t_m * 1e3:.0f} mm over the lens, emitter beside it), Mitsuba "
          f"{spp} spp: the slab makes the centre pixel read {out['extra_centre_mitsuba_mm']:.3f} mm farther, "
          f"closed form {out['extra_centre_closed_mm']:.3f} mm ((n-1)t/2 = {(slab.n - 1) * slab.t_m / 2 * 1e3:.3f} "
          f"on the axis); over the image the closed-form extra spans {out['extra_range_mm'][0]:.3f} .. "
          f"{out['extra_range_mm'][1]:.3f} mm and Mitsuba's differs from it by {out['diff_rms_mm']:.4f} mm RMS "
          f"(mean {out['diff_mean_mm']:+.4f} mm); Mitsuba's ray-spawn offset predicts -{out['spawn_loss_mm']:.4f} mm: "
          f"corrected for it, {out['diff_corrected_rms_mm']:.4f} mm RMS (mean {out['diff_corrected_mean_mm']:+.4f} mm)")
    print(f"    tofhil ({spp} spp, refraction): centre pixel {out['tofhil_centre_mm']:.4f} mm farther; against the "
          f"closed form {out['tofhil_vs_closed_rms_mm']:.4f} mm RMS (max {out['tofhil_vs_closed_max_mm']:.4f}); "
          f"against Mitsuba (corrected) {out['tofhil_vs_mitsuba_rms_mm']:.4f} mm RMS "
          f"(mean {out['tofhil_vs_mitsuba_mean_mm']:+.4f} mm)")
    print(f"    with the cover's echo and its reflections of the target (tofhil 1 bounce, {spp} spp; Mitsuba max_depth 8, "
          f"{8 * spp} spp): beyond the closed form, image mean {out['b1_tofhil_mean_mm']:+.4f} mm (tofhil) and "
          f"{out['b1_mitsuba_mean_mm']:+.4f} mm (Mitsuba, corrected); tofhil - Mitsuba {out['b1_diff_mean_mm']:+.4f} mm "
          f"(per pixel {out['b1_diff_rms_mm']:.4f} mm RMS); the echo alone moves tofhil's centre pixel "
          f"{out['echo_tofhil_centre_mm']:+.4f} mm")
    return out


def scattering_cube_scene(emitter: dict, sigma_s: float, sigma_a: float, g: float) -> Scene:
    """A 0.4 m cube of a homogeneous medium 1 m in front of the camera, a white wall at 1.6 m
    behind it filling the view; the emitter at the camera centre."""
    from tofhil.sim.scene import scene_from_dict

    return scene_from_dict({
        "name": "scattering_cube",
        "camera": {"preset": "holmlund_thesis", "pose": {"position": [0.0, 0.0, 0.0]}},
        "emitter": {"offset_m": [0.0, 0.0, 0.0], "power_w": 1.0, "profile": emitter},
        "materials": {"white": {"reflectance": ALBEDO},
                      "fog": {"scattering_per_m": sigma_s, "absorption_per_m": sigma_a, "anisotropy": g}},
        "objects": [{"name": "wall", "type": "plane", "size": [6.0, 6.0], "material": "white",
                     "pose": {"position": [0.0, 0.0, 1.6]}},
                    {"name": "cube", "type": "box", "size": [0.4, 0.4, 0.4], "material": "fog",
                     "pose": {"position": [0.0, 0.0, 1.0], "rotation_deg": [0.0, 25.0, 0.0]}}],
        "sensor": {"freq_hz": [FREQ_HZ]},
    })


def scattering_cube_check(mi, work: Path, passes: int, spp: int, bounces: list[int], threads: int,
                          figures: Path | None) -> list[dict]:
    """A scattering cube in both renderers (Mitsuba: a null-bounded homogeneous medium,
    transient_prbvolpath; a flat forward-hemisphere spot as the emitter, which Mitsuba links
    through the null boundary with next-event estimation). Scattering events count as
    bounces in both: tofhil B = Mitsuba max_depth B + 2."""
    scene = scattering_cube_scene(HEMISPHERE, 5.0, 1.0, 0.5)
    print("(4) scattering cube (0.4 m, sigma_s 5/m, sigma_a 1/m, HG g 0.5, rotated 25 deg) before a wall at 1.6 m")
    geom = Tofhil(scene, 0, threads).geometry_radial_m()
    out = []
    for b in bounces:
        tf = Tofhil(scene, b, threads)
        ms = Mitsuba(mi, scene, b, "independent", work, integrator="transient_prbvolpath")
        out.append(agreement(f"scattering_cube_B{b}", tf, ms, geom, passes, spp, None, figures))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="small sample counts: a check that it runs (~1-2 min)")
    ap.add_argument("--bounces", type=int, nargs="+", default=[2], help="indirect bounces B (Mitsuba max_depth B+2)")
    ap.add_argument("--threads", type=int, default=min(2, os.cpu_count() or 1))
    ap.add_argument("--emitter", choices=("isotropic", "hemisphere"), default="isotropic",
                    help="isotropic point (Mitsuba 'point'); hemisphere: flat over the forward half-space")
    ap.add_argument("--samplers", nargs="+", default=["independent", "multijitter"],
                    help="Mitsuba samplers to time (independent is its default)")
    ap.add_argument("--figures", type=Path, default=None, help="write the error-map PNGs into this folder")
    ap.add_argument("--skip-timing", action="store_true")
    ap.add_argument("--only-timing", action="store_true", help="skip the agreement and glass-slab parts")
    ap.add_argument("--spps", type=int, nargs="+", default=None,
                    help="samples per pixel for the corner's timing (default 256 1024; --quick 16 64)")
    ap.add_argument("--timing-corner-only", action="store_true", help="time the corner only, not the tilted plane")
    ap.add_argument("--compare-wavefront", action="store_true",
                    help="also time tofhil's bounce-by-bounce loop (textures take it; before session 4 "
                         "tabulated beams, the isotropic emitter among them, did too)")
    ap.add_argument("--media-only", action="store_true", help="only the glass slab (2) and the scattering cube (4)")
    ap.add_argument("--glass-only", action="store_true", help="with --media-only: only the glass slab (2)")
    ap.add_argument("--before", type=Path, default=None, metavar="DIR",
                    help="also run this benchmark with the older tofhil in DIR, alternately, for a "
                         "before/after in one run (benchmarks/before_after.py)")
    ap.add_argument("--rounds", type=int, default=2, help="with --before: before/after pairs")
    args = ap.parse_args()
    if args.before is not None:
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        from before_after import run_alternating

        run_alternating(__file__, sys.argv[1:], args.before, args.rounds)
        return 0
    mi = load_mitsuba()
    if mi is None:
        return 0
    import drjit as dr

    dr.set_thread_count(args.threads)
    emitter = ISOTROPIC if args.emitter == "isotropic" else HEMISPHERE
    passes, spp = (4, 16) if args.quick else (8, 256)
    print(f"bench_vs_mitsuba: mitsuba {mi.__version__} ({mi.variant()}), {args.threads} threads, "
          f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores; {args.emitter} emitter, "
          f"{FREQ_HZ / 1e6:.0f} MHz, albedo {ALBEDO}")
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        if not args.only_timing:
            print("(1) agreement (same scene, independent passes; noise from each renderer's own variance)")
        for name, scene in () if args.only_timing or args.media_only else (("corner", corner_scene(emitter)),
                                                         ("tilted_plane", tilted_plane_scene(emitter))):
            geom = Tofhil(scene, 0, args.threads).geometry_radial_m()
            direct = (Tofhil(scene, 0, args.threads), Mitsuba(mi, scene, 0, "independent", work))
            for b in args.bounces if name == "corner" else args.bounces[:1]:   # a plane has no multipath
                tf = Tofhil(scene, b, args.threads)
                ms = Mitsuba(mi, scene, b, "independent", work)
                agreement(f"{name}_B{b}", tf, ms, geom, passes, spp, direct if b == args.bounces[0] else None,
                          args.figures if name == "corner" else None)
        sys.path.insert(0, str(Path(__file__).resolve().parent))     # glass_slab beside this script
        if not args.only_timing:
            glass_slab_check(mi, work, 16 if args.quick else 64)
            if not args.glass_only:
                scattering_cube_check(mi, work, passes, spp, [0] + [b for b in args.bounces if b > 0], args.threads,
                                      args.figures)
        if args.skip_timing or args.media_only:
            return 0
        b = args.bounces[0]
        from tofhil.sim import render as tofhil_render

        share = getattr(tofhil_render, "camera_ray_share", lambda n, nb: 1)
        corner_spps = args.spps or ([16, 64] if args.quick else [256, 1024])
        for name, scene, spps in (("corner", corner_scene(emitter), corner_spps),
                                  ("tilted plane", tilted_plane_scene(emitter), [4, 16, 64])):
            if name != "corner" and args.timing_corner_only:
                continue
            # Over the pixels seen whole (interior_pixels: the whole image on the corner).
            mask = interior_pixels(Tofhil(scene, 0, args.threads).geometry_radial_m())
            print(f"(3) CPU time to 1 mm RMS depth error, {name} 160x120, {b} bounces, {int(mask.sum())} pixels "
                  f"(tofhil: a camera ray per {share(spps[-1], b)} samples at {spps[-1]} spp)")
            res = [time_to_1mm(Tofhil(scene, b, args.threads), spps, mask)]
            if args.compare_wavefront:
                wf = time_to_1mm(Tofhil(scene, b, args.threads, wavefront=True), spps, mask)
                print(f"  fused loop / wavefront loop: CPU time to 1 mm {res[0]['cpu_1mm'] / wf['cpu_1mm']:.2f}x, "
                      f"cost per path sample {res[0]['ns_per_sample'] / wf['ns_per_sample']:.2f}x")
            for s in args.samplers:
                res.append(time_to_1mm(Mitsuba(mi, scene, b, s, work), spps, mask))
            best = min(res[1:], key=lambda r: r["cpu_1mm"])
            t = res[0]
            print(f"  {name}: tofhil / Mitsuba's best ({best['label']}): CPU time to 1 mm "
                  f"{t['cpu_1mm'] / best['cpu_1mm']:.2f}x (aim <= 0.33), cost per path sample "
                  f"{t['ns_per_sample'] / best['ns_per_sample']:.2f}x (aim <= 1)")
            if name != "corner":
                # 1 mm takes a few samples on the plane, where a render's fixed cost is the
                # time: also 0.1 mm (the same renders)
                t1 = time_to_1mm(Tofhil(scene, b, args.threads), spps, mask, 1e-4)
                m1 = [time_to_1mm(Mitsuba(mi, scene, b, s, work), spps, mask, 1e-4) for s in args.samplers]
                best = min(m1, key=lambda r: r["cpu_1mm"])
                print(f"  {name}: tofhil / Mitsuba's best ({best['label']}): CPU time to 0.1 mm "
                      f"{t1['cpu_1mm'] / best['cpu_1mm']:.2f}x")
    return 0


if __name__ == "__main__":
    t_wall, t_cpu = time.perf_counter(), time.process_time()
    rc = main()
    print(f"bench_vs_mitsuba: {time.process_time() - t_cpu:.0f} CPU-s, {time.perf_counter() - t_wall:.0f} s wall "
          f"(load average {os.getloadavg()[0]:.1f})")
    sys.exit(rc)
