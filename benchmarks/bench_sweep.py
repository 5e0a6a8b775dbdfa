"""Speed-up of a sweep on 2 Dask workers over 1, and the engine's per-case overhead.

    python benchmarks/bench_sweep.py [--cases 8] [--scale 0.5]

Runs the same sweep (``wall_card``, one render per card reflectance, seeds sharing it,
each case simulate + compare against the twin) four ways: a bare loop over
``tofhil.app.sweep.run_case`` (no records, no table), the engine in this process
(``workers=0``), a LocalCluster of 1 worker process and one of 2. Prints the wall time of
each, the speed-up of 2 workers over 1, and the per-case overhead of the engine (in process
and on Dask, the cluster's start-up counted separately) against the bare loop.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

from tofhil.app import sweep as S
from tofhil.app.sweep import run as sweep_run  # the per-process twin cache lives there


def spec(cases: int, scale: float) -> S.SweepSpec:
    return S.parse_spec({"name": "bench", "scene": "wall_card", "frames": 4,
                         "effects": {"stray_light": {"weight": 0.03, "sigma_px": 6.0}},
                         "axes": {"camera.scale": [scale], "params.card_reflectance": [0.4, 0.8],
                                  "seed": list(range(max(cases // 2, 1)))},
                         "compare": {"reference": "twin", "frames": 4}})


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=8)
    ap.add_argument("--scale", type=float, default=0.5, help="camera scale of the 160 x 120 preset")
    args = ap.parse_args()
    sp = spec(args.cases, args.scale)
    n = len(S.expand_cases(sp))
    times: dict[str, float] = {}
    with tempfile.TemporaryDirectory() as tmp:
        S.run_case(sp, S.expand_cases(sp)[0], str(Path(tmp) / "warm"))  # numba compilation, imports
        sweep_run._TWINS.clear()
        t = time.perf_counter()
        for case in S.expand_cases(sp):
            rec = S.run_case(sp, case, str(Path(tmp) / "bare"))
            assert rec["status"] == "ok", rec["error"]
        times["bare loop"] = time.perf_counter() - t
        sweep_run._TWINS.clear()
        t = time.perf_counter()
        S.run_sweep(sp, Path(tmp) / "serial", workers=0)
        times["engine, in process"] = time.perf_counter() - t
        for w in (1, 2):
            t = time.perf_counter()
            client = S.local_client(w)
            # worker start-up, imports and numba compilation: one case on every worker
            warm = S.expand_cases(sp)[0]
            client.run(S.run_case, sp, warm, str(Path(tmp) / f"warm{w}"))
            start = time.perf_counter() - t
            t = time.perf_counter()
            res = S.run_sweep(sp, Path(tmp) / f"dask{w}", client=client)
            times[f"dask, {w} worker(s)"] = time.perf_counter() - t
            times[f"dask, {w} worker(s), start-up + warm-up"] = start
            cluster = client.cluster
            client.close()
            cluster.close()
            assert res.failed == 0
    print(f"{n} cases (wall_card at scale {args.scale}, simulate {sp.frames} frames + compare with the twin)")
    for k, v in times.items():
        print(f"  {k:32s} {v:7.2f} s")
    print(f"speed-up of 2 workers over 1: {times['dask, 1 worker(s)'] / times['dask, 2 worker(s)']:.2f}x")
    bare = times["bare loop"] / n
    print(f"per-case overhead against the bare loop ({bare:.3f} s/case): engine in process "
          f"{(times['engine, in process'] / n - bare) * 1e3:+.0f} ms, Dask 1 worker "
          f"{(times['dask, 1 worker(s)'] / n - bare) * 1e3:+.0f} ms (workers warmed up; the bare loop renders once "
          "per scene too)")
    print(f"load average during the run: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")


if __name__ == "__main__":
    main()
