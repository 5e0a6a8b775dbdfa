"""Diagnosis at camera resolution: wall time and peak memory of ``tofhil diagnose`` on a
512 x 512 raw-tap session from the twin, all candidates.

The session is the bundled bench scene (wall, dark square, card) on a 512 x 512 sensor with
the lens of the preset scaled to it, rendered by ``tofhil simulate`` with a hidden effect
(stray light by default) and noise; the diagnosis runs as its own process (``tofhil
diagnose``), so its peak resident memory (VmHWM) is its own. Aims: < 60 s wall, < 1 GB.

    python benchmarks/bench_diagnose.py [--size 512] [--frames 4] [--hidden stray_light.weight=0.04,...]
        [--profile]          # cProfile of the diagnosis, top 30 by cumulative time
        [--before DIR]       # also time another tofhil (DIR on PYTHONPATH, e.g. a checkout of an
                             # older commit laid out as a package) on the same session, first

A checkout laid out as a package: ``git archive COMMIT | tar -x -C SRC``, then DIR/tofhil a
copy of SRC/tofhil with links DIR/tofhil/{sim,eval,drivers,configs} -> SRC/{sim,...}
(benchmarks/before_after.py). A fresh DIR compiles its numba kernels in its first run (~20
CPU-s): run it once before the run that counts.

Prints the named causes too: a faster diagnosis must name the same ones.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

AIM_S = 60.0
AIM_BYTES = 1e9

_CHILD = r"""
import cProfile, json, pstats, resource, sys, time
from tofhil.eval.diagnose.run import run_diagnosis
session, scene, out, profile = sys.argv[1], sys.argv[2], sys.argv[3], sys.argv[4] == "1"
t0, c0 = time.perf_counter(), time.process_time()
prof = cProfile.Profile() if profile else None
if prof:
    prof.enable()
res = run_diagnosis(session, scene, out)
if prof:
    prof.disable()
wall, cpu = time.perf_counter() - t0, time.process_time() - c0
hwm = 0
for line in open("/proc/self/status"):
    if line.startswith("VmHWM:"):
        hwm = int(line.split()[1]) * 1024
if prof:
    pstats.Stats(prof, stream=sys.stderr).sort_stats("cumulative").print_stats(30)
print(json.dumps({"wall_s": wall, "cpu_s": cpu, "peak_rss_bytes": hwm, "causes": res.causes,
                  "chi2": res.chi2_per_value}))
"""


def scene_yaml(size: int) -> str:
    """bench_demo on a size x size sensor: the preset's lens scaled by size / 160 (its width)."""
    from tofhil.sim.scene import load_scene

    cam = load_scene("bench_demo").camera
    k = size / cam.width
    base = Path(__file__).resolve().parents[1] / "configs" / "scenes" / "bench_demo.yaml"
    text = base.read_text()
    camera = (f"camera:\n  preset: holmlund_thesis\n  width: {size}\n  height: {size}\n"
              f"  fx: {cam.fx * k:.4f}\n  fy: {cam.fy * k:.4f}\n  cx: {(size - 1) / 2}\n  cy: {(size - 1) / 2}\n"
              f"  pixel_pitch_m: {cam.pixel_pitch_m / k:.6g}\n")
    head, rest = text.split("camera:\n", 1)
    # keep the rest of the camera block (pose, f_number) after our lines
    rest_lines = rest.splitlines(keepends=True)
    kept = [ln for ln in rest_lines[:4] if ln.startswith("  ") and not ln.startswith("  preset")]
    return head + camera + "".join(kept) + "".join(rest_lines[len(kept) + 1:])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--frames", type=int, default=4)
    ap.add_argument("--hidden", default="stray_light.weight=0.04,stray_light.sigma_px=12,stray_light.veil=0.004",
                    help="effect parameters hidden in the session (EFFECT.PARAM=VALUE, comma-separated)")
    ap.add_argument("--profile", action="store_true")
    ap.add_argument("--keep", type=Path, default=None, help="directory to keep the session and scene in")
    ap.add_argument("--before", type=Path, default=None,
                    help="another tofhil (a directory holding the package tofhil) to time first, on the same session")
    args = ap.parse_args()
    tmp = tempfile.TemporaryDirectory() if args.keep is None else None
    work = Path(tmp.name) if tmp else args.keep
    work.mkdir(parents=True, exist_ok=True)
    scene = work / f"bench_{args.size}.yaml"
    scene.write_text(scene_yaml(args.size))
    session = work / f"session_{args.size}.h5"
    env = dict(os.environ)
    if not session.exists():
        cmd = [sys.executable, "-m", "tofhil.cli", "simulate", str(scene), "--out", str(session),
               "--frames", str(args.frames), "--seed", "1"]
        for h in filter(None, args.hidden.split(",")):
            cmd += ["--effect", h]
        t0 = time.perf_counter()
        subprocess.run(cmd, check=True, env=env, stdout=subprocess.DEVNULL)
        print(f"session: {args.size} x {args.size}, {args.frames} frames, hidden {args.hidden or 'nothing'} "
              f"({time.perf_counter() - t0:.1f} s to simulate)")
    out = work / "diagnosis"
    runs = [("before", dict(env, PYTHONPATH=str(args.before.resolve())))] if args.before else []
    runs.append(("this tofhil" if args.before else "", env))
    for label, run_env in runs:
        # (run in the work directory: a checkout's own tofhil/ in the current directory would
        # shadow the one on PYTHONPATH and mix two versions)
        r = subprocess.run([sys.executable, "-c", _CHILD, str(session.resolve()), str(scene.resolve()),
                            str(out.resolve()) + f"_{time.time_ns()}", "1" if args.profile else "0"],
                           check=True, env=run_env, capture_output=True, text=True, cwd=work)
        if args.profile:
            print(r.stderr)
        res = json.loads(r.stdout.strip().splitlines()[-1])
        print(f"{label + ': ' if label else ''}diagnosis {args.size} x {args.size}, all candidates: "
              f"wall {res['wall_s']:.1f} s (aim < {AIM_S:.0f} s), CPU {res['cpu_s']:.1f} s, "
              f"peak RSS {res['peak_rss_bytes'] / 1e9:.2f} GB (aim < {AIM_BYTES / 1e9:.0f} GB); "
              f"named {res['causes']}, chi2/value {res['chi2']['before']:.4f} -> {res['chi2']['after_extended_scene']:.4f}",
              flush=True)
    if tmp:
        tmp.cleanup()


if __name__ == "__main__":
    main()
