"""Run one bench procedure: spec sheet, rig, plan, campaign, analysis, verdict, report."""

from __future__ import annotations

import time
from pathlib import Path
from types import ModuleType
from typing import Any

from tofhil.app.bench import depth, interference, photon_transfer, relative_range, scattering, spheres, warmup
from tofhil.app.bench.base import BenchOptions, BenchResult, load_spec_sheet
from tofhil.app.campaign import CampaignInterrupted, run_campaign
from tofhil.errors import TofhilError
from tofhil.progress import Progress, no_progress

#: name -> module (each has NAME, SUMMARY, make_rig, make_plan, analyse).
PROCEDURES: dict[str, ModuleType] = {photon_transfer.NAME: photon_transfer}
for _family in (depth, scattering, spheres, relative_range, warmup, interference):
    PROCEDURES.update({p.NAME: p for p in _family.PROCEDURES})


def procedure_list() -> list[tuple[str, str]]:
    """``(name, one line)`` of every procedure."""
    return [(name, mod.SUMMARY) for name, mod in PROCEDURES.items()]


def run_bench(procedure: str, device: str, out_dir: str | Path, *, spec: str | Path | None = None,
              options: BenchOptions | None = None, resume: bool = False, force: bool = False,
              progress: Progress = no_progress, report: bool = True) -> BenchResult:
    """Run ``procedure`` on ``device`` into ``out_dir``: ``campaign.json`` and ``sessions/`` (the
    captures, resumable), ``report.html``, ``figures.json``, ``curves.parquet`` and the
    procedure's own files. The spec sheet is read first: a bad one stops before any capture."""
    from tofhil.app.bench.report import write_report

    opts = options or BenchOptions()
    mod = PROCEDURES.get(procedure)
    if mod is None:
        raise TofhilError(f"no procedure {procedure!r}", field="PROCEDURE",
                          expected="one of " + ", ".join(PROCEDURES) + " (tofhil bench --list)")
    sheet = load_spec_sheet(spec) if spec is not None else None
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise TofhilError("is a file, not a directory", file=out, field="--out", expected="a directory")
    t0 = time.monotonic()
    rig = mod.make_rig(device, opts)
    try:
        plan = mod.make_plan(opts, rig)
        setup = time.monotonic() - t0
        campaign = run_campaign(plan, rig, out, resume=resume, force=force, progress=progress,
                                extra={"procedure": procedure, "options": _options_record(opts)})
        try:
            result = mod.analyse(campaign, rig, opts)
        except KeyboardInterrupt:  # the captures are all recorded: say so, and how to finish
            n = len(campaign.captures)
            raise CampaignInterrupted(out, n, n) from None
    finally:
        rig.close()
    result.seconds = {"setup": setup, **campaign.seconds, **result.seconds}
    if getattr(rig, "render_s", 0.0) > 0:  # part of the captures' time: the emulator rendering its bench
        result.seconds["capture_emulator_render"] = rig.render_s
    result.details["campaign"] = {"taken": campaign.taken, "skipped": campaign.skipped}
    if sheet is not None:
        result.verdict = sheet.verdict(result.figures)
        result.details["spec_sheet"] = {"name": sheet.name, "file": sheet.source}
    if report:  # (tests that read only the figures skip the page)
        t1 = time.monotonic()
        try:
            write_report(result, out)
        except KeyboardInterrupt:
            n = len(campaign.captures)
            raise CampaignInterrupted(out, n, n) from None
        result.seconds["report"] = time.monotonic() - t1
    return result


def _options_record(opts: BenchOptions) -> dict[str, Any]:
    return {"frames": opts.frames, "seed": opts.seed, "scene": opts.scene, "distances_m": list(opts.distances_m),
            "integration_time_us": opts.integration_time_us, "mod_freq_hz": opts.mod_freq_hz,
            "roi": opts.roi, "hidden": opts.hidden}
