"""``tofhil diagnose`` and ``tofhil demo``."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Optional

import typer

from tofhil.outputs import refuse_existing
from tofhil.cli import app, console, lit, new_output_dir, out
from tofhil.cli import options as opt
from tofhil.errors import TofhilError


def _progress_printer() -> callable:
    start = time.monotonic()

    def show(message: str) -> None:
        console.print(f"[dim]{time.monotonic() - start:6.1f} s[/dim]  {lit(message)}", highlight=False)

    return show


def _summary(res, report: Path) -> None:
    from tofhil.cli.evaluate import RMSE_LABEL, rmse_footnote
    from tofhil.eval.diagnose.report import headline

    g = res.gain
    out.print(f"[bold]{lit(headline(res))}[/bold]", highlight=False)
    if res.verdict is not None:
        out.print(f"[bold]verdict:[/bold] {lit(res.verdict.text)}", highlight=False)
    if res.left:
        out.print(f"[bold]{lit(res.left)}[/bold]", highlight=False)
    if res.defects.get("pixels"):
        out.print(f"[bold]defects:[/bold] {lit(res.defects['text'])}", highlight=False)
    for r in res.channel_table.get("after", {}).get("readings", []):
        if r["significant"]:  # what is left in a channel after the fit
            z = f" (z = {r['z']:+.1f})" if r["z"] is not None else ""
            out.print(f"  left in a channel: {lit(r['text'])}{z}", highlight=False)
    if res.causes:
        for e, p in res.params.items():
            # a closed-form map reports its form and file, not numbers only
            form = f" ({res.forms[e]} form)" if res.forms.get(e) else ""
            out.print(f"  {e}{form}: " + ", ".join(f"{k} = {v:.4g}" if isinstance(v, (int, float)) else f"{k} = {v}"
                                                   for k, v in p.items()), highlight=False)
    if res.drift is not None and res.drift["named"]:
        out.print(f"[bold]drift:[/bold] {lit(res.drift['text'])}", highlight=False)
    worse = [c for c, v in res.channels.items() if v["worse"]]
    if worse:
        out.print(f"[bold red]worse after the fit:[/bold red] {', '.join(worse)}")
    for t in (res.effect_size or {}).get("fitted_too_small", {}).values():
        out.print(f"  fitted, not named: {lit(t)}", highlight=False)
    for r in res.residual_regions[:3]:
        out.print(f"  left above noise: {lit(r['text'])}", highlight=False)
    for f in res.structure[:8]:
        out.print(f"  residual: {lit(f['text'])}", highlight=False)
    out.print(f"held-out gain: {RMSE_LABEL} {g['depth_rmse_m']['before'] * 1e3:.1f} -> "
              f"{g['depth_rmse_m']['after'] * 1e3:.1f} mm (held-out pixels), amplitude RMSE {g['amplitude_rmse']['before']:.3g} -> {g['amplitude_rmse']['after']:.3g}, "
              f"misfit {res.chi2_per_value['before']:.2f} -> {res.chi2_per_value['after_extended_scene']:.2f} per value "
              f"(1.0 = noise)", highlight=False)
    if "ndt_score_per_point" in g:
        out.print(f"NDT score per point {g['ndt_score_per_point']['before']:.4g} -> {g['ndt_score_per_point']['after']:.4g}, "
                  f"ICP inlier RMSE {g['icp_inlier_rmse_m']['before'] * 1e3:.2f} -> {g['icp_inlier_rmse_m']['after'] * 1e3:.2f} mm",
                  highlight=False)
    for line in res.observability.lines:
        out.print(f"[bold]observability:[/bold] {lit(line)}", highlight=False)
    out.print(rmse_footnote("measured", "twin"), highlight=False, markup=False)
    out.print(f"report: {lit(report)}")


@app.command()
def diagnose(session: Path = typer.Argument(..., parser=opt.existing_file,
                                            help="A session with raw taps (2 frames or more)."),
             scene: str = typer.Option(..., "--scene", help="The twin's base scene (file or bundled name)."),
             out_dir: Path = typer.Option(..., "--out", parser=opt.out_dir,
                                          help="Directory for diagnosis.json, report.html, extended_scene.yaml."),
             max_effects: int = typer.Option(3, parser=opt.count(0, 50),
                                             help="Most effects to add (0: only the base twin's misfit; nothing searched)."),
             candidates: Optional[str] = typer.Option(None, help="Comma-separated effects to try (default: all)."),
             force: bool = typer.Option(False, "--force", help="Overwrite an earlier diagnosis in OUT."),
             max_memory: Optional[int] = typer.Option(None, "--max-memory", parser=opt.memory_size,
                                                      help="Refuse before the work when the estimated peak memory of each of its renders exceeds this (2G, 512M, bytes); without it: 70 % of the memory available."),
             view_save: Optional[Path] = typer.Option(
                 None, "--view-save", parser=opt.new_file,
                 help="Also write the diagnosis maps to this .rrd file for the Rerun viewer (pip install "
                      "'tofhil\\[view]').")) -> None:
    """Find what the twin gets wrong, fit it, write the extended scene and the held-out gain."""
    from tofhil.eval.diagnose.run import DRIFT, run_diagnosis
    from tofhil.sim.effects import ORDER

    if view_save is not None:
        from tofhil.app.view import check_view_output, require_rerun

        require_rerun("--view-save")
        check_view_output(view_save, force, field="--view-save")

    names = None
    if candidates:
        names = [c.strip() for c in candidates.split(",") if c.strip()]
        known = (*ORDER, DRIFT)  # the per-frame drift is a form of its own, not a scene effect
        unknown = [c for c in names if c not in known]
        if unknown:
            raise TofhilError(f"unknown effect(s) {', '.join(unknown)}", field="--candidates",
                              expected="names from " + ", ".join(known))
    from tofhil.session import open_session
    from tofhil.sim.memory import set_memory_limit

    set_memory_limit(max_memory)  # the twin's renders check it before each starts
    with open_session(session, need_frames=True) as s:  # nothing to diagnose: one line, before the work
        camera = s.camera
    if max_memory is not None:  # the first render's estimate, before the first progress line
        from tofhil.sim.memory import check_memory, render_memory
        from tofhil.sim.scene import load_scene

        base = load_scene(scene)
        check_memory(render_memory(base, {"camera": camera}), source=base.source)
    with new_output_dir(out_dir):
        res = run_diagnosis(session, scene, out_dir, force=force, progress=_progress_printer(),
                            max_effects=max_effects, candidates=names)
    _summary(res, out_dir / "report.html")
    if view_save is not None:
        from tofhil.app.view import log_diagnosis_maps

        logged = log_diagnosis_maps(res.maps, view_save, verdict=res.verdict.text if res.verdict else "")
        out.print(f"view: {len(logged)} maps -> {lit(view_save)}", highlight=False)


@app.command()
def demo(out_dir: Path = typer.Option(Path("demo-out"), "--out", parser=opt.out_dir,
                                      help="Directory for the demo's files."),
         frames: int = typer.Option(8, parser=opt.count(2, 10_000), help="Frames to capture from the emulated camera."),
         scene: str = typer.Option("bench_demo", help="Bundled scene or file the emulated camera looks at."),
         force: bool = typer.Option(False, "--force", help="Reuse OUT even if it holds an earlier demo.")) -> None:
    """The main job on the embedded default: capture from the emulated TOFcam635 (whose hidden
    truth differs from the twin), simulate the twin, compare, diagnose, extend the model, report."""
    from tofhil.drivers.base import CaptureSettings
    from tofhil.drivers.capture import capture
    from tofhil.drivers.tofcam635.emulator import EmulatedTofCam635, Epc635Emulator
    from tofhil.sim.sources import TOFCAM635_OVERRIDES, SimulatedSource
    from tofhil.eval.diagnose.run import run_diagnosis
    from tofhil.cli.evaluate import compare_line
    from tofhil.eval.compare import compare_sessions
    from tofhil.sim.pipeline import simulate_session
    from tofhil.sim.scene import load_scene
    from tofhil.sim.session_setup import write_twin_scene

    if frames < 2:
        raise TofhilError(f"is {frames}", field="--frames", expected="at least 2 (training and held-out frames)")
    names = ["capture.h5", "twin.h5", "twin_scene.yaml", "compare", "diagnosis", "summary.json"]
    if out_dir.exists() and not out_dir.is_dir():
        raise TofhilError("is a file, not a directory", file=out_dir, field="--out",
                          expected="a directory for the demo's files (new or existing)")
    if any((out_dir / n).exists() for n in names):
        refuse_existing(out_dir, force, what="already holds a demo", expected="an empty or new directory (or --force)")
    # The demo's inputs are emulated, so a demo that fails or is interrupted removes the folder
    # it created (a rerun is not blocked by half a demo); an existing folder is left as it was.
    with new_output_dir(out_dir):
        out_dir.mkdir(parents=True, exist_ok=True)
        show = _progress_printer()

        show(f"1/5 capturing {frames} frames from the emulated TOFcam635 looking at '{scene}' "
             "(its hidden truth: stray light, wiggling, a clock-skew pattern)")
        emulator = Epc635Emulator(SimulatedSource(scene))
        with EmulatedTofCam635("emulator", emulator=emulator) as dev:
            summary = capture(dev, out_dir / "capture.h5", frames, CaptureSettings(mode="dcs"), force=True)
        show(f"    {summary.frames_written} frames written, {summary.dropped} dropped, {summary.reconnects} reconnects")

        show("2/5 the twin: the same scene and camera model, without the hidden imperfections")
        # The twin runs with the capture's settings (the emulated TOFcam635 modulates at 20 MHz
        # whatever the scene's sensor block says): frequencies, tap phases, integration time and
        # camera from the capture, the rest from the scene.
        twin_path = out_dir / "twin_scene.yaml"
        twin, setup = write_twin_scene(load_scene(scene, overrides=TOFCAM635_OVERRIDES), out_dir / "capture.h5",
                                       twin_path)
        show(f"    {setup.note}")
        simulate_session(twin, out_dir / "twin.h5", frames=frames, seed=1, noise=True, force=True)

        show("3/5 comparing capture and twin (pixels, point clouds, NDT)")
        cmp = compare_sessions(out_dir / "capture.h5", out_dir / "twin.h5", out_dir / "compare", force=True)
        measured = cmp["variants"]["measured"]
        out.print("compare, capture - twin over all pixels: " + compare_line("", measured["regions"]["all"]).strip(),
                  highlight=False)
        for note in measured["notes"]:
            out.print(f"  {note}", highlight=False)

        show("4/5 diagnosing: fitting every effect of the library on training data, scoring on held-out data")
        res = run_diagnosis(out_dir / "capture.h5", twin_path, out_dir / "diagnosis", force=True, progress=show)
        show("5/5 done")
        _summary(res, out_dir / "diagnosis" / "report.html")
        out.print(f"comparison report: {lit(out_dir / 'compare' / 'report.html')}")
        (out_dir / "summary.json").write_text(json.dumps({"cause": res.cause, "causes": res.causes, "params": res.params,
                                                          "gain": res.gain}, indent=2, default=float))
