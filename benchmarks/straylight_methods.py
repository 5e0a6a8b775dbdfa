"""Stray-light corrections side by side on the twin's dark-square cases.

    /work/venv/bin/python benchmarks/straylight_methods.py [--markdown docs/straylight_table.md] [--json out.json]

For each square reflectance (50 % .. 1 % of the wall) of the bundled ``dark_square_card``
scene rendered with a stray-light PSF, prints the stray-light depth error in the dark
square before correction (the baseline, measured in the same run) and the fraction of it
each method removes:

- calibrated PSF, ONE calibration on ``wall_card`` with its stray-light-free twin;
- calibrated PSF, ONE calibration on a card in front of a black wall (no twin needed);
- the same twin calibration without the tap (fixed-pattern) calibration;
- thesis method 1 (uniform subtraction) at its best w FOR EACH CASE;
- thesis method 2 (Gaussian inverse filter) at its best sigma and w FOR EACH CASE;
- thesis method 1 with the one w that is best on average over all cases.

The cases as a sweep spec (measurement against the stray-light-free twin, on Dask, one
table): ``tofhil sweep configs/sweeps/straylight_reflectance.yaml --out DIR``.

``--lens-forms``: the full table for every lens form of ``tests/straylight_lenses.py``
(other Gaussians + veil + ghost, power-law tail, ghosts 1-10 px off the principal point,
magnified ghosts, a field-dependent lobe): the Gaussian-form and free-form calibrations
beside the thesis methods at their best per case (``straylight_lenses.py``).
``--noisy-cli OUT``: every lens form with noisy captures (30 frames), calibrated by the
bench procedure and corrected and compared through the CLI against each region's noise
floor (``straylight_noisy_cli.py --lens all --bench``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path


def _table(r: dict) -> list[str]:
    head = ("| square / wall | error before (mm) | PSF, twin cal. | PSF, card-on-black cal. | "
            "PSF, twin cal., no tap cal. | thesis 1, best w per case | thesis 2, best sigma, w per case | "
            "thesis 1, one w for all |")
    lines = [head, "|" + "---|" * 8]
    single = r.get("uniform_single_w", {}).get("removed", [None] * len(r["cases"]))
    for c, s1 in zip(r["cases"], single):
        def pct(key: str) -> str:
            v = c.get(key)
            return "–" if v is None else f"{100 * v['removed']:.1f} %"
        u, g = c.get("uniform_best"), c.get("gaussian_best")
        lines.append(
            f"| {100 * c['square_reflectance']:g} % | {1000 * c['error_before_m']:.1f} | {pct('psf_reference')} | "
            f"{pct('psf_target')} | {pct('psf_reference_without_tap_calibration')} | "
            + (f"{100 * u['removed']:.1f} % (w={u['w']:.3g}) | " if u else "– | ")
            + (f"{100 * g['removed']:.1f} % (sigma={g['sigma_px']:g} px, w={g['w']:.3f}) | " if g else "– | ")
            + (f"{100 * s1:.1f} % |" if s1 is not None else "– |"))
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--markdown", type=Path, help="also write the table (Markdown) here")
    ap.add_argument("--json", type=Path, help="also write all numbers (JSON) here")
    ap.add_argument("--quick", action="store_true", help="three reflectances, no thesis search")
    ap.add_argument("--noise", type=int, default=0, metavar="N",
                    help="noisy captures, each the mean of N frames (references stay the noise-free twin)")
    ap.add_argument("--bundled-sensor", action="store_true",
                    help="keep the scenes' sensor as bundled (no ADC pedestal: dark taps clip at 0 DN)")
    ap.add_argument("--lens-forms", action="store_true",
                    help="instead: every lens form of tests/straylight_lenses.py (benchmarks/straylight_lenses.py)")
    ap.add_argument("--noisy-cli", type=Path, metavar="OUT",
                    help="instead: 30 noisy frames through the CLI against the noise floor "
                         "(benchmarks/straylight_noisy_cli.py, its sessions and reports in OUT)")
    args = ap.parse_args(argv)
    if args.noisy_cli:
        import straylight_noisy_cli  # beside this script

        return straylight_noisy_cli.main([str(args.noisy_cli), "--lens", "all", "--bench"])
    if args.lens_forms:
        import straylight_lenses  # beside this script

        return straylight_lenses.main(["--markdown", str(args.markdown)] if args.markdown else [])

    import straylight_study as st  # the study beside this script (benchmarks/)

    t0 = time.perf_counter()
    refl = (0.5, 0.05, 0.01) if args.quick else st.REFLECTANCES
    r = st.run_study(refl, thesis=not args.quick, sensor=None if args.bundled_sensor else st.STUDY_SENSOR,
                     noise=args.noise > 0, frames=max(args.noise, 1), log=lambda s: print(f"[{time.perf_counter() - t0:6.1f} s] {s}",
                                                                       file=sys.stderr))
    r["seconds"] = time.perf_counter() - t0
    lines = _table(r)
    print(f"stray-light PSF of the study: {json.dumps(r['psf'])}; sensor overrides {r['sensor_overrides']}; "
          + (f"noisy captures, mean of {r['frames']} frames" if r["noise"] else "noise-free"))
    print("fraction of the stray-light depth error in the dark square removed (baseline: the error before "
          "correction, same run):")
    print("\n".join(lines))
    if "uniform_single_w" in r:
        print(f"thesis method 1 with one w for all cases: w = {r['uniform_single_w']['w']:.3g}")
    print(f"({r['seconds']:.0f} s)")
    if args.markdown:
        args.markdown.write_text("\n".join(lines) + "\n", encoding="utf-8")
    if args.json:
        args.json.write_text(json.dumps(r, indent=2, default=float), encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
