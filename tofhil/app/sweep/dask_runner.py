"""The sweep engine: run every case not yet finished, locally or on a Dask cluster, and
rebuild the table and the report.

Execution is on ``dask.distributed``: a ``LocalCluster`` of worker processes on this machine
by default, or an existing cluster (``scheduler``, ``client``); ``workers=0`` runs the cases
one by one in this process (no Dask). Each case is one task (:func:`tofhil.app.sweep.run.run_case`);
its record is written by this process as it arrives, so a killed sweep resumes
(``resume=True``) without redoing what finished, and a failed case (a worker that died
included) is a record with its error while the others go on. With a remote cluster the
output directory and the inputs must be on a file system every worker sees.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import yaml

from tofhil.app.sweep.calibration import run_calibration
from tofhil.app.sweep.cases import Case, digest, expand_cases
from tofhil.app.sweep.results import read_records, results_table, write_record, write_report, write_table
from tofhil.app.sweep.run import plain_params, run_case
from tofhil.app.sweep.spec import SweepSpec
from tofhil.errors import Interrupted, TofhilError
from tofhil.outputs import atomic_path, refuse_existing
from tofhil.progress import Progress, no_progress

#: What a sweep directory holds (a directory holding any of them holds a sweep): --force removes
#: all of it (an earlier calibration too: it was fitted for that sweep's spec), --resume keeps it.
OUTPUTS = ("results.parquet", "results.csv", "report.html", "spec.yaml", "cases", "calibration")


class SweepInterrupted(Interrupted):
    """Ctrl-C during a sweep: the finished cases are kept, ``--resume`` continues."""

    def __init__(self, path: str | Path, done: int, total: int) -> None:
        KeyboardInterrupt.__init__(self, f"interrupted: {done} of {total} cases finished and kept in {path} "
                                         "(rerun with --resume to continue)")
        self.path, self.frames_kept = str(path), 0


@dataclass
class SweepResult:
    """What :func:`run_sweep` did: the table, the cases run now, those already done, those failed."""

    out_dir: Path
    table: Any  # pandas.DataFrame
    ran: int
    skipped: int
    failed: int
    seconds: float


def prepare_sweep_dir(spec: SweepSpec, out_dir: str | Path, *, resume: bool, force: bool) -> Path:
    """Check the output directory: a new or empty one; with ``resume`` one holding this same
    spec; with ``force`` an earlier sweep's files are removed. Nothing is changed otherwise."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise TofhilError("is a file, not a directory", file=out, field="--out", expected="a directory for the sweep")
    held = [n for n in OUTPUTS if (out / n).exists()]
    saved = out / "spec.yaml"
    if held and resume and not force:
        if not saved.exists():
            raise TofhilError("holds sweep outputs but no spec.yaml to resume from", file=out,
                              expected="the --out directory of an earlier sweep, or --force")
        old = yaml.safe_load(saved.read_text(encoding="utf-8")) or {}
        if old.get("cases") != _spec_fingerprint(spec):
            raise TofhilError("holds a sweep of another spec (its cases differ); refusing to mix them", file=out,
                              expected="the same spec to --resume, or --force to start over")
        return out
    if held:
        refuse_existing(out / held[0], force, what="already holds a sweep (use --resume to continue it)")
        for n in held:  # forced: the earlier sweep's files go
            p = out / n
            shutil.rmtree(p) if p.is_dir() else p.unlink()
    return out


def _spec_fingerprint(spec: SweepSpec) -> str:
    """A digest of what makes the spec's cases (not its name, description or file): the
    same fingerprint, the same cases, so ``--resume`` may continue them."""
    d = spec.to_dict()
    for k in ("source", "base_dir", "text", "description", "report_metrics", "name"):
        d.pop(k, None)
    return digest(d)


def _save_spec(spec: SweepSpec, out: Path) -> None:
    """``spec.yaml``: the validated spec and its fingerprint (what ``--resume`` checks)."""
    out.mkdir(parents=True, exist_ok=True)
    meta = {"cases": _spec_fingerprint(spec), "source": spec.source, "spec": json.loads(json.dumps(
        {k: v for k, v in spec.to_dict().items() if k != "text"}, default=str))}
    with atomic_path(out / "spec.yaml") as tmp:
        tmp.write_text(yaml.safe_dump(meta, sort_keys=False), encoding="utf-8")


