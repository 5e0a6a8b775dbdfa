"""Stray-light correction of noisy captures through the CLI, against the noise floor (issue 17).

    python benchmarks/straylight_noisy_cli.py OUT_DIR [--lens gauss_other|all] [--noise 0.002] [--frames 30]
                                              [--psf-form gaussian] [--cal-noise 0] [--bench]

A lens of ``tests/straylight_lenses.py`` (kernels written there, independent of the model)
scatters the 80 x 60 dark-square scene; every capture has ``--frames`` frames with Gaussian
tap noise ``--noise`` (offset 50). The PSF is calibrated through the CLI on a card over
black (``tofhil correct --method psf --calibrate``; ``--cal-noise`` > 0: the calibration
capture is noisy too, 30 frames); each reflectance is then compared through the CLI
(``tofhil compare A B --frames N --correct psf:psf=lens.json --roi SQUARE``), which averages
the taps before demodulation and reports each region's noise floor. ``--bench``: the
documented bench procedure instead of the one card: the card and a bright patch at four
more field positions (five sessions, ``--calibrate`` five times, ``--psf-form free``).
``--lens all``: every lens form, one summary row each. Printed per
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


def run_lens(name: str, d: Path, args: argparse.Namespace) -> list[tuple[float, ...]]:
    """Calibrate through the CLI, then compare every reflectance; rows of (rho, RMSE before,
    after, noise floor after, removed, allowed by the floor)."""
    d.mkdir(parents=True, exist_ok=True)
    lens = L.lenses()[name]
    caps = [c[0] for c in L.patch_captures(lens)] if args.bench else [L.calibration_capture(lens)[0]]
    cals = [write_session(d / f"cal{i}.h5", c, n_frames=30 if args.cal_noise else 1, noise=args.cal_noise,
                          offset=50.0, seed=7 + i) for i, c in enumerate(caps)]
    calib = [x for c in cals for x in ("--calibrate", c)]
    if run("correct", cals[0], "--method", "psf", *calib, "--psf-form", "free" if args.bench else args.psf_form,
           "--save-psf", d / "lens.json", "--out", d / "cal_corrected.h5", "--force") != 0:
        raise SystemExit(1)
    roi = f"{SQUARE[1].start},{SQUARE[0].start},{SQUARE[1].stop},{SQUARE[0].stop}"
    region = "roi_" + roi.replace(",", "_")
    rows = []
    for rho in L.REFLECTANCES:
        s, _ = scene_signal(square_rho=rho, card=True, wall=True)
        a = write_session(d / f"a{rho:g}.h5", lens(s), n_frames=args.frames, noise=args.noise, offset=50.0, seed=1)
        b = write_session(d / f"b{rho:g}.h5", s, n_frames=1, offset=50.0)
        if run("compare", a, b, "--out", d / f"r{rho:g}", "--frames", args.frames, "--roi", roi, "--no-objects",
               "--min-relative-amplitude", 0, "--correct", f"psf:psf={d / 'lens.json'}", "--force") != 0:
            raise SystemExit(1)
        m = json.loads((d / f"r{rho:g}" / "metrics.json").read_text())
        v0 = m["variants"]["measured"]["regions"][region]
        v1 = [v for k, v in m["variants"].items() if k != "measured"][0]["regions"][region]
        e0, e1, floor = v0["depth_residual_m"]["rmse"], v1["depth_residual_m"]["rmse"], v1["noise_floor_m"]
        rows.append((rho, e0, e1, floor, 1 - e1 / e0, 1 - floor / e0))
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--lens", default="gauss_other", choices=list(L.lenses()) + ["all"])
    ap.add_argument("--noise", type=float, default=0.002, help="tap noise (the wall's amplitude is 0.25)")
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--psf-form", default="gaussian", choices=("gaussian", "free"))
    ap.add_argument("--cal-noise", type=float, default=0.0)
    ap.add_argument("--bench", action="store_true", help="calibrate by the bench procedure (card + 4 patches, free)")
    args = ap.parse_args(argv)
    form = "free, card + 4 patches" if args.bench else args.psf_form
    cal = "noisy" if args.cal_noise else "noise-free"
    if args.lens == "all":
        print(f"{args.frames} frames, tap noise {args.noise}; PSF {form}, calibration {cal}; % of the dark-square "
              "RMSE removed / allowed by the noise floor / removed over allowed, at "
              + " / ".join(f"{100 * r:g}" for r in L.REFLECTANCES) + " %")
        print("| lens | removed | allowed by the noise floor | removed / allowed |")
        print("|---|---|---|---|")
        for name in L.lenses():
            t0 = time.perf_counter()
            rows = run_lens(name, args.out / name, args)
            cells = [" / ".join(f"{100 * v:.1f}" for v in vals) for vals in
                     ([r[4] for r in rows], [r[5] for r in rows], [r[4] / r[5] for r in rows])]
            print(f"| {L.lenses()[name].name} | " + " | ".join(cells) + " |", flush=True)
            print(f"  ({name}: {time.perf_counter() - t0:.0f} s)", file=sys.stderr, flush=True)
        return 0
    t0 = time.perf_counter()
    rows = run_lens(args.lens, args.out, args)
    lens = L.lenses()[args.lens]
    print(f"lens {args.lens} ({lens.name}); {args.frames} frames, tap noise {args.noise}; PSF {form}, "
          f"calibration {cal}; {time.perf_counter() - t0:.0f} s")
    print("| square / wall | RMSE before (mm) | RMSE after (mm) | noise floor after (mm) | removed | allowed by the "
          "noise floor | removed / allowed |")
    print("|---|---|---|---|---|---|---|")
    for rho, e0, e1, floor, got, allowed in rows:
        print(f"| {100 * rho:g} % | {1e3 * e0:.1f} | {1e3 * e1:.1f} | {1e3 * floor:.1f} | {100 * got:.1f} % | "
              f"{100 * allowed:.1f} % | {100 * got / allowed:.1f} % |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
