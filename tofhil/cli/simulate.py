"""``tofhil simulate`` and ``tofhil effects``: the simulator twin on the command line."""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

from tofhil.cli import app, lit, out, print_json, progress
from tofhil.cli import options as opt
from tofhil.errors import TofhilError
from tofhil.yamlio import load_yaml


def _parse_assignments(items: List[str], option: str) -> dict:
    """``["a=1", "b.c=x"]`` -> nested mapping with YAML-typed values."""
    result: dict = {}
    for item in items:
        if "=" not in item:
            raise TofhilError(f"got {item!r}", field=option, expected="NAME=VALUE")
        key, _, text = item.partition("=")
        try:
            value = load_yaml(text, source=option)  # 1e-12 is a number (YAML 1.2), as in scene files
        except TofhilError:
            value = text
        node = result
        parts = key.strip().split(".")
        for p in parts[:-1]:
            node = node.setdefault(p, {})
        node[parts[-1]] = value
    return result


@app.command()
def simulate(scene: str = typer.Argument(..., help="A scene file (.yaml) or a bundled scene name."),
             out_path: Path = typer.Option(..., "--out", parser=opt.new_file, help="The session file to write (.h5)."),
             frames: int = typer.Option(1, "--frames", parser=opt.count(1, 1_000_000), help="Number of frames."),
             seed: int = typer.Option(0, "--seed", parser=opt.count(0, 2**63 - 1, what="a seed"),
                                      help="Noise seed: the same seed gives identical frames."),
             no_noise: bool = typer.Option(False, "--no-noise", help="Noise-free taps (exact expectation)."),
             param: List[str] = typer.Option([], "--param", help="Scene parameter NAME=VALUE (repeatable)."),
             effect: List[str] = typer.Option([], "--effect",
                                              help="Effect parameter EFFECT.PARAM=VALUE, added to the "
                                                   "scene's effects block (repeatable)."),
             no_effects: bool = typer.Option(False, "--no-effects", help="Ignore the scene's effects block."),
             report: Optional[Path] = typer.Option(None, "--report",
                                                   help="Also write DIR/report.html: each pixel's light by bounce "
                                                        "and by source object, a direct-ToF scene's histograms, a "
                                                        "lens prescription's ghost PSFs."),
             max_memory: Optional[int] = typer.Option(None, "--max-memory", parser=opt.memory_size,
                                                      help="Refuse before the work when the estimated peak memory of a render exceeds this (2G, 512M, bytes); without it: 70 % of the memory available."),
             force: bool = typer.Option(False, "--force", help="Overwrite OUT (and the report) if it exists.")) -> None:
    """Render a scene through the twin (effects, sensor, noise) into a session file with raw taps
    and depth, the scene text embedded; a scene with a direct_tof block gives SPAD histograms and
    the depth of their peaks instead of taps."""
    from tofhil.sim.memory import set_memory_limit
    from tofhil.sim.pipeline import write_simulation
    from tofhil.sim.scene import load_scene

    set_memory_limit(max_memory)  # checked against the render's estimate before it starts
    overrides = {"params": _parse_assignments(param, "--param")} if param else None
    sc = load_scene(scene, overrides=overrides)
    effects = None
    if no_effects or effect:
        effects = {} if no_effects else {k: dict(v or {}) for k, v in sc.effects.to_block().items()}
        for name, values in _parse_assignments(effect, "--effect").items():
            if not isinstance(values, dict):
                raise TofhilError(f"got {name}={values!r}", field="--effect", expected="EFFECT.PARAM=VALUE")
            effects.setdefault(name, {}).update(values)
        from tofhil.sim.effects import parse_effects

        parse_effects(effects, source=f"{sc.source} with --effect")  # errors name the option
    if report is not None:
        from tofhil.eval.reports.simulate import OUTPUTS
        from tofhil.outputs import prepare_output_dir

        prepare_output_dir(report, OUTPUTS, force=force)  # refuse before the (slow) render
    # The renderer traces no multipath shares through glass or media: such a scene's report
    # says so and draws the rest (the tour's `simulate glass_pane --report DIR` was refused).
    media = any(m.ior is not None or m.scattering_per_m > 0 for m in sc.materials.values())
    shares = report is not None and not media
    sim = write_simulation(sc, out_path, frames=frames, seed=seed, noise=not no_noise, force=force,
                           effects=effects, progress=progress, multipath_shares=shares)
    path = sim.path
    if report is not None:
        from tofhil.eval.reports.simulate import write_simulate_report

        notes = [] if shares else ["multipath shares are not computed through glass or scattering media: "
                                   "the scene has a material with ior or scattering_per_m"]
        write_simulate_report(report, sc, shares=sim.multipath_shares(sc) if shares else None, direct=sim.direct,
                              session_path=path, force=force, notes=notes)
    out.print(f"wrote {frames} simulated frame{'s' if frames != 1 else ''} of {lit(sc.name or scene)} to {lit(path)}")
    if report is not None:
        out.print(f"report: {lit(report / 'report.html')}")


@app.command("effects")
def list_effects(as_json: bool = typer.Option(False, "--json", help="Print JSON instead of a table."),
                 name: Optional[str] = typer.Argument(None, help="Show one effect only.")) -> None:
    """List the twin's effects: stage, parameters with off values, bounds and units."""
    from tofhil.sim.effects import describe_effects

    items = describe_effects()
    if name is not None:
        items = [e for e in items if e["name"] == name]
        if not items:
            raise TofhilError(f"unknown effect {name!r}", field="name",
                              expected="one of " + ", ".join(e["name"] for e in describe_effects()))
    if as_json:
        print_json(items)
        return
    for e in items:
        out.print(f"[bold]{lit(e['name'])}[/bold] ({lit(e['stage'])}): {lit(e['doc'])}")
        for p, d in e["params"].items():
            out.print(f"    {p:16s} off={d['off']:<10g} [{d['lo']:g}, {d['hi']:g}] {d['unit']:8s} {d['doc']}",
                      highlight=False, markup=False)
        for o, doc in e["options"].items():
            out.print(f"    {o:16s} (option) {doc}", highlight=False, markup=False)
