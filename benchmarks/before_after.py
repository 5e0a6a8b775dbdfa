"""Before and after in one run: a benchmark script run again, alternately, by an older tofhil.

``--before DIR`` on a benchmark (bench_render.py, bench_vs_mitsuba.py) re-runs the same script
as child processes, DIR first on PYTHONPATH (the older tofhil), then this one, ``--rounds``
times alternately, so both see the same machine and load; each child's lines are printed with
its label. The children run in a scratch directory: a checkout's own ``tofhil/`` in the
current directory would shadow the one on PYTHONPATH and mix two versions.

DIR is a checkout of an older commit laid out as a package::

    git archive COMMIT | tar -x -C SRC
    mkdir DIR && cp -r SRC/tofhil DIR/tofhil
    for d in sim eval drivers configs; do ln -s SRC/$d DIR/tofhil/$d; done

(the repository maps ``tofhil.sim`` to ``sim/`` and so on; the links do the same for an
import from PYTHONPATH). A fresh DIR compiles its numba kernels (and caches them beside its
sources) in its first run: run the benchmark once before the run that counts, or the before
side pays ~20 CPU-s of compilation.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path


def strip_before(argv: list[str]) -> list[str]:
    """``argv`` without ``--before DIR`` and ``--rounds N`` (the children's arguments)."""
    out, skip = [], False
    for a in argv:
        if skip:
            skip = False
            continue
        if a in ("--before", "--rounds"):
            skip = True
            continue
        if a.startswith(("--before=", "--rounds=")):
            continue
        out.append(a)
    return out


def run_alternating(script: str, argv: list[str], before: Path, rounds: int) -> None:
    """Run ``script argv`` with the tofhil in ``before`` and with this one, ``rounds`` times
    alternately, printing each child's output with its label."""
    before = before.resolve()
    if not (before / "tofhil" / "__init__.py").is_file():
        raise SystemExit(f"--before {before}: expected a folder holding tofhil/__init__.py "
                         "(a checkout laid out as a package, see benchmarks/before_after.py)")
    child_args = [sys.executable, str(Path(script).resolve()), *strip_before(argv)]
    base_env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    with tempfile.TemporaryDirectory(prefix="tofhil-before-after-") as scratch:
        for r in range(rounds):
            for label, env in (("before", base_env | {"PYTHONPATH": str(before)}), ("after", base_env)):
                p = subprocess.run(child_args, env=env, cwd=scratch, capture_output=True, text=True)
                if p.returncode:
                    raise SystemExit(f"{label} (round {r + 1}) failed ({p.returncode}):\n{p.stdout}\n{p.stderr}")
                for line in p.stdout.splitlines():
                    print(f"[{label} {r + 1}] {line}", flush=True)
