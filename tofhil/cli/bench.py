"""``tofhil bench PROCEDURE``: bench procedures with the twin's prediction and a spec-sheet verdict."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Optional

import typer

from tofhil.cli import app, console, lit, out, progress
from tofhil.errors import TofhilError


def _floats(text: str, field: str) -> tuple[float, ...]:
    try:
        vals = tuple(float(x) for x in text.split(",") if x.strip())
    except ValueError:
        vals = ()
    if not vals or not all(0 < v < math.inf for v in vals):
        raise TofhilError(f"{field} {text!r}", field=field, expected="comma-separated positive numbers")
    return vals


def _hidden(items: list[str]) -> dict[str, Any]:
    """``range_scale=0.005``, ``range_offset.path_m=0.02``, ``wiggling.h3_amplitude=0.03``."""
    out_: dict[str, Any] = {}
    for item in items:
        if item == "emulator":  # the emulated camera's own hidden truth
            out_["emulator"] = True
            continue
        key, eq, val = item.partition("=")
        try:
            value = float(val)
        except ValueError:
            value = None
        if not eq or value is None or not key:
            raise TofhilError(f"--hidden {item!r}", field="--hidden",
                              expected="range_scale=EPS or EFFECT.PARAM=VALUE (an effect of tofhil effects)")
        if key == "thermal_drift_m_per_c":
            out_[key] = value
            continue
        if "." in key:
            eff, _, par = key.partition(".")
            out_.setdefault(eff, {})[par] = value
        else:
            out_[key] = value
    return out_


def _roi(text: str | None) -> tuple[int, int, int, int] | None:
    if text is None:
        return None
    try:
        roi = tuple(int(v) for v in text.split(","))
    except ValueError:
        roi = ()
    if len(roi) != 4 or roi[2] <= roi[0] or roi[3] <= roi[1] or min(roi) < 0:
        raise TofhilError(f"--roi {text!r}", field="--roi", expected="X0,Y0,X1,Y1 (X1 > X0, Y1 > Y0; half-open)")
    return roi  # type: ignore[return-value]


def _prompt(message: str) -> None:
    console.print(f"[bold]bench:[/bold] {lit(message)}")
    typer.confirm("done?", default=True, abort=True, err=True)


@app.command("bench")
def bench(procedure: Optional[str] = typer.Argument(None, help="The procedure (tofhil bench --list)."),
          device: Optional[str] = typer.Option(None, "--device", help="emulator[:FILE], depthai-sim[:SCENE], usb, "
                                               "serial:PORT, replay:S.h5 (tofhil devices)."),
          out_dir: Optional[Path] = typer.Option(None, "--out", help="Directory for the captures (sessions/, "
                                                 "campaign.json), report.html, figures.json, curves.parquet."),
          spec: Optional[Path] = typer.Option(None, "--spec", help="Spec sheet (YAML): the vendor's figures."),
          list_: bool = typer.Option(False, "--list", help="List the procedures, one a line."),
          frames: int = typer.Option(8, "--frames", help="Frames per capture."),
          seed: int = typer.Option(0, "--seed", help="Seed of an emulated bench's noise."),
          scene: Optional[str] = typer.Option(None, "--scene", help="The twin's scene (or flat-field bench file)."),
          distances: Optional[str] = typer.Option(None, "--distances", help="Target distances in metres, e.g. "
                                                  "0.6,1.0,1.4 (accuracy-vs-distance; relative-range: the reference range, "
                                                  "then the test ranges)."),
          levels: Optional[str] = typer.Option(None, "--levels", help="ambient: irradiances in W/m² (0,5,20); "
                                               "dark-squares: square reflectances relative to the wall (0.5,0.1,0.02); interference: the "
                                               "second camera's irradiance on the target in W/m² (0.1)."),
          lengths: Optional[str] = typer.Option(None, "--lengths", help="spheres: the bar's lengths (sphere "
                                                "spacings) in metres (0.15,0.3,0.5)."),
          captures: Optional[int] = typer.Option(None, "--captures", help="warm-up: number of captures (12)."),
          interval_s: Optional[float] = typer.Option(None, "--interval-s", help="warm-up: seconds between captures (10)."),
          integration_time_us: Optional[float] = typer.Option(None, "--integration-time-us"),
          mod_freq_hz: Optional[float] = typer.Option(None, "--mod-freq-hz"),
          roi: Optional[str] = typer.Option(None, "--roi", help="X0,Y0,X1,Y1 region (default: the centre fifth)."),
          hidden: list[str] = typer.Option([], "--hidden", help="Emulated bench only: hidden truth, e.g. "
                                           "range_scale=0.005, range_offset.path_m=0.02, or emulator (the emulated "
                                           "camera's own: stray light, wiggling, fixed pattern); repeatable."),
          diagnose: bool = typer.Option(False, "--diagnose", help="Where measured and predicted disagree, run "
                                        "tofhil diagnose on the capture that differs most (tens of seconds)."),
          resume: bool = typer.Option(False, "--resume", help="Continue an interrupted campaign in OUT."),
          force: bool = typer.Option(False, "--force", help="Start over in OUT.")) -> None:
    """Run a bench procedure: its captures (resumable), the metrics, the twin's prediction beside
    them and the verdict against a spec sheet, as a report."""
    from tofhil.app.bench import BenchOptions, procedure_list, run_bench

    if list_:
        for name, summary in procedure_list():
            out.print(f"{name}: {summary}", highlight=False, markup=False, soft_wrap=True)
        return
    if procedure is None or device is None or out_dir is None:
        raise TofhilError("PROCEDURE, --device and --out are needed", field="PROCEDURE",
                          expected="tofhil bench PROCEDURE --device DEV --out DIR (or --list)")
    if frames < 1:
        raise TofhilError(f"--frames {frames}", field="--frames", expected="a positive number of frames")
    opts = BenchOptions(frames=frames, seed=seed, scene=scene, integration_time_us=integration_time_us,
                        mod_freq_hz=mod_freq_hz, roi=_roi(roi), hidden=_hidden(hidden), prompt=_prompt,
                        extra={"diagnose": diagnose})
    if distances:
        opts.distances_m = _floats(distances, "--distances")
    if levels:
        try:
            vals = tuple(float(x) for x in levels.split(",") if x.strip())
        except ValueError:
            vals = ()
        if not vals or not all(0 <= v < math.inf for v in vals) or (procedure == "dark-squares" and not all(v > 0 for v in vals)):
            raise TofhilError(f"--levels {levels!r}", field="--levels", expected="comma-separated numbers >= 0 "
                              "(dark-squares: > 0)")
        if procedure == "interference":  # the second camera's irradiance on the target
            if len(vals) != 1 or not vals[0] > 0:
                raise TofhilError(f"--levels {levels!r}", field="--levels",
                                  expected="interference: one irradiance > 0 (W/m²)")
            opts.extra["interferer_w_m2"] = vals[0]
        else:
            opts.extra["ambient_w_m2" if procedure == "ambient" else "square_reflectances"] = vals
    if lengths:
        if procedure != "spheres":
            raise TofhilError(f"--lengths {lengths!r}", field="--lengths", expected="the spheres procedure")
        opts.extra["spheres_lengths_m"] = _floats(lengths, "--lengths")
    if captures is not None:
        if captures < 2:
            raise TofhilError(f"--captures {captures}", field="--captures", expected="2 or more")
        opts.extra["warmup_captures"] = captures
    if interval_s is not None:
        if not interval_s >= 0:
            raise TofhilError(f"--interval-s {interval_s}", field="--interval-s", expected="seconds >= 0")
        opts.extra["warmup_interval_s"] = interval_s
    res = run_bench(procedure, device, out_dir, spec=spec, options=opts, resume=resume, force=force,
                    progress=progress)
    for row in res.verdict:
        out.print(f"{row['verdict']:>12}  {row['figure']}: {row['value']:.4g} (spec {row['limit']} {row['unit']})",
                  highlight=False, markup=False)
    for f in res.figures:
        pred = f"  twin {f.predicted:.4g}" if f.predicted == f.predicted else ""
        pm = f" ± {f.sigma:.2g}" if f.sigma == f.sigma else ""
        out.print(f"{f.name}: {f.value:.4g}{pm} {f.unit}{pred}", highlight=False, markup=False)
    for line in res.findings:
        out.print(line, highlight=False, markup=False, soft_wrap=True)
    spent = ", ".join(f"{k} {v:.1f} s" for k, v in res.seconds.items() if v > 0.05)
    out.print(f"report: {lit(out_dir / 'report.html')} ({spent})")
