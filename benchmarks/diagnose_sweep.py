"""Detection rate, false alarms and honesty of diagnosis over seeds.

For every effect of the library (the hidden-parameter draws of benchmarks/diagnose_cases.py)
render measured sessions with several seeds, and sessions with nothing hidden; diagnose them
against the base twin and print one line per run, then per form: how often the hidden effect
was named alone, how often the verdict was "explained", the share of the held-out excess over
noise removed (median), and the **reported gains that were losses**: a diagnosis that named a
cause while the held-out misfit, depth RMSE or amplitude RMSE got worse, or a channel worse
beyond its noise (must be 0). Null seeds give the false-alarm rate (any effect named).

    python benchmarks/diagnose_sweep.py [--seeds 5] [--null-seeds 20] [--effects offset,field_angle]
        [--forms offset_map,drift] [--scene bench_demo] [--width 80] [--null-frames 4]

``--forms`` adds hidden forms the library has no parametric effect for (tests/eval/hidden_forms.py,
applied to the light between render and sensor): ``offset_map`` random per-column (8 mm) and
per-pixel (6 mm) range offsets in a 32-frame session, expected as ``range_offset_map``;
``drift`` a range drift linear over 8 frames (8-15 mm first to last), expected as the per-frame
drift with no effect named; ``wiggling_h35`` a 3rd + 5th harmonic without the 7th (a partial
form: ``harmonics without h7``). The column "named or 'A or B'" also counts a run that named
one other family and gave the expected one as its alternative (the data cannot tell them apart). ``--effects none`` runs only the forms. A null seed counts as a
false alarm when any effect or the drift is named.

Hidden forms outside the library's simple forms (issue 10; the changes of
tests/eval/hidden_scalar_forms.py and tests/eval/hidden_forms.py):

    python benchmarks/diagnose_sweep.py --scene dark_square --effects none \
        --forms wiggling_h357,amplitude_tanh,cos_beam,log_amplitude

The same study as a sweep spec (one representative value per effect, parallel on Dask,
resumable, one table): ``tofhil sweep configs/sweeps/diagnose_effects.yaml --out DIR``.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from tofhil.eval.diagnose.run import diagnose
from tofhil.sim.pipeline import simulate_session
from tofhil.sim.scene import load_scene

from diagnose_cases import CASES  # benchmarks/ is on the path when this file runs as a script

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository root: tests/eval/hidden_forms.py
from tests.eval import hidden_forms as hf  # noqa: E402

from tests.eval import hidden_scalar_forms as hsf  # noqa: E402

#: Hidden forms outside the library's simple forms: name -> (draw(rng) -> session arguments,
#: expected outcome, the family that must be named (None: none, e.g. the drift)).
FORMS: dict[str, tuple[Callable[[np.random.Generator], dict[str, Any]], Callable[[Any], bool], str | None]] = {
    "offset_map": (lambda r: {"change": hf.column_row_offsets(r), "frames": 32},
                   lambda res: res.causes == ["range_offset_map"], "range_offset_map"),
    "drift": (lambda r: {"frame_change": hf.linear_drift(r), "frames": 8},
              lambda res: bool(res.drift and res.drift["named"]) and not res.causes, None),
    "wiggling_h357": (lambda r: {"change": hsf.odd_harmonics(r), "frames": 4},
                      lambda res: res.causes == ["wiggling"], "wiggling"),
    "wiggling_h35": (lambda r: {"change": hsf.odd_harmonics(r, orders=(3, 5)), "frames": 4},
                     lambda res: res.causes == ["wiggling"], "wiggling"),
    "amplitude_tanh": (lambda r: {"change": hsf.amplitude_sigmoid(r), "frames": 4},
                       lambda res: res.causes == ["amplitude_dependent"], "amplitude_dependent"),
    "cos_beam": (lambda r: {"change": hsf.cos_beam(r), "frames": 4},
                 lambda res: res.causes == ["illumination"], "illumination"),
    "log_amplitude": (lambda r: {"change": hf.log_amplitude_error(r), "frames": 4},
                      lambda res: res.causes == ["amplitude_dependent"], "amplitude_dependent"),
    # classes that act on one calibration channel (tests/eval/test_channel_classes.py, test_defects.py)
    "frequency_phase": (lambda r: {"change": hf.frequency_phase_offset(r), "frames": 6, "freq_hz": (44e6, 60e6)},
                        lambda res: res.causes == ["frequency_calibration"], "frequency_calibration"),
    "tap_gains": (lambda r: {"tap_change": hf.tap_gain_imbalance(r), "frames": 6},
                  lambda res: res.causes == ["tap_calibration"], "tap_calibration"),
    "warm_up": (lambda r: {"frame_change": hf.warm_up_drift(r), "frames": 6},
                lambda res: bool(res.drift and res.drift["named"]) and not res.causes, None),
    "radial_falloff": (lambda r: {"change": hf.radial_falloff(r), "frames": 6},
                       lambda res: res.causes == ["illumination"], "illumination"),
    "unmodulated": (lambda r: {"change": hf.unmodulated_offset(r, r.uniform(1.5, 3.0)), "frames": 6},
                    lambda res: res.causes == ["offset"], "offset"),
    "outside_panel": (lambda r: {"change": hf.outside_panel_multipath(r), "frames": 6},
                      lambda res: res.causes == ["unseen_reflector"], "unseen_reflector"),
    "outside_panel_2f": (lambda r: {"change": hf.outside_panel_multipath(r), "frames": 6, "freq_hz": (44e6, 60e6)},
                         lambda res: res.causes == ["unseen_reflector"], "unseen_reflector"),
    "stuck_pixels": (lambda r: {"tap_change": hf.stuck_pixels(r), "frames": 6},
                     lambda res: not res.causes and res.defects["pixels"] > 0, None),
    "hot_pixels": (lambda r: {"tap_change": hf.hot_pixels(r), "frames": 6},
                   lambda res: not res.causes and res.defects["pixels"] > 0, None),
}


def named_or_alternative(res, family: str | None) -> bool:
    """One cause named, and the expected family is it or an alternative the data cannot tell
    from it ("A or B", ``diagnosis.json`` ``alternatives``)."""
    if family is None or len(res.causes) != 1:
        return False
    alts = getattr(res, "alternatives", {}) or {}
    return family in {res.causes[0]} | {a["other"] for a in alts.get(res.causes[0], ())}


def false_alarm(res) -> bool:
    return bool(res.causes or (res.drift and res.drift["named"]))


def loss(res) -> bool:
    """A named cause whose held-out figures got worse: what diagnosis must never report."""
    if not res.causes:
        return False
    g, c = res.gain, res.chi2_per_value
    return bool(c["after_extended_scene"] > c["before"] or g["depth_rmse_m"]["after"] > g["depth_rmse_m"]["before"] * 1.02
                or g["amplitude_rmse"]["after"] > g["amplitude_rmse"]["before"] * 1.02
                or any(v["worse"] for v in res.channels.values()))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--null-seeds", type=int, default=20)
    ap.add_argument("--effects", default="", help="comma-separated subset of the library (default: all)")
    ap.add_argument("--scene", default="bench_demo")
    ap.add_argument("--width", type=int, default=80)
    ap.add_argument("--max-effects", type=int, default=2)
    ap.add_argument("--forms", default="", help="comma-separated hidden forms outside the library: "
                    + ", ".join(FORMS))
    ap.add_argument("--null-frames", type=int, default=4, help="frames of each null session")
    ap.add_argument("--null-freqs", default="", help="modulation frequency sets of the null sessions, e.g. "
                    "'44e6;44e6,60e6;40e6,60e6,100e6' (seeds cycle through them; default: the scene's)")
    args = ap.parse_args()
    names = [] if args.effects == "none" else [e for e in args.effects.split(",") if e] or list(CASES)
    forms = [f for f in args.forms.split(",") if f]
    for f in forms:
        if f not in FORMS:
            ap.error(f"unknown form {f!r}: one of {', '.join(FORMS)}")
    scene = load_scene(args.scene)
    scene = dataclasses.replace(scene, camera=scene.camera.scaled(args.width / scene.camera.width))
    print(f"{'hidden':20s} {'seed':>4s} {'named':28s} {'verdict':18s} {'removed':>7s} {'misfit before':>13s} "
          f"{'after':>7s} {'depth mm':>8s} {'after':>6s} {'loss':>4s} {'s':>5s}")
    rows: dict[str, list[tuple[bool, bool, float, bool, str, bool]]] = {}
    runs = ([(n, s) for n in names + forms for s in range(args.seeds)]
            + [("none", s) for s in range(args.null_seeds)])
    null_freqs = [tuple(float(x) for x in part.split(",")) for part in args.null_freqs.split(";") if part]
    with tempfile.TemporaryDirectory() as tmp:
        for name, seed in runs:
            rng = np.random.default_rng(1000 * seed + ((names + forms).index(name) + 1 if name != "none" else 0))
            path = Path(tmp) / f"{name}_{seed}.h5"
            case_scene = scene
            if name in FORMS:
                kw = FORMS[name][0](rng)
                if "freq_hz" in kw:
                    case_scene = hf.with_frequencies(scene, kw["freq_hz"])
                hf.write_session(case_scene, path, kw.get("change"), frames=kw["frames"],
                                 seed=int(rng.integers(10_000)), frame_change=kw.get("frame_change"),
                                 tap_change=kw.get("tap_change"))
            else:
                hidden = {} if name == "none" else {name: CASES[name](rng)}
                if name == "none" and null_freqs:
                    case_scene = hf.with_frequencies(scene, null_freqs[seed % len(null_freqs)])
                simulate_session(case_scene, path, frames=4 if name != "none" else args.null_frames,
                                 seed=int(rng.integers(10_000)), noise=True, effects=hidden)
            t0 = time.perf_counter()
            res = diagnose(path, case_scene, max_effects=args.max_effects)
            dt = time.perf_counter() - t0
            if name in FORMS:
                ok, family = FORMS[name][1](res), FORMS[name][2]
            else:
                ok, family = (not false_alarm(res) if name == "none" else res.causes == [name]), name
            v = res.verdict
            removed = float("nan") if v.excess_removed is None else v.excess_removed
            lost = loss(res)
            form = (res.forms.get(family, "") or "simple") if ok and family and name != "none" else "-"
            either = ok or (name != "none" and named_or_alternative(res, family))
            rows.setdefault(name, []).append((ok, v.kind == "explained", removed, lost, form, either))
            pct = "-" if not np.isfinite(removed) else f"{100 * removed:.0f}%"
            alts = getattr(res, "alternatives", {}) or {}
            named = "+".join([c + (f"({res.forms[c]})" if res.forms.get(c) else "")
                              + "".join(f" or {a['other']}" for a in alts.get(c, ())) for c in res.causes]
                             + (["drift"] if res.drift and res.drift["named"] else [])) or "-"
            print(f"{name:20s} {seed:4d} {named:28s} {v.kind:18s} {pct:>7s} "
                  f"{res.chi2_per_value['before']:13.2f} {res.chi2_per_value['after_extended_scene']:7.2f} "
                  f"{res.gain['depth_rmse_m']['before'] * 1e3:8.1f} {res.gain['depth_rmse_m']['after'] * 1e3:6.1f} "
                  f"{'LOSS' if lost else '-':>4s} {dt:5.1f}", flush=True)
    print("\n| hidden form | seeds | named alone (as its family) | named or 'A or B' | form fitted | explained "
          "| excess removed (median) | gains that were losses |")
    print("|---|---|---|---|---|---|---|---|")
    for name, r in rows.items():
        med = np.nanmedian([x[2] for x in r]) if any(np.isfinite(x[2]) for x in r) else float("nan")
        label = ("nothing (false alarms: any effect named)" if name == "none"
                 else f"{name} -> {FORMS[name][2] or ('defects' if 'pixels' in name else 'drift')}"
                 if name in forms else name)
        named = sum(x[0] for x in r) if name != "none" else len(r) - sum(x[0] for x in r)
        kinds = sorted({x[4] for x in r if x[4] != "-"})
        fitted = ", ".join(f"{k} {sum(x[4] == k for x in r)}" for k in kinds) or "-"
        either = f"{sum(x[5] for x in r)}/{len(r)}" if name != "none" else "-"
        print(f"| {label} | {len(r)} | {named}/{len(r)} | {either} | {fitted} | {sum(x[1] for x in r)}/{len(r)} | "
              f"{'-' if not np.isfinite(med) else f'{100 * med:.0f} %'} | {sum(x[3] for x in r)} |")
    total_losses = sum(x[3] for r in rows.values() for x in r)
    print(f"\nreported gains that were losses: {total_losses} (must be 0)")


if __name__ == "__main__":
    main()
