"""Stray-light correction of noisy captures through the CLI, against the noise floor (issue 17).

    python benchmarks/straylight_noisy_cli.py OUT_DIR [--lens gauss_other] [--noise 0.002] [--frames 30]
                                              [--psf-form gaussian] [--cal-noise 0]

A lens of ``tests/straylight_lenses.py`` (kernels written there, independent of the model)
scatters the 80 x 60 dark-square scene; every capture has ``--frames`` frames with Gaussian
tap noise ``--noise`` (offset 50). The PSF is calibrated through the CLI on a card over
black (``tofhil correct --method psf --calibrate``; ``--cal-noise`` > 0: the calibration
capture is noisy too, 30 frames); each reflectance is then compared through the CLI
(``tofhil compare A B --frames N --correct psf:psf=lens.json --roi SQUARE``), which averages
the taps before demodulation and reports each region's noise floor. Printed per
reflectance: the square's depth RMSE before and after, the noise floor after, the fraction
removed, the fraction the noise floor allows (``1 - floor / before``) and their ratio (the
issue's aim: >= 90 %).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tests import straylight_lenses as L  # noqa: E402
from tests.straylight_synthetic import SQUARE, scene_signal, write_session  # noqa: E402
from tofhil.cli import main as cli  # noqa: E402


def run(*args: object) -> int:
    try:
        cli([str(a) for a in args])
    except SystemExit as exc:
        return int(exc.code or 0)
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--lens", default="gauss_other", choices=list(L.lenses()))
    ap.add_argument("--noise", type=float, default=0.002, help="tap noise (the wall's amplitude is 0.25)")
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--psf-form", default="gaussian", choices=("gaussian", "free"))
    ap.add_argument("--cal-noise", type=float, default=0.0)
    args = ap.parse_args(argv)
    d = args.out
    d.mkdir(parents=True, exist_ok=True)
    lens = L.lenses()[args.lens]
    cal = write_session(d / "cal.h5", L.calibration_capture(lens)[0], n_frames=30 if args.cal_noise else 1,
                        noise=args.cal_noise, offset=50.0, seed=7)
    t0 = time.perf_counter()
    if run("correct", cal, "--method", "psf", "--calibrate", cal, "--psf-form", args.psf_form,
           "--save-psf", d / "lens.json", "--out", d / "cal_corrected.h5", "--force") != 0:
        return 1
    roi = f"{SQUARE[1].start},{SQUARE[0].start},{SQUARE[1].stop},{SQUARE[0].stop}"
    region = "roi_" + roi.replace(",", "_")
    rows = []
    for rho in L.REFLECTANCES:
        s, _ = scene_signal(square_rho=rho, card=True, wall=True)
        a = write_session(d / f"a{rho:g}.h5", lens(s), n_frames=args.frames, noise=args.noise, offset=50.0, seed=1)
        b = write_session(d / f"b{rho:g}.h5", s, n_frames=1, offset=50.0)
        if run("compare", a, b, "--out", d / f"r{rho:g}", "--frames", args.frames, "--roi", roi, "--no-objects",
               "--min-relative-amplitude", 0, "--correct", f"psf:psf={d / 'lens.json'}", "--force") != 0:
            return 1
        m = json.loads((d / f"r{rho:g}" / "metrics.json").read_text())
        v0 = m["variants"]["measured"]["regions"][region]
        v1 = [v for k, v in m["variants"].items() if k != "measured"][0]["regions"][region]
        e0, e1, floor = v0["depth_residual_m"]["rmse"], v1["depth_residual_m"]["rmse"], v1["noise_floor_m"]
        rows.append((rho, e0, e1, floor, 1 - e1 / e0, 1 - floor / e0))
    print(f"lens {args.lens} ({lens.name}); {args.frames} frames, tap noise {args.noise}; PSF {args.psf_form}, "
          f"calibration {'noisy' if args.cal_noise else 'noise-free'}; {time.perf_counter() - t0:.0f} s")
    print("| square / wall | RMSE before (mm) | RMSE after (mm) | noise floor after (mm) | removed | allowed by the "
          "noise floor | removed / allowed |")
    print("|---|---|---|---|---|---|---|")
    for rho, e0, e1, floor, got, allowed in rows:
        print(f"| {100 * rho:g} % | {1e3 * e0:.1f} | {1e3 * e1:.1f} | {1e3 * floor:.1f} | {100 * got:.1f} % | "
              f"{100 * allowed:.1f} % | {100 * got / allowed:.1f} % |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
