"""``tofhil sweep`` and ``tofhil batch diagnose|compare``: many cases on Dask, one table."""

from __future__ import annotations

import time
from pathlib import Path
from typing import List, Optional

import typer

from tofhil.cli import app, console, lit, out, progress
from tofhil.cli import options as opt

batch_app = typer.Typer(no_args_is_help=True, help="Diagnose or compare many sessions with the sweep engine.")
app.add_typer(batch_app, name="batch")

_SCHEDULER = typer.Option(None, "--scheduler", help="Address of a running Dask scheduler (tcp://host:8786); "
                                                    "default: a local cluster of worker processes.")
_WORKERS = typer.Option(None, "--workers", parser=opt.count(0, 4096),
                        help="Local worker processes (default: one per core; 0: run the cases here, one by one).")
_RESUME = typer.Option(False, "--resume", help="Continue a sweep in OUT: finished cases are not redone.")
_FORCE = typer.Option(False, "--force", help="Start over in OUT, removing an earlier sweep's results.")
_RETRY = typer.Option(False, "--retry-failed", help="With --resume: run the cases that failed again too.")


def _log(start: float):
    def say(message: str) -> None:
        console.print(f"[dim]{time.monotonic() - start:6.1f} s[/dim]  {lit(message)}", highlight=False)

    return say


def _run(spec, out_dir: Path, scheduler: Optional[str], workers: Optional[int], resume: bool, force: bool,
         retry_failed: bool = False) -> None:
    from tofhil.app.sweep import expand_cases, run_sweep

    start = time.monotonic()
    n = len(expand_cases(spec))
    _log(start)(f"{spec.name}: {n} case(s)")
    res = run_sweep(spec, out_dir, scheduler=scheduler, workers=workers, resume=resume, force=force,
                    retry_failed=retry_failed, progress=progress, log=_log(start))
    out.print(f"{res.ran} case(s) run, {res.skipped} already done, {res.failed} failed "
              f"({res.seconds:.1f} s)", highlight=False)
    if res.failed:
        for _, r in res.table[res.table["status"] != "ok"].head(5).iterrows():
            out.print(f"  failed {lit(r['case'])}: {lit(r['error'])}", highlight=False)
    out.print(f"table: {lit(out_dir / 'results.parquet')} (and results.csv); report: {lit(out_dir / 'report.html')}")


@app.command()
def sweep(spec_file: Path = typer.Argument(..., parser=opt.existing_file, help="Sweep spec (YAML)."),
          out_dir: Path = typer.Option(..., "--out", parser=opt.out_dir,
                                       help="Directory for cases/, results.parquet, results.csv, report.html."),
          scheduler: Optional[str] = _SCHEDULER, workers: Optional[int] = _WORKERS,
          resume: bool = _RESUME, force: bool = _FORCE, retry_failed: bool = _RETRY) -> None:
    """Run a sweep: every case of the spec as one Dask task, one table of results and a report."""
    from tofhil.app.sweep import load_spec

    _run(load_spec(spec_file), out_dir, scheduler, workers, resume, force, retry_failed)


@batch_app.command("diagnose")
def batch_diagnose(sessions: List[str] = typer.Argument(..., help="Session files, glob patterns, or @LIST files."),
                   scene: str = typer.Option(..., "--scene", help="The twin's base scene (file or bundled name)."),
                   out_dir: Path = typer.Option(..., "--out", parser=opt.out_dir, help="Directory for the results."),
                   max_effects: Optional[int] = typer.Option(None, parser=opt.count(1, 50), help="Most effects to add."),
                   scheduler: Optional[str] = _SCHEDULER, workers: Optional[int] = _WORKERS,
                   resume: bool = _RESUME, force: bool = _FORCE, retry_failed: bool = _RETRY) -> None:
    """Diagnose every session against one scene; one summary table."""
    from tofhil.app.sweep import batch_spec, session_list

    spec = batch_spec("diagnose", session_list(sessions), scene=scene, max_effects=max_effects)
    _run(spec, out_dir, scheduler, workers, resume, force, retry_failed)


@batch_app.command("compare")
def batch_compare(sessions: List[str] = typer.Argument(..., help="Session files, glob patterns, or @LIST files."),
                  reference: Optional[Path] = typer.Option(None, "--reference", parser=opt.existing_file,
                                                           help="The reference session B for every session."),
                  scene: Optional[str] = typer.Option(None, "--scene",
                                                      help="Compare against the twin of this scene instead."),
                  correct: List[str] = typer.Option([], "--correct", help="A correction to apply to each session."),
                  frames: int = typer.Option(10, "--frames", parser=opt.count(1, 100_000), help="Frames to average."),
                  out_dir: Path = typer.Option(..., "--out", parser=opt.out_dir, help="Directory for the results."),
                  scheduler: Optional[str] = _SCHEDULER, workers: Optional[int] = _WORKERS,
                  resume: bool = _RESUME, force: bool = _FORCE, retry_failed: bool = _RETRY) -> None:
    """Compare every session with one reference (or the twin); one summary table."""
    from tofhil.errors import TofhilError
    from tofhil.app.sweep import batch_spec, session_list

    if (reference is None) == (scene is None):
        raise TofhilError("give exactly one of --reference and --scene", field="--reference",
                          expected="a reference session, or a scene whose twin is the reference")
    spec = batch_spec("compare", session_list(sessions), scene=scene,
                      reference=None if reference is None else str(reference.resolve()),
                      corrections=correct, frames=frames)
    _run(spec, out_dir, scheduler, workers, resume, force, retry_failed)
