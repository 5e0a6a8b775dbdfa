"""Stray-light corrections on lenses of other forms than the correction's model (issue 17).

    python benchmarks/straylight_lenses.py [--markdown out.md] [--lenses ghost_7px,field_lobe]

Every lens of ``tests/straylight_lenses.py`` (kernels written there, independent of
``sim/straylight/``) scatters the 80 x 60 dark-square scene, noise-free; printed is the
fraction of the dark-square error removed at 50 / 5 / 2 / 1 % reflectivity by:

- the Gaussian-dictionary PSF, ONE calibration on a card over black (the issue's baseline);
- the free-form PSF (fitted ghost centre, regularised), the same one card;
- the free-form PSF from the bench procedure: the card and a bright patch at four more
  field positions (shift-variant lobes fitted too);
- thesis method 1 (uniform subtraction) at its best w FOR EACH CASE;
- thesis method 2 (Gaussian inverse filter) at its best sigma and w FOR EACH CASE.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
from scipy.optimize import minimize_scalar  # noqa: E402

from tests import straylight_lenses as L  # noqa: E402
from tofhil.eval.corrections import psf_calibration as pc  # noqa: E402
from tofhil.eval.corrections import straylight as sl  # noqa: E402


def _best_uniform(s_meas: np.ndarray, s_true: np.ndarray) -> float:
    n = s_meas.shape[-1] * s_meas.shape[-2]
    r = minimize_scalar(lambda lw: L.square_error(sl.subtract_uniform(s_meas, 10 ** lw)[0], s_true[0]),
                        bounds=(np.log10(1e-4 / n), np.log10(0.5 / n)), method="bounded")
    return float(r.fun)


def _best_gaussian(s_meas: np.ndarray, s_true: np.ndarray) -> float:
    best = np.inf
    for sg in 2.0 * np.sqrt(2) ** np.arange(8):
        r = minimize_scalar(lambda w: L.square_error(sl.inverse_filter_gaussian(s_meas, sg, sg, w, 0.0)[0],
                                                     s_true[0]), bounds=(0.0, 0.5), method="bounded")
        best = min(best, float(r.fun))
    return best


def run(names: list[str], thesis: bool = True, log=print) -> list[dict]:
    rows = []
    for name in names:
        lens = L.lenses()[name]
        t0 = time.perf_counter()
        psfs = {
            "gaussian, card": pc.calibrate_psf_target(L.calibration_capture(lens), L.CX, L.CY),
            "free, card": pc.calibrate_psf_target(L.calibration_capture(lens), L.CX, L.CY,
                                                  **dict(pc.FREE_FORM, field=False)),
            "free, card + 4 patches": pc.calibrate_psf_target(L.patch_captures(lens), L.CX, L.CY, rounds=3,
                                                              **pc.FREE_FORM),
        }
        row = {"lens": name, "description": lens.description if hasattr(lens, "description") else lens.name,
               "removed": {}}
        for key, psf in psfs.items():
            row["removed"][key] = L.removed(lens, lambda s, p=psf: sl.deconvolve(s, p, center_px=(L.CX, L.CY)))
            row.setdefault("warnings", {})[key] = psf.info.get("warnings", [])
        if thesis:
            for key, best in (("thesis 1, best w per case", _best_uniform),
                              ("thesis 2, best sigma, w per case", _best_gaussian)):
                res = {}
                for rho, s_meas, s_true in L.cases(lens):
                    before = L.square_error(s_meas[0], s_true[0])
                    res[rho] = 1.0 - best(s_meas, s_true) / before
                row["removed"][key] = res
        rows.append(row)
        log(f"{name}: {time.perf_counter() - t0:.0f} s")
        log(table([row])[-1])
    return rows


def table(rows: list[dict]) -> list[str]:
    keys = list(rows[0]["removed"])
    refl = " / ".join(f"{100 * r:g}" for r in L.REFLECTANCES)
    lines = [f"| lens (% removed at {refl} % reflectivity) | " + " | ".join(keys) + " |",
             "|" + "---|" * (len(keys) + 1)]
    for r in rows:
        cells = [" / ".join(f"{100 * v:.1f}" for v in r["removed"][k].values()) for k in keys]
        lines.append(f"| {r['description']} | " + " | ".join(cells) + " |")
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--markdown", type=Path)
    ap.add_argument("--lenses", default=",".join(L.lenses()))
    ap.add_argument("--no-thesis", action="store_true")
    args = ap.parse_args(argv)
    rows = run(args.lenses.split(","), thesis=not args.no_thesis, log=lambda s: print(s, file=sys.stderr, flush=True))
    lines = table(rows)
    print("\n".join(lines))
    for r in rows:
        for k, w in r["warnings"].items():
            for x in w:
                print(f"  {r['lens']}, {k}: warning: {x}")
    if args.markdown:
        args.markdown.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
