"""Every stray-light correction on the thesis's dark-square series, before and after, per region.

    python benchmarks/corrections_table.py [--frames N] [--markdown docs/corrections_table.md] [--json OUT]
                                           [--saturate] [--quick]

For each square reflectance (50 % .. 1 % of the wall) of the bundled ``dark_square_card``
scene, a capture is simulated with the stray light hidden (a Gaussian lobe, weight 0.03,
sigma 12 px, and a veil of 0.005, as the demo's emulator; ``N`` noisy frames) and compared
(``tofhil.eval.compare.compare_sessions``, the CLI's code) with the stray-light-free twin
(noise-free), as measured and after each correction, scored like the diagnosis (compare's
held-out split: whatever is fitted, on the even frames; before and after, the mean of the odd
ones):

- ``twin``: the twin correction, given the twin with the stray light (the fitted twin);
- ``psf``: PSF deconvolution with the same PSF (the diagnosed one); ``psf+twin``: the same
  with the clipped source pixels' light restored from the twin (``twin=SCENE``);
- ``uniform``: the thesis's subtraction with the PSF's uniform part, ``w`` = veil / pixels
  (what a uniform model of this lens can know);
- ``gaussian-inverse``: the thesis's inverse filter with the PSF's Gaussian lobe (its
  sigma and weight; the veil is not in its form).

Per region (wall, square, the card's neighbourhood), the residual's median against the
twin before -> after, and "worse" where compare marks the region made worse beyond its
noise (with the reason). ``--saturate``: a longer integration so that the card clips
(the PSF and thesis methods then meet clipped sources; the twin restores them). No number
here is a target: everything is measured in the run.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

REFLECTANCES = (0.5, 0.2, 0.1, 0.05, 0.02, 0.01)
PSF = {"weight": 0.03, "sigma_px": 12.0, "veil": 0.005}
REGIONS = ("wall", "square", "near clipped (15 px)", "card")


def _session(path: Path, twin, frames: int, noise: bool, scene_text: str) -> None:
    from tofhil.session import SessionWriter

    frames_iter = twin.frames(frames=frames, seed=11, noise=noise)
    with SessionWriter(path, twin.scene.camera, device={"model": "tofhil-sim"}, scene_text=scene_text,
                       sensor_config=twin.config.to_dict()) as w:
        for f in frames_iter:
            w.append(f)


def case(rho: float, out: Path, frames: int, saturate: bool) -> dict:
    from tofhil.eval.compare import compare_sessions
    from tofhil.sim.scene import load_scene, scene_to_yaml
    from tofhil.sim.straylight import StrayLightPSF
    from tofhil.sim.twin import Twin

    over = {"params": {"square_reflectance": rho}}
    if saturate:
        over["sensor"] = {"integration_time_s": 1.2e-3}
    truth = load_scene("dark_square_card", {**over, "effects": {"stray_light": PSF}})
    base = load_scene("dark_square_card", over)
    d = out / f"rho_{rho:g}"
    d.mkdir(parents=True, exist_ok=True)
    ext = d / "extended_scene.yaml"
    ext.write_text(scene_to_yaml(truth), encoding="utf-8")
    psf_file = StrayLightPSF.from_params(PSF).save(d / "psf.json", force=True)
    _session(d / "capture.h5", Twin(truth), frames, True, scene_to_yaml(base))
    _session(d / "twin.h5", Twin(base), 1, False, scene_to_yaml(base))
    h, w = truth.camera.shape
    methods = {"twin": f"twin:scene={ext}", "psf": f"psf:psf={psf_file}", "psf+twin": f"psf:psf={psf_file},twin={ext}",
               "uniform": f"uniform:w={PSF['veil'] / (h * w):.6g}",
               "gaussian-inverse": f"gaussian-inverse:sigma_h={PSF['sigma_px']},sigma_v={PSF['sigma_px']},"
                                   f"w={PSF['weight']}"}
    m = compare_sessions(d / "capture.h5", d / "twin.h5", d / "compare", corrections=list(methods.values()),
                         max_frames=frames, force=True)
    res = {"square_reflectance": rho, "regions": {}, "methods": {}, "heldout": m.get("heldout")}
    meas = m["variants"]["measured"]["regions"]
    for r in REGIONS:
        if r in meas:
            dr = meas[r]["depth_residual_m"]
            res["regions"][r] = {"median_m": dr["median"], "noise_floor_m": meas[r].get("noise_floor_m"),
                                 "saturated_fraction": meas[r]["saturated_fraction_a"]}
    for name, spec in methods.items():
        v = m["variants"][spec]
        res["methods"][name] = {"spec": spec, "correction": v.get("correction"),
                                "regions": {r: ch for r, ch in v["before_after"].items() if r in REGIONS}}
    return res


def _cell(ch: dict | None) -> str:
    if ch is None or ch.get("median_after_m") is None:
        return "–"
    s = f"{1e3 * ch['median_after_m']:.1f}"
    return s + (" **worse**" if ch["worse"] else "")


def table(results: list[dict]) -> list[str]:
    """One row per reflectance and region: the median before and after each method (mm)."""
    names = list(results[0]["methods"])
    lines = ["| square / wall | region | before (mm) | noise of the median (mm) | "
             + " | ".join(f"{n} (mm)" for n in names) + " |",
             "|" + "---|" * (4 + len(names))]
    for r in results:
        for region, before in r["regions"].items():
            if before["median_m"] is None:
                continue
            chs = [r["methods"][n]["regions"].get(region) for n in names]
            noise = next((c["median_noise_m"] for c in chs if c and c.get("median_noise_m") is not None), None)
            lines.append(f"| {100 * r['square_reflectance']:g} % | {region} | {1e3 * before['median_m']:.1f} | "
                         f"{'–' if noise is None else format(1e3 * noise, '.1f')} | "
                         + " | ".join(_cell(c) for c in chs) + " |")
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=4, help="noisy frames per capture (averaged in compare)")
    ap.add_argument("--markdown", type=Path, help="also write the table (Markdown) here")
    ap.add_argument("--json", type=Path, help="also write all numbers (JSON) here")
    ap.add_argument("--saturate", action="store_true", help="an integration time at which the card clips")
    ap.add_argument("--quick", action="store_true", help="three reflectances")
    ap.add_argument("--keep", type=Path, help="keep the sessions and reports here (default a temporary directory)")
    args = ap.parse_args(argv)
    rhos = (0.5, 0.05, 0.01) if args.quick else REFLECTANCES
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        out = args.keep or Path(tmp)
        results = [case(rho, out, args.frames, args.saturate) for rho in rhos]
    lines = table(results)
    worse = [(r["square_reflectance"], n, reg, ch["reason"]) for r in results for n, v in r["methods"].items()
             for reg, ch in v["regions"].items() if ch["worse"]]
    print("\n".join(lines))
    print(f"\n{len(worse)} region(s) made worse beyond their noise (each marked in metrics.json and the report):")
    for rho, n, reg, why in worse:
        print(f"  {100 * rho:g} %: {n} makes {reg} worse: {why or 'reason not known'}")
    held = results[0].get("heldout")
    if held:  # the same split for every case: the frames the figures are scored on
        print(f"scored {'in-sample' if held['in_sample'] else 'on held-out frames'}: {held['text']}")
    print(f"({len(results)} cases, {args.frames} frames each{', card clipping' if args.saturate else ''}; "
          f"{time.perf_counter() - t0:.0f} s)")
    if args.markdown:
        args.markdown.write_text("\n".join(lines) + "\n", encoding="utf-8")
    if args.json:
        args.json.write_text(json.dumps(results, indent=1, default=float), encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