def local_client(workers: int | None = None, **kwargs: Any) -> Any:
    """A ``dask.distributed`` client on a new ``LocalCluster`` of worker processes (one
    task at a time each: the cases are CPU-bound Python and numba), no dashboard, quiet logs."""
    import logging

    from distributed import Client, LocalCluster

    n = workers or os.cpu_count() or 1
    # The cores are shared out: numba's parallel kernels in each worker get cores / workers
    # threads (n workers each starting one thread per core would oversubscribe the machine).
    env = {"NUMBA_NUM_THREADS": str(max(1, (os.cpu_count() or 1) // n)), "OMP_NUM_THREADS": "1"}
    kwargs.setdefault("env", env)
    cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None,
                           silence_logs=logging.ERROR, **kwargs)
    return Client(cluster)


def run_sweep(spec: SweepSpec, out_dir: str | Path, *, scheduler: str | None = None, workers: int | None = None,
              client: Any = None, resume: bool = False, force: bool = False, retry_failed: bool = False,
              progress: Progress | None = None, log: Callable[[str], None] | None = None) -> SweepResult:
    """Run every case not yet finished, writing each record as it finishes; then the table
    and the report. ``retry_failed`` (with ``resume``) runs the cases that failed again too
    (a device that was unplugged, a worker that died); their old records stay until replaced.

    ``client``: an existing ``distributed.Client``; else ``scheduler`` (an address) connects to
    a running cluster; else a ``LocalCluster`` of ``workers`` processes (default: one per
    core); ``workers=0`` runs the cases in this process, one by one.
    """
    say = log or (lambda s: None)
    bar = progress or no_progress
    t0 = time.perf_counter()
    cases = expand_cases(spec)
    out = prepare_sweep_dir(spec, out_dir, resume=resume, force=force)
    created = not out.exists()
    _save_spec(spec, out)
    done = read_records(out) if resume else {}
    if retry_failed:
        if not resume:
            raise TofhilError("retrying failed cases continues a sweep", field="--retry-failed",
                              expected="--resume as well")
        retried = sum(1 for c in cases if c.id in done and done[c.id].get("status") != "ok")
        done = {k: r for k, r in done.items() if r.get("status") == "ok"}
        if retried:
            say(f"retrying {retried} failed case(s)")
    todo = [c for c in cases if c.id not in done]
    if done:
        say(f"resuming: {len(cases) - len(todo)} of {len(cases)} cases already done")
    ran = failed = 0
    try:
        if todo and spec.calibrate is not None:
            run_calibration(spec, out, say)
        if todo and workers == 0 and client is None and scheduler is None:
            for case in bar(todo, len(todo), "sweep"):
                rec = run_case(spec, case, str(out))
                write_record(out, rec)
                ran += 1
                failed += rec["status"] != "ok"
        elif todo:
            ran, failed = _run_on_dask(spec, todo, out, scheduler=scheduler, workers=workers, client=client,
                                       progress=bar, say=say)
    except BaseException as exc:
        kept = len(read_records(out)) if out.is_dir() else 0
        if created and not kept:
            shutil.rmtree(out, ignore_errors=True)
        if isinstance(exc, KeyboardInterrupt) and kept:
            raise SweepInterrupted(out, kept, len(cases)) from None
        raise
    return finish_sweep(spec, out, ran=ran, failed=failed, seconds=time.perf_counter() - t0, n_cases=len(cases))


def _run_on_dask(spec: SweepSpec, todo: list[Case], out: Path, *, scheduler: str | None, workers: int | None,
                 client: Any, progress: Progress, say: Callable[[str], None]) -> tuple[int, int]:
    """Submit the cases to a cluster (the given client, the scheduler's, or a new local one,
    closed again at the end) and write each record as it arrives; the cases run and failed."""
    from distributed import Client, as_completed

    own = None
    if client is None:
        if scheduler:
            say(f"connecting to the Dask scheduler at {scheduler}")
            try:
                client = own = Client(scheduler, timeout="20s")
            except (OSError, TimeoutError, ValueError) as exc:
                raise TofhilError(f"cannot reach the Dask scheduler ({exc})", field="--scheduler",
                                  expected="the address of a running scheduler, e.g. tcp://host:8786") from None
        else:
            say(f"starting a local Dask cluster ({workers or os.cpu_count()} worker processes)")
            client = own = local_client(workers)
    ran = failed = 0
    try:
        futures = [client.submit(run_case, spec, c, str(out.resolve()), pure=False) for c in todo]
        by_future = dict(zip(futures, todo))
        for fut in progress(as_completed(futures), len(futures), "sweep"):
            case = by_future.pop(fut)
            try:
                rec = fut.result()
            except Exception as exc:  # the worker died (KilledWorker), or the task could not run
                rec = {"id": case.id, "index": case.index, "params": plain_params(case.params), "status": "error",
                       "error": f"{type(exc).__name__}: {exc}", "metrics": {}, "seconds": None}
            write_record(out, rec)
            fut.release()
            ran += 1
            failed += rec["status"] != "ok"
    finally:
        if own is not None:
            cluster = getattr(own, "cluster", None)
            own.close()
            if cluster is not None and scheduler is None:
                cluster.close()
    return ran, failed


def finish_sweep(spec: SweepSpec, out: Path, *, ran: int = 0, failed: int = 0, seconds: float = 0.0,
                 n_cases: int | None = None) -> SweepResult:
    """Rebuild the table and the report from the case records on disk."""
    ids = {c.id for c in expand_cases(spec)}
    records = [r for k, r in read_records(out).items() if k in ids]
    df = results_table(records, list(spec.axes))
    write_table(df, out)
    write_report(df, spec, out)
    n = n_cases if n_cases is not None else len(ids)
    return SweepResult(out, df, ran=ran, skipped=n - ran, failed=int((df["status"] != "ok").sum()) if len(df) else 0,
                       seconds=seconds)

