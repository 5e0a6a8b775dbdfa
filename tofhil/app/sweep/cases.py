"""The cases of a sweep: the design expanded into cases, and what one case simulates.

A case is one combination of axis values (grid) or one draw (random, from the design's
seed), with an id ``INDEX-DIGEST`` that stays the same as long as the spec's cases do
(``--resume`` relies on it). :func:`case_effects` and :func:`case_scene` turn its values
into the effects it simulates and the scene it is rendered from.
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import itertools
import json
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Mapping

import numpy as np

if TYPE_CHECKING:
    from tofhil.app.sweep.spec import SweepSpec


@dataclass
class Case:
    """One case: its id (index and a digest of its parameters) and its axis values."""

    id: str
    index: int
    params: dict[str, Any]


def digest(x: Any) -> str:
    """A short stable digest of a JSON-able value (case ids, the spec's fingerprint)."""
    return hashlib.sha256(json.dumps(x, sort_keys=True, default=str).encode()).hexdigest()[:10]


def _draw(rng: np.random.Generator, dist: Any) -> Any:
    """One value of an axis in a random design: an element of its list, or a draw from its distribution."""
    if isinstance(dist, list):
        return copy.deepcopy(dist[int(rng.integers(len(dist)))])
    (form, (lo, hi)), = dist.items()
    if form == "uniform":
        return float(rng.uniform(lo, hi))
    if form == "log_uniform":
        return float(np.exp(rng.uniform(np.log(lo), np.log(hi))))
    return int(rng.integers(int(lo), int(hi) + 1))


def expand_cases(spec: SweepSpec) -> list[Case]:
    """Every case of the design, in a fixed order (a random design is drawn from
    ``design.seed``, so the same spec gives the same cases)."""
    names = list(spec.axes)
    if spec.design == "grid":
        combos = [dict(zip(names, vals)) for vals in itertools.product(*(spec.axes[n] for n in names))]
    else:
        rng = np.random.default_rng(spec.design_seed)
        combos = [{n: _draw(rng, spec.axes[n]) for n in names} for _ in range(spec.n)]
    return [Case(f"{i:04d}-{digest(c)}", i, c) for i, c in enumerate(combos)]


def effects_label(effects: Mapping[str, Any]) -> str:
    """An effect set's name in the table: its effects joined by '+', or 'none'."""
    return "+".join(sorted(effects)) or "none"


def case_effects(spec: SweepSpec, params: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
    """The effects a case simulates on top of the scene's own: the spec's ``effects``, the
    case's effect set (``effects`` axis), then its single effect parameters."""
    eff = {k: dict(v) for k, v in spec.effects.items()}
    for k, v in (params.get("effects") or {}).items():
        eff.setdefault(k, {}).update(v)
    for name, value in params.items():
        parts = name.split(".")
        if parts[0] == "effects" and len(parts) == 3:
            eff.setdefault(parts[1], {})[parts[2]] = value
    return eff


def case_scene(spec: SweepSpec, params: Mapping[str, Any], overrides: Mapping[str, Any] | None = None) -> Any:
    """The scene of a case (scene parameters, camera preset and scale applied, then
    ``overrides`` such as an emulated device's camera); its own ``effects:`` block is what
    the twin models."""

    ov: dict[str, Any] = dict(overrides or {})
    sp = {k.split(".", 1)[1]: v for k, v in params.items() if k.startswith("params.")}
    if sp:
        ov["params"] = sp
    return load_with_camera(spec.scene, params, ov)


def load_with_camera(scene_ref: str, params: Mapping[str, Any], overrides: Mapping[str, Any] | None = None) -> Any:
    """Load a scene with a case's ``camera.preset`` (resolved at load: the preset's sensor
    settings come with it) and ``camera.scale`` (the sensor resampled)."""
    from tofhil.sim.scene import load_scene

    ov = dict(overrides or {})
    if "camera.preset" in params:
        ov["camera"] = {"preset": params["camera.preset"]}
    scene = load_scene(scene_ref, overrides=ov or None)
    scale = params.get("camera.scale")
    if scale is not None and scale != 1.0:
        scene = dataclasses.replace(scene, camera=scene.camera.scaled(float(scale)))
    return scene

