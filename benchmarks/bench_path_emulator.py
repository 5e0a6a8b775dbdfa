"""The bench path, scene by scene: every bundled scene captured by the emulated TOFcam635 (its
pyusb driver on the emulated device; per-tap effects cannot be hidden there, the emulator
re-expresses its render as the device's DCS through the complex signal) and diagnosed against the scene as written, as a user at a
bench would (issue 32). The emulator renders the scene as a TOFcam635 with its hidden truth
(stray light, wiggling, the clock-skew pattern: ``HIDDEN_TRUTH_EFFECTS``) and, with
``--further``, one more effect hidden in its scene; the diagnosis must name them, with the
device's signal scale fitted and stated.

    python benchmarks/bench_path_emulator.py [--scenes dark_square,wall] [--further none,illumination]
                                             [--frames 6] [--out results.json]

Prints one line per (scene, further effect): what was named, whether the hidden truth is in
it (or in an "A or B" said), the fitted signal scale and the seconds; then the share right.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

#: Further effects hidden beside the emulator's own truth, as the emulator's scene states them.
FURTHER: dict[str, dict[str, dict]] = {
    "none": {},
    "illumination": {"illumination": {"dn": 1.0}},           # a beam narrower than the scene's
    "field_angle": {"field_angle": {"c2_m": 0.02}},          # range growing with the field angle
    "emitter_position": {"emitter_position": {"dz": 0.04}},  # the emitter 4 cm behind the lens
}


def capture(scene: str, effects: dict, frames: int, out: Path, seed: int) -> Path:
    from tofhil.drivers.base import CaptureSettings
    from tofhil.drivers.capture import capture as capture_session
    from tofhil.drivers.tofcam635.emulator import EmulatedTofCam635, Epc635Emulator
    from tofhil.sim.sources import SimulatedSource

    src = SimulatedSource(scene, effects=effects, seed=seed)
    drv = EmulatedTofCam635("emulator:" + scene, emulator=Epc635Emulator(src))
    drv.open()
    try:
        capture_session(drv, out, frames, CaptureSettings(mode="dcs"), force=True)
    finally:
        drv.close()
    return out


def named_or_said(res, effect: str) -> bool:
    """``effect`` named, or one reading of an "A or B" the diagnosis says."""
    if effect in res.causes:
        return True
    return any(effect in a.get("other", "") for alts in res.to_json().get("alternatives", {}).values() for a in alts)


def main() -> None:
    from tofhil.errors import InputFileError
    from tofhil.eval.diagnose.run import diagnose
    from tofhil.sim.scene import bundled_scenes, load_scene
    from tofhil.sim.sources import HIDDEN_TRUTH_EFFECTS

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default="", help="comma-separated bundled scenes (default: every one)")
    ap.add_argument("--further", default="none", help="comma-separated further effects: " + ", ".join(FURTHER))
    ap.add_argument("--frames", type=int, default=6)
    ap.add_argument("--seed", type=int, default=635)
    ap.add_argument("--out", default="")
    a = ap.parse_args()
    scenes = [s for s in a.scenes.split(",") if s] or sorted(bundled_scenes())
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for scene in scenes:
            for further in a.further.split(","):
                hidden = {**HIDDEN_TRUTH_EFFECTS, **FURTHER[further]}
                t0 = time.perf_counter()
                row = {"scene": scene, "further": further}
                try:
                    path = capture(scene, hidden, a.frames, Path(tmp) / f"{scene}_{further}.h5", a.seed)
                    res = diagnose(path, load_scene(scene))
                except InputFileError as exc:  # a scene the emulated camera cannot render: said, next
                    row |= {"skipped": str(exc)[:200]}
                    print(f"{scene:18s} {further:20s} skipped: {row['skipped']}", flush=True)
                    rows.append(row)
                    continue
                except Exception as exc:
                    row |= {"error": f"{type(exc).__name__}: {exc}"[:200], "right": False}
                    print(f"{scene:18s} {further:20s} ERROR {row['error']}", flush=True)
                    rows.append(row)
                    continue
                found = {e: named_or_said(res, e) for e in hidden}
                row |= {"named": list(res.causes), "verdict": str(res.verdict.kind), "found": found,
                        "right": all(found.values()), "scale": round(res.signal_scale.factor, 4),
                        "seconds": round(time.perf_counter() - t0, 1)}
                rows.append(row)
                print(f"{scene:18s} {further:20s} {'right' if row['right'] else 'WRONG':5s} named "
                      f"{' + '.join(res.causes) or '-':55s} {row['verdict']:18s} scale x{row['scale']:<8g} "
                      f"{row['seconds']:.0f} s", flush=True)
    done = [r for r in rows if "skipped" not in r]
    right = sum(r["right"] for r in done)
    print(f"\n{right}/{len(done)} name the hidden truth (every hidden effect named or said as one reading of an A or B)")
    if a.out:
        Path(a.out).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
