"""Detection rate and held-out gain of diagnosis over several seeds.

For every effect of the library (the hidden-parameter draws of benchmarks/diagnose_cases.py) and
for "nothing hidden", render measured sessions with several seeds, diagnose them against the
base twin, and print: how often the hidden effect was named alone, the misfit per held-out
value before and after, the depth RMSE before and after, and the time per diagnosis.

    python benchmarks/diagnose_sweep.py [--seeds 3] [--effects stray_light,wiggling]

The same study as a sweep spec (one representative value per effect, parallel on Dask,
resumable, one table): ``tofhil sweep configs/sweeps/diagnose_effects.yaml --out DIR``.
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time
from pathlib import Path

import numpy as np

from tofhil.eval.diagnose import diagnose
from tofhil.sim.pipeline import simulate_session
from tofhil.sim.scene import load_scene

from diagnose_cases import CASES  # benchmarks/ is on the path when this file runs as a script


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--effects", default="", help="comma-separated subset (default: all, plus 'none')")
    args = ap.parse_args()
    cases = CASES
    names = [e for e in args.effects.split(",") if e] or list(cases) + ["none"]
    scene = load_scene("bench_demo")
    scene = dataclasses.replace(scene, camera=scene.camera.scaled(0.5))
    print(f"{'hidden':20s} {'seed':>4s} {'named':30s} {'ok':>3s} {'misfit before':>13s} {'after':>7s} "
          f"{'depth RMSE mm before':>20s} {'after':>7s} {'s':>5s}")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in names:
            for seed in range(args.seeds):
                rng = np.random.default_rng(1000 * seed + (names.index(name) + 1))
                hidden = {} if name == "none" else {name: cases[name](rng)}
                path = Path(tmp) / f"{name}_{seed}.h5"
                simulate_session(scene, path, frames=4, seed=int(rng.integers(10_000)), noise=True, effects=hidden)
                t0 = time.perf_counter()
                res = diagnose(path, scene, max_effects=2)
                dt = time.perf_counter() - t0
                ok = res.causes == ([] if name == "none" else [name])
                rows.append((name, ok, res.chi2_per_value["before"], res.chi2_per_value["after_extended_scene"], dt))
                print(f"{name:20s} {seed:4d} {'+'.join(res.causes) or '-':30s} {'yes' if ok else 'NO':>3s} "
                      f"{res.chi2_per_value['before']:13.2f} {res.chi2_per_value['after_extended_scene']:7.2f} "
                      f"{res.gain['depth_rmse_m']['before'] * 1e3:20.1f} {res.gain['depth_rmse_m']['after'] * 1e3:7.1f} "
                      f"{dt:5.1f}", flush=True)
    hits = sum(r[1] for r in rows)
    print(f"\ncorrect diagnoses: {hits}/{len(rows)} ({100 * hits / len(rows):.0f} %); "
          f"median time {np.median([r[4] for r in rows]):.1f} s per diagnosis")


if __name__ == "__main__":
    main()
