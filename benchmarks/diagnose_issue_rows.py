"""Issue 32's table, row by row and over seeds: each plain thing a real camera does, hidden in a
160 x 120, 6-frame session of ``dark_square`` (raw taps, the sensor's noise and ADC), and what
``diagnose`` says. A row is right when its family is named (or said as one reading of an "A or
B") and the verdict is not "the scene does not match".

    python benchmarks/diagnose_issue_rows.py [--seeds 3] [--width 160] [--frames 6] [--only ROW]

The hidden changes are written here and in ``tests/eval/hidden_forms.py``, not with the effect
library's code.
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

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from tests.eval import hidden_forms as hf  # noqa: E402


def _gain(factor: float) -> Callable:
    """Every signal times ``factor`` (an exposure or integration-time mismatch): the emitter's
    light and the ambient alike, so the offset above the black level scales too."""
    def change(signal: Any, sensor: Any) -> Any:
        out = signal.copy()
        out.phasor_w = signal.phasor_w * factor
        out.dc_w = np.asarray(signal.dc_w) * factor
        out.ambient_w = np.asarray(signal.ambient_w) * factor
        return out
    return change


def _contrast(index: int, factor: float) -> Callable:
    """One modulation frequency's modulation contrast ``factor`` of the twin's (its phasor only)."""
    def change(signal: Any, sensor: Any) -> Any:
        out = signal.copy()
        out.phasor_w = np.array(signal.phasor_w)
        out.phasor_w[index] = signal.phasor_w[index] * factor
        return out
    return change


def _scene(width: int, freqs: tuple[float, ...] | None = None, taps: int | None = None) -> Any:
    scene = hf.small_dark_square(width)
    if freqs:
        scene = hf.with_frequencies(scene, freqs)
    if taps:
        sensor = dataclasses.replace(scene.sensor, theta_rad=tuple(2 * np.pi * k / taps for k in range(taps)))
        scene = dataclasses.replace(scene, sensor=sensor)
    return scene


def _emitter_further(dz: float) -> Callable:
    """The scene's emitter ``dz`` further from the lens than the twin's scene says."""
    def scene_of(scene: Any) -> Any:
        e = scene.emitter
        return dataclasses.replace(scene, emitter=dataclasses.replace(
            e, offset_m=tuple(np.asarray(e.offset_m, dtype=float) + np.array([0.0, 0.0, -dz]))))
    return scene_of


#: row -> (the families that are right, how to make the session: rng -> (scene, kwargs of write_session)).
ROWS: dict[str, tuple[set[str], Callable]] = {
    "gain 0.8": ({"reflectance", "illumination"}, lambda r, w: (_scene(w), {"change": _gain(0.8)})),
    "unmodulated offset": ({"offset", "ambient"},
                           lambda r, w: (_scene(w), {"change": hf.unmodulated_offset(r, r.uniform(1.5, 3.0))})),
    "60 MHz contrast -15 %": ({"frequency_calibration"},
                              lambda r, w: (_scene(w, (44e6, 60e6)), {"change": _contrast(1, 0.85)})),
    "emitter 4 cm further": ({"emitter_position"}, lambda r, w: (_scene(w), {"scene_of": _emitter_further(0.04)})),
    "2nd harmonic, 3 taps": ({"wiggling"}, lambda r, w: (_scene(w, taps=3), {"waveform": (2, r.uniform(0.03, 0.06),
                                                                                        r.uniform(-3, 3))})),
    "warm-up drift": ({"drift"}, lambda r, w: (_scene(w), {"frame_change": hf.warm_up_drift(r)})),
    "radial falloff": ({"illumination"}, lambda r, w: (_scene(w), {"change": hf.radial_falloff(r)})),
}


def run_row(row: str, seed: int, width: int, frames: int, tmp: Path) -> dict:
    from tofhil.eval.diagnose.run import diagnose

    right_families, make = ROWS[row]
    rng = np.random.default_rng(1000 * seed + list(ROWS).index(row))
    scene, kw = make(rng, width)
    truth_scene = scene
    if "scene_of" in kw:
        truth_scene = kw.pop("scene_of")(scene)
    if "waveform" in kw:
        h, a, psi = kw.pop("waveform")  # a harmonic of the emitter's waveform the twin's scene lacks
        e = truth_scene.emitter
        truth_scene = dataclasses.replace(truth_scene, emitter=dataclasses.replace(
            e, harmonics=tuple(e.harmonics) + ((h, a, psi),)))
    path = hf.write_session(truth_scene, tmp / f"{row.replace(' ', '_')}_{seed}.h5", kw.pop("change", None),
                            frames=frames, seed=seed, **kw)
    t0 = time.perf_counter()
    res = diagnose(path, scene)
    named = set(res.causes) | ({"drift"} if (res.drift or {}).get("named") else set())
    said = {a.get("other", "") for alts in res.to_json().get("alternatives", {}).values() for a in alts}
    said |= {e for a in res.to_json().get("observability", {}).get("ambiguous", []) for e in a.get("effects", [])}
    right = bool(named & right_families or any(f in s for f in right_families for s in said))
    right &= str(res.verdict.kind) != "scene does not match"
    return {"row": row, "seed": seed, "named": sorted(named), "verdict": str(res.verdict.kind), "right": right,
            "seconds": round(time.perf_counter() - t0, 1)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--width", type=int, default=160)
    ap.add_argument("--frames", type=int, default=6)
    ap.add_argument("--only", default=None, help="one row by name")
    a = ap.parse_args()
    rows = [a.only] if a.only else list(ROWS)
    out = []
    with tempfile.TemporaryDirectory() as tmp:
        for row in rows:
            for seed in range(a.seeds):
                r = run_row(row, seed, a.width, a.frames, Path(tmp))
                out.append(r)
                print(f"{row:24s} seed {seed}  {'right' if r['right'] else 'WRONG'}  {r['verdict']:18s} "
                      f"named {' + '.join(r['named']) or '-'}  ({r['seconds']:.0f} s)", flush=True)
    right = sum(r["right"] for r in out)
    print(f"\n{right}/{len(out)} right")


if __name__ == "__main__":
    main()
