"""Diagnosis over random disturbances (issue 32's development instrument): how often the right
family is named or the right channel and shape said, how often "the scene does not match" is
said (never right here: the geometry is right in every draw), and what nulls name.

    python benchmarks/diagnose_disturbances.py --draws 200 --nulls 60 [--width 80] [--out results.json]
    python benchmarks/diagnose_disturbances.py --shard 1/2 --out a.json &   # one process a core
    python benchmarks/diagnose_disturbances.py --shard 2/2 --out b.json; \
    python benchmarks/diagnose_disturbances.py --summary a.json b.json

Draws come from ``tests/eval/disturbances.py`` (written without the effect library's code): two
bundled scenes (dark_square, two_squares) x two sensors (1 frequency 4 taps, 44 + 60 MHz 3 taps),
single disturbances and pairs, strengths z 10 to 1000. Prints one line per draw and a table per
class; the seeds are the draw index, so a run is repeatable and a failing draw can be rerun alone
(``--only N``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from tests.eval import disturbances as D  # noqa: E402

SCENES = ("dark_square", "two_squares")
SENSORS = ("1f4t", "2f3t")


def scene_for(name: str, width: int, variant: str):
    from tofhil.sim.scene import load_scene

    scene = load_scene(name)
    scene = dataclasses.replace(scene, camera=scene.camera.scaled(width / scene.camera.width))
    return D.sensor_variant(scene, variant)


def run_one(i: int, width: int, frames: int, tmp: Path, null: bool) -> dict:
    from tofhil.eval.diagnose.run import diagnose

    rng = np.random.default_rng(10_000 + i if null else i)
    name, variant = SCENES[i % 2], SENSORS[(i // 2) % 2]
    scene = scene_for(name, width, variant)
    sens = scene.sensor
    dist = [] if null else D.draw(rng, len(sens.freq_hz), len(sens.theta_rad), pair=(i % 5 == 4))
    path = D.write_disturbed(scene, tmp / f"d{i}.h5", dist, frames=frames, seed=i)
    t0 = time.perf_counter()
    res = diagnose(path, scene)
    sec = time.perf_counter() - t0
    row = {"i": i, "null": null, "scene": name, "sensor": variant, "seconds": round(sec, 1),
           "disturbances": [dataclasses.asdict(d) for d in dist], "verdict": res.verdict.kind,
           "named": list(res.causes) + (["drift"] if (res.drift or {}).get("named") else [])}
    if null:
        row["right"] = not row["named"] and res.verdict.kind != "scene does not match"
        row["how"] = "nothing named" if row["right"] else "named " + ",".join(row["named"])
    else:
        j = D.judge(res, dist)
        row |= {"right": j.right, "how": j.how, "scene_mismatch": j.scene_mismatch}
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--draws", type=int, default=200)
    ap.add_argument("--nulls", type=int, default=60)
    ap.add_argument("--width", type=int, default=80)
    ap.add_argument("--frames", type=int, default=4)
    ap.add_argument("--only", type=int, default=None, help="run draw N alone")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--shard", default="1/1", help="K/N: run every N-th job from the K-th (one process a core)")
    ap.add_argument("--summary", type=Path, nargs="+", default=None, help="print the table of saved --out files")
    a = ap.parse_args()
    if a.summary:
        summarise([r for p in a.summary for r in json.loads(p.read_text())])
        return
    k, n = (int(v) for v in a.shard.split("/"))
    rows = []
    with tempfile.TemporaryDirectory() as td:
        tmp = Path(td)
        jobs = [(a.only, False)] if a.only is not None else \
            [(i, False) for i in range(a.draws)] + [(i, True) for i in range(a.nulls)]
        for i, null in jobs[k - 1::n]:
            r = run_one(i, a.width, a.frames, tmp, null)
            rows.append(r)
            what = "null" if null else " + ".join(f"{d['channel']}/{d['shape']} z{d['z']:.0f}" for d in r["disturbances"])
            print(f"{'null' if null else 'draw'} {i:3d} {r['scene']:11s} {r['sensor']} {what:42s} -> {r['verdict']:20s} "
                  f"{','.join(r['named']) or '-':40s} {'RIGHT' if r['right'] else 'wrong'} {r['how']} ({r['seconds']} s)",
                  flush=True)
            (tmp / f"d{i}.h5").unlink(missing_ok=True)
            if a.out:  # after every job: a long run stopped early keeps what it measured
                a.out.write_text(json.dumps(rows, indent=1))
    summarise(rows)


def summarise(rows: list[dict]) -> None:
    draws = [r for r in rows if not r["null"]]
    nulls = [r for r in rows if r["null"]]
    by = defaultdict(lambda: [0, 0])
    for r in draws:
        key = " + ".join(sorted(f"{d['channel']}/{d['shape']}" for d in r["disturbances"])) \
            if len(r["disturbances"]) == 1 else "pairs"
        by[key][0] += r["right"]
        by[key][1] += 1
    print("\nclass                         right / draws")
    for k in sorted(by):
        print(f"{k:30s} {by[k][0]:3d} / {by[k][1]}")
    if draws:
        right = sum(r["right"] for r in draws)
        mism = sum(r.get("scene_mismatch", False) for r in draws)
        print(f"\ndraws: right {right}/{len(draws)} ({100 * right / len(draws):.0f} %, aim >= 90 %); "
              f"'scene does not match' {mism}/{len(draws)} ({100 * mism / len(draws):.1f} %, aim <= 2 %)")
    if nulls:
        named = sum(not r["right"] for r in nulls)
        print(f"nulls: {named}/{len(nulls)} name something or say the scene does not match (aim 0)")


if __name__ == "__main__":
    main()
