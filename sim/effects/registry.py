"""The effect registry and the forward model's application of effects.

An effect family's module defines its classes and registers each with :func:`register`; the
registry keeps one instance per effect name in :data:`EFFECTS`, in forward-model order
(:data:`ORDER`: by each effect's ``rank``, whatever order the modules are imported in).
Today's order (optics before the pixel; per-pixel effects after the spatial mixing)::

    pose, lens_distortion, reflectance, ambient        scene stage: what is rendered
    multipath                                          render stage: the render recombined
    illumination, stray_light, offset,                 signal stage: light on the sensor
    range_offset, field_angle,
    fixed_pattern, range_offset_map                    pixel stage: demodulation per pixel
    amplitude_dependent, wiggling                      signal stage, applied after the pixel stage

A new effect is one new module (a class with ``name``, ``stage``, ``rank``, ``params`` and
its stage's hook, decorated with :func:`register`), imported by the package ``__init__``.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Mapping

from tofhil.errors import InputFileError
from tofhil.schema import to_plain
from tofhil.sim.effects.base import DEFAULT_SEPARATION, STAGE_HOOKS, STAGES, Effect, EffectContext, Separation
import numpy as np

from tofhil.sim.sensor import OpticalSignal

#: Every effect by name, in forward-model order (filled by :func:`register`).
EFFECTS: dict[str, Effect] = {}
#: The effect names in forward-model order: the order every stage applies them in.
ORDER: tuple[str, ...] = ()


def register(cls: type[Effect]) -> type[Effect]:
    """Class decorator: put an instance of the effect ``cls`` in the registry, at its place in
    the forward-model order (its ``rank``). Refuses a name or a rank taken, a stage that does
    not exist and an effect that does not implement its stage's hook."""
    global ORDER
    eff = cls()
    hook = STAGE_HOOKS.get(eff.stage)
    if not eff.name or hook is None or getattr(cls, hook) is getattr(Effect, hook):
        raise TypeError(f"{cls.__name__}: an effect needs a name, a stage in {STAGES} and that stage's hook")
    if eff.name in EFFECTS or any(e.rank == eff.rank for e in EFFECTS.values()) or not eff.rank > 0:
        raise TypeError(f"{cls.__name__}: effect name {eff.name!r} or rank {eff.rank} already registered (or rank <= 0)")
    ranked = sorted([*EFFECTS.values(), eff], key=lambda e: e.rank)
    EFFECTS.clear()
    EFFECTS.update((e.name, e) for e in ranked)
    ORDER = tuple(EFFECTS)
    return cls


def separation(a: str, b: str) -> Separation:
    """The capture that tells effect ``a`` from effect ``b`` (declared on either one's
    ``mimicked_by``), else :data:`~tofhil.sim.effects.base.DEFAULT_SEPARATION`. Names that are
    not effects (a test's stand-ins) get the default too."""
    for x, y in ((a, b), (b, a)):
        found = getattr(EFFECTS.get(x), "mimicked_by", {}).get(y)
        if found is not None:
            return found
    return DEFAULT_SEPARATION


class ParsedEffects(dict):
    """An effect set as :func:`parse_effects` returns it: validated, defaults filled, in
    forward-model order. Read it, do not change it: the twin takes it as it is instead of
    validating it again (a fit predicts thousands of times, each through several of the
    twin's methods). A subset of one, in its order, is one too."""


def parse_effects(block: Mapping[str, Any] | None, *, source: str | Path = "<effects>") -> ParsedEffects:
    """Validate an ``effects:`` block into ``{name: values}`` in forward-model order.

    ``{name: null}`` or ``{name: {}}`` switches the effect on with its defaults; ``{name:
    {enabled: false, ...}}`` keeps it off."""
    block = {} if block is None else block
    if not isinstance(block, Mapping):
        raise InputFileError(f"got {block!r}", file=source, field="effects",
                             expected="a mapping effect name -> parameters")
    for name in block:
        if name not in EFFECTS:
            raise InputFileError(f"unknown effect {name!r}", file=source, field=f"effects.{name}",
                                 expected="one of " + ", ".join(ORDER))
    out: dict[str, dict[str, Any]] = {}
    for name in ORDER:
        if name not in block:
            continue
        raw = dict(block[name] or {})
        enabled = raw.pop("enabled", True)
        if not isinstance(enabled, bool):
            raise InputFileError(f"got {enabled!r}", file=source, field=f"effects.{name}.enabled",
                                 expected="true or false")
        if enabled:
            out[name] = EFFECTS[name].validate(raw, source=source)
    return ParsedEffects(out)


