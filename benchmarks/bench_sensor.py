"""Sensor-side benchmark of the twin: stray light, sensor exposure, and forward() on a cached render.

Each figure is printed with its ratio to a baseline measured in the same run (these machines
are shared and noisy: compare ratios, not seconds):

(a) stray-light operator on a complex [F=2, NH=2, 120, 160] signal with a [239, 319] kernel
    against scipy.signal.fftconvolve (full linear convolution, then cropped) of the same data;
(b) one noisy sensor exposure (Poisson + read noise + ADC) of a 160 x 120, 4-tap frame against
    the core's plain taps_from_signal of the same size (the noise-free cosine model);
(c) forward() on a cached render of the bundled dark_square_card scene with stray light,
    wiggling and a fixed pattern, against rendering that scene once, direct light at 1 sample
    per pixel and with multipath (what a fit saves per evaluation by not re-rendering).

    python benchmarks/bench_sensor.py [--repeats N]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from scipy.signal import fftconvolve

from tofhil.camera import load_camera_preset
from tofhil.demod import taps_from_signal
from tofhil.sim.sensor import OpticalSignal, SensorConfig, SensorModel
from tofhil.sim.straylight import GaussianLobe, StrayLightOperator, StrayLightPSF, psf_kernel


def timed(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=20)
    args = ap.parse_args()
    r = args.repeats
    cam = load_camera_preset("holmlund_thesis")
    h, w = cam.shape
    rng = np.random.default_rng(0)

    # (a) stray light
    s = rng.normal(size=(2, 2, h, w)) + 1j * rng.normal(size=(2, 2, h, w))
    psf = StrayLightPSF(gaussians=(GaussianLobe(0.02, 40, 40),), veil=0.01)
    op = StrayLightOperator(psf, (h, w))
    k = psf_kernel(psf, (h, w))
    ours = timed(lambda: op.apply(s), r)
    base = timed(lambda: fftconvolve(s, k[None, None], mode="full", axes=(-2, -1))[..., h - 1:2 * h - 1,
                                                                                    w - 1:2 * w - 1], r)
    build = timed(lambda: StrayLightOperator(psf, (h, w)).apply(s), r)
    print(f"(a) stray light [2,2,{h},{w}]: {ours * 1e3:.2f} ms (operator reused), {build * 1e3:.2f} ms "
          f"(built each call); scipy fftconvolve {base * 1e3:.2f} ms; ratio ours/baseline {ours / base:.2f}")

    # (b) sensor exposure
    cfg = SensorConfig.from_dict({}, camera=cam)
    d = rng.uniform(0.5, 3.0, (h, w))
    p = rng.uniform(1e-12, 1e-11, (h, w))
    sig = OpticalSignal(freq_hz=[44e6], harmonics=(1,), phasor_w=(p * np.exp(1j * 4 * np.pi * 44e6 * d / 3e8))[None, None],
                        dc_w=p, ambient_w=np.zeros((h, w)))
    sensor = SensorModel(cfg, cam)
    ex = timed(lambda: sensor.expose(sig, seed=1), r)
    phi = np.angle(sig.phasor_w[0, 0])
    plain = timed(lambda: taps_from_signal(np.abs(sig.phasor_w[0, 0]), phi, p, np.asarray(cfg.theta_rad)), r)
    print(f"(b) noisy exposure {w}x{h}x4 taps: {ex * 1e3:.2f} ms ({1 / ex:.0f} frames/s); "
          f"plain cosine model {plain * 1e3:.2f} ms; ratio {ex / plain:.1f}")

    # (c) forward on a cached render vs a render
    from tofhil.sim.pipeline import forward, prepare_render
    from tofhil.sim.render import render
    from tofhil.sim.scene import load_scene

    scene = load_scene("dark_square_card")
    _, rr = prepare_render(scene, {})
    eff = {"stray_light": {"weight": 0.02, "sigma_px": 40, "veil": 0.01}, "wiggling": {"h3_amplitude": 0.05},
           "fixed_pattern": {"random_delay_s": 5e-12}}
    fw = timed(lambda: forward(scene, rr, eff, noise=False), r)
    rd = timed(lambda: render(scene), max(3, r // 4))
    mp = timed(lambda: render(scene, bounces=2, samples_per_pixel=4, separate_direct=True), 1)
    print(f"(c) forward() with 3 effects on a cached 160x120 render: {fw * 1e3:.1f} ms; one direct-light "
          f"render (1 spp) {rd * 1e3:.1f} ms, ratio {fw / rd:.2f}; one multipath render (2 bounces, 4 spp) "
          f"{mp:.2f} s, ratio {fw / mp:.3f}")


if __name__ == "__main__":
    main()
