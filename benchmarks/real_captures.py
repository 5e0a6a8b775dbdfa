"""The real captures end to end: import, scene-from-capture, diagnose; the figures per capture.

    python benchmarks/real_captures.py --out /tmp/real [--only near,office,kinect] [--target SPEC]

Runs each step as the CLI (a fresh process), with its wall time and peak memory (the child's
maximum resident set, from ``os.wait4``), and prints per capture: the verdict, what was named,
ambiguous or unobservable, the held-out gain per channel, what the residual left shows, and
the run time and memory of each step. The captures are those of ../shared/data/real/ (README
there); their modulation frequencies and wavelengths are not recorded, so each is given the
one the tests use (``tests/real_data.CAPTURES``: its unambiguous range covers the capture's
depths), and the figures hold at that frequency.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from tests.real_data import CAPTURES  # noqa: E402  (the settings the tests use, in one place)


def run(args: list[str]) -> tuple[float, float, float, str]:
    """Wall seconds, peak memory (MiB), CPU seconds (user + system: the figure that does not
    depend on how many others share the cores) and output of one CLI call."""
    t0 = time.perf_counter()
    p = subprocess.Popen([sys.executable, "-m", "tofhil.cli", *args], stdout=subprocess.PIPE,
                         stderr=subprocess.STDOUT, text=True, env=os.environ | {"COLUMNS": "200"})
    out = p.stdout.read()
    _, status, ru = os.wait4(p.pid, 0)
    p.returncode = os.waitstatus_to_exitcode(status)
    wall = time.perf_counter() - t0
    if p.returncode:
        raise SystemExit(f"tofhil {' '.join(args)} failed ({p.returncode}):\n{out}")
    return wall, ru.ru_maxrss / 1024.0, ru.ru_utime + ru.ru_stime, out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--only", default=",".join(CAPTURES))
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    rows = {}
    for name in args.only.split(","):
        cap = CAPTURES[name]
        src, opts = cap.file, cap.options()
        d = args.out / name
        d.mkdir(exist_ok=True)
        session = d / "session.h5"
        steps = {}
        if not session.exists():
            steps["import"] = run(["import", str(src), "--out", str(session)])[:3]
        steps["scene-from-capture"] = run(["scene-from-capture", str(session), "--out", str(d / "scene.yaml"),
                                           *opts, "--force"])[:3]
        steps["diagnose"] = run(["diagnose", str(session), "--scene", str(d / "scene.yaml"), "--out", str(d / "diag"),
                                 "--force"])[:3]
        res = json.loads((d / "diag" / "diagnosis.json").read_text())
        g = res["gain"]
        rows[name] = {
            "freq_hz": cap.freq_hz, "wavelength_m": cap.wavelength_m,
            "verdict": res["verdict"]["kind"], "verdict_text": res["verdict"]["text"],
            "notes": res["verdict"]["notes"], "causes": res["causes"], "params": res["params"],
            "ambiguous": [a["effects"] for a in res["observability"]["ambiguous"]],
            "unobservable": sorted(res["observability"]["unobservable"]),
            "depth_rmse_mm": [round(g["depth_rmse_m"]["before"] * 1e3, 3), round(g["depth_rmse_m"]["after"] * 1e3, 3)],
            "amplitude_rmse": [round(g["amplitude_rmse"]["before"], 4), round(g["amplitude_rmse"]["after"], 4)],
            "channels_per_value": {c: [v["before_per_value"], v["after_per_value"]] for c, v in res["channels"].items()},
            "noise": res["noise"], "residual_regions": len(res["residual_regions"]),
            "residual_structure": [f["text"] for f in res.get("residual_structure", [])],
            "effect_size": {c: [v["rmse_before"], v["rmse_after"], v["systematic_removed"], v["minimum_gain"], v["unit"]]
                            for c, v in res.get("effect_size", {}).get("channels", {}).items()},
            "fitted_too_small": res.get("effect_size", {}).get("fitted_too_small", {}),
            "residual_regions_text": [r["text"] for r in res["residual_regions"]],
            "steps_wall_s_peak_mib_cpu_s": {k: [round(v[0], 1), round(v[1]), round(v[2], 1)]
                                            for k, v in steps.items()},
        }
        print(json.dumps({name: rows[name]}, indent=1), flush=True)
    (args.out / "summary.json").write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