def effects_by_stage(effects: Mapping[str, Mapping[str, Any]], *stages: str) -> list[tuple[Effect, Mapping[str, Any]]]:
    return [(EFFECTS[n], effects[n]) for n in ORDER if n in effects and EFFECTS[n].stage in stages]


def apply_scene_effects(scene: Any, effects: Mapping[str, Mapping[str, Any]]) -> Any:
    """The Scene with every scene-stage effect applied (a new Scene; the input is unchanged)."""
    for eff, values in effects_by_stage(effects, "scene"):
        if not eff.is_off(values):
            scene = eff.apply_scene(scene, values)
    return scene


def apply_signal_effects(signal: OpticalSignal, effects: Mapping[str, Mapping[str, Any]],
                         ctx: EffectContext) -> OpticalSignal:
    """Signal- and pixel-stage effects in forward-model order."""
    for eff, values in effects_by_stage(effects, "signal", "pixel"):
        if not eff.is_off(values):
            signal = eff.apply_signal(signal, values, ctx)
    return signal


def apply_tap_effects(taps: np.ndarray, effects: Mapping[str, Mapping[str, Any]], ctx: EffectContext) -> np.ndarray:
    """Taps-stage effects in forward-model order (the readout after the pixel)."""
    for eff, values in effects_by_stage(effects, "taps"):
        if not eff.is_off(values):
            taps = eff.apply_taps(taps, values, ctx)
    return taps


def render_requirements(effects: Mapping[str, Mapping[str, Any]], scene: Any) -> dict[str, Any]:
    """Renderer arguments the effects need (merged)."""
    req: dict[str, Any] = {}
    for eff, values in effects_by_stage(effects, "render"):
        req.update(eff.render_requirements(values, scene))
    return req


def effects_to_block(effects: Mapping[str, Mapping[str, Any]]) -> dict[str, dict[str, Any]]:
    """Plain (YAML/JSON-safe) form of parsed effects, for embedding in files."""
    return {n: to_plain(dict(v)) for n, v in effects.items()}


def describe_effects() -> list[dict[str, Any]]:
    """Every effect's name, stage, meaning, parameters (off, bounds, unit) and options."""
    return [EFFECTS[n].describe() for n in ORDER]


def _num(x: float) -> str:
    if x in (math.pi, -math.pi):
        return "-pi" if x < 0 else "pi"
    return f"{x:g}"


def effects_table_markdown() -> str:
    """The table of effects in docs/effects.md, from the registry: stage, each parameter's
    off value, bounds, unit and default, what diagnosis fits (range, step, log scale,
    start and extra starts) and what the effect models."""
    rows = ["| effect | stage | parameters: off / [lo, hi] unit / default | diagnosis fits: range (step) [start; also] "
            "| what it models |", "|---|---|---|---|---|"]
    for name in ORDER:
        e = EFFECTS[name]
        params, fits = [], []
        for k, p in e.params.items():
            text = f"`{k}` {_num(p.off)} / [{_num(p.lo)}, {_num(p.hi)}]" + (f" {p.unit}" if p.unit else "")
            if p.default is not None:
                text += f" / {_num(p.default)}"
            params.append(text)
            if p.fit is not None:
                scale = "log10 " if p.log else ""
                text = f"`{k}` {scale}[{_num(p.fit[0])}, {_num(p.fit[1])}] ({_num(p.step)})"
                tries = ([] if p.start is None else [f"start {_num(p.start)}"])
                tries += [f"also {', '.join(_num(v) for v in p.starts)}"] if p.starts else []
                if tries:
                    text += " [" + "; ".join(tries) + "]"
                if p.forms != ("",):
                    text += " {" + ", ".join(f"form `{f}`" if f else "simple form" for f in p.forms) + "}"
                fits.append(text)
        rows.append(f"| `{name}` | {e.stage} | {'; '.join(params)} | {'; '.join(fits) or '-'} | {e.summary} |")
    return "\n".join(rows) + "\n"
