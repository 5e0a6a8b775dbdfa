"""Sweeps: many cases of simulate / compare / diagnose, one table of results, on Dask.

A sweep spec (YAML, :func:`load_spec`) names a scene, the axes to vary (scene parameters,
effect parameters, whole effect sets, camera presets, a camera scale, seeds) and a design
(``grid``: every combination; ``random``: ``n`` draws). Each case is one task: it simulates
a session (or takes a given one, for a batch over recorded sessions), compares it against
the twin or a reference session, and diagnoses it against the twin, as the spec says.

Execution is on ``dask.distributed``: a ``LocalCluster`` of processes on this machine by
default, or an existing cluster (``scheduler``). ``workers=0`` runs the cases one by one in
this process (no Dask). Every finished case is written at once as ``cases/CASE_ID.json``
(atomically); the table (``results.parquet``, ``results.csv``) and ``report.html`` are
rebuilt from those files, so a killed sweep resumes (``resume=True``) without redoing what
finished. A case that fails is recorded with its error; the others go on.

Renders are cached per worker process: cases whose scene has the same content (e.g. seeds,
or effects that act after the render) share one :class:`tofhil.sim.twin.Twin` and so one
render. The files a case writes (sessions, compare and diagnosis reports) go to
``cases/CASE_ID/``: with a remote cluster the output directory must be on a file system the
workers share.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import glob
import itertools
import json
import math
import os
import shutil
import time
import traceback
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Mapping, Sequence

import numpy as np
import yaml

from tofhil.errors import InputFileError, Interrupted, TofhilError
from tofhil.progress import Progress, no_progress
from tofhil.schema import Schema

SPEC_KEYS = ("name", "description", "scene", "sessions", "reference", "axes", "design", "frames", "noise", "seed",
             "effects", "simulate", "capture", "calibrate", "compare", "diagnose", "keep_sessions", "report")
#: Axis names: ``params.NAME`` (a scene parameter), ``effects.EFFECT.PARAM``, ``effects`` (a
#: whole effect set per value), ``camera.preset``, ``camera.scale``, ``seed``, ``session``.
FIXED_AXES = ("effects", "camera.preset", "camera.scale", "seed", "session")
#: Acquisition settings a capture case sets on the device (``capture.NAME`` axes and keys).
CAPTURE_SETTINGS = ("integration_time_us", "mod_freq_hz", "channel", "min_amplitude")
CAPTURE_KEYS = ("device", "frames", "mode", "roi", "timeout_s") + CAPTURE_SETTINGS
CALIBRATE_KEYS = ("scene", "captures", "reference", "frames", "form", "ghost_center")
#: A correction's ``psf=`` value that means the PSF this sweep calibrated (``calibrate``).
CALIBRATED_PSF = "@calibration"
#: The device scheme whose bench the sweep may change: the in-process emulator renders each
#: case's scene (its parameters, effects and seed); a real device's bench is what it is.
EMULATED_BENCH = "emulator"
DISTRIBUTIONS = ("uniform", "log_uniform", "integers", "choice")
GRID_FORMS = ("linspace", "logspace")
OUTPUTS = ("results.parquet", "results.csv", "report.html", "spec.yaml", "cases")


# ----------------------------------------------------------------------------- the spec
@dataclass
class SweepSpec:
    """A validated sweep. ``axes`` maps an axis name to its values (grid) or distribution
    (random); ``base_dir`` resolves relative paths of the spec."""

    name: str
    scene: str | None
    axes: dict[str, Any]
    design: str = "grid"
    n: int = 0
    design_seed: int = 0
    frames: int = 4
    noise: bool = True
    seed: int = 0
    effects: dict[str, dict[str, Any]] = field(default_factory=dict)
    simulate: bool = True
    #: Capture each case from a device instead of simulating it (``device``, settings).
    capture: dict[str, Any] | None = None
    #: One stray-light PSF calibration before the cases (``psf:psf=@calibration`` uses it).
    calibrate: dict[str, Any] | None = None
    compare: dict[str, Any] | None = None
    diagnose: dict[str, Any] | None = None
    reference: str | None = None
    keep_sessions: bool = True
    report_metrics: list[str] = field(default_factory=list)
    description: str = ""
    source: str = "<spec>"
    base_dir: str = "."
    text: str = ""

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def _resolve_path(value: str, base_dir: Path) -> str:
    p = Path(value).expanduser()
    return str(p if p.is_absolute() else (base_dir / p))


def _scene_ref(value: str, base_dir: Path) -> str:
    """A bundled scene name stays a name; anything that looks like a path is resolved."""
    if Path(value).suffix or "/" in value:
        return _resolve_path(value, base_dir)
    return value


def parse_spec(data: Any, *, source: str = "<spec>", base_dir: str | Path = ".", text: str = "") -> SweepSpec:
    """Validate a spec mapping: every error names the file and the field."""
    from tofhil.sim.effects import EFFECTS

    s = Schema(source)
    base = Path(base_dir)
    d = s.mapping(data, "", allowed=SPEC_KEYS, none_ok=False, expected="a sweep spec mapping")
    scene = d.get("scene")
    sessions = d.get("sessions")
    if scene is None and sessions is None:
        raise s.error("missing", "scene", "a scene (bundled name or YAML file) to simulate, or 'sessions' to batch over")
    if scene is not None:
        scene = _scene_ref(s.string(scene, "scene", nonempty=True), base)
    axes = s.mapping(d.get("axes"), "axes")
    if sessions is not None:
        if "session" in axes:
            raise s.error("given twice", "axes.session", "sessions either as 'sessions:' or as an axis")
        if not isinstance(sessions, list) or not sessions:
            raise s.bad(sessions, "sessions", "a non-empty list of session files")
        axes["session"] = [_resolve_path(s.string(p, f"sessions[{i}]", nonempty=True), base)
                           for i, p in enumerate(sessions)]
    design = s.mapping(d.get("design", {"type": "grid"}), "design", allowed=("type", "n", "seed"), none_ok=False)
    kind = s.enum(design.get("type", "grid"), "design.type", ("grid", "random"))
    n = 0
    if kind == "random":
        n = s.integer(s.require(design, "n", "design", "the number of random cases (an integer >= 1)"),
                      "design.n", lo=1, hi=1_000_000)
    elif "n" in design:
        raise s.error("only for a random design", "design.n", "no 'n' in a grid design")
    dseed = s.integer(design.get("seed", 0), "design.seed", lo=0, hi=2**63 - 1)
    if not axes and kind == "grid" and sessions is None:
        pass  # one case: the scene as it is
    for name, values in axes.items():
        f = f"axes.{name}"
        parts = name.split(".")
        if name in FIXED_AXES:
            pass
        elif parts[0] == "params" and len(parts) == 2 and parts[1]:
            pass
        elif parts[0] == "capture" and len(parts) == 2 and parts[1] in CAPTURE_SETTINGS:
            pass
        elif parts[0] == "effects" and len(parts) == 3:
            if parts[1] not in EFFECTS:
                raise s.error(f"unknown effect {parts[1]!r}", f, "one of " + ", ".join(sorted(EFFECTS)))
            if parts[2] not in EFFECTS[parts[1]].params:
                raise s.error(f"unknown parameter {parts[2]!r} of effect {parts[1]}", f,
                              "one of " + ", ".join(sorted(EFFECTS[parts[1]].params)))
        else:
            raise s.error(f"unknown axis {name!r}", f, "params.NAME, effects.EFFECT.PARAM, capture.SETTING, "
                          + ", ".join(FIXED_AXES))
        axes[name] = _parse_axis(s, f, name, values, kind)
    if scene is None and any(a != "session" for a in axes):
        raise s.error("needs a scene", "axes", "only the 'session' axis when batching over recorded sessions")
    frames = s.integer(d.get("frames", 4), "frames", lo=1, hi=100_000)
    noise = s.boolean(d.get("noise", True), "noise")
    seed = s.integer(d.get("seed", 0), "seed", lo=0, hi=2**32 - 1)
    effects = _parse_effect_set(s, "effects", d.get("effects") or {})
    capture = _parse_capture(s, d.get("capture"), axes, scene=scene, sessions=sessions, frames=frames)
    simulate = s.boolean(d.get("simulate", sessions is None and capture is None), "simulate")
    if simulate and capture is not None:
        raise s.error("both simulate and capture", "simulate", "false when the cases capture from a device")
    if simulate and scene is None:
        raise s.error("needs a scene", "simulate", "a 'scene' to simulate")
    if not simulate and sessions is None and capture is None:
        raise s.error("nothing to evaluate", "simulate", "true, 'capture' from a device, or 'sessions' to batch over")
    compare = d.get("compare")
    if compare is not None:
        compare = s.mapping(compare, "compare", allowed=("reference", "corrections", "frames", "min_relative_amplitude"),
                            none_ok=False)
        ref = compare.get("reference", "twin")
        if ref != "twin":
            compare["reference"] = _resolve_path(s.string(ref, "compare.reference", nonempty=True), base)
        elif scene is None:
            raise s.error("the twin needs a scene", "compare.reference", "a reference session file, or a 'scene'")
        compare["reference"] = compare.get("reference", "twin")
        cors = compare.get("corrections", [])
        if not isinstance(cors, list):
            raise s.bad(cors, "compare.corrections", "a list of correction specs like 'uniform:w=2e-5'")
        compare["corrections"] = [s.string(c, f"compare.corrections[{i}]", nonempty=True) for i, c in enumerate(cors)]
        compare["frames"] = s.integer(compare.get("frames", 10), "compare.frames", lo=1, hi=100_000)
        if "min_relative_amplitude" in compare:
            s.number(compare["min_relative_amplitude"], "compare.min_relative_amplitude", lo=0.0, hi=1.0, hi_open=True)
    diagnose = d.get("diagnose")
    if diagnose is not None:
        if scene is None:
            raise s.error("needs a scene", "diagnose", "a 'scene': the twin to diagnose against")
        diagnose = s.mapping(diagnose, "diagnose", allowed=("max_effects", "candidates", "max_frames",
                                                            "min_relative_gain", "block_px"))
        if "max_effects" in diagnose:
            s.integer(diagnose["max_effects"], "diagnose.max_effects", lo=1, hi=20)
        if "max_frames" in diagnose:
            s.integer(diagnose["max_frames"], "diagnose.max_frames", lo=1, hi=100_000)
        if "block_px" in diagnose:
            s.integer(diagnose["block_px"], "diagnose.block_px", lo=1, hi=4096)
        if "min_relative_gain" in diagnose:
            s.number(diagnose["min_relative_gain"], "diagnose.min_relative_gain", lo=0.0, hi=1.0)
        if "candidates" in diagnose:
            c = diagnose["candidates"]
            if not isinstance(c, list) or not c:
                raise s.bad(c, "diagnose.candidates", "a list of effect names")
            for i, e in enumerate(c):
                s.enum(e, f"diagnose.candidates[{i}]", sorted(EFFECTS))
    calibrate = _parse_calibrate(s, d.get("calibrate"), axes, scene=scene, simulate=simulate, frames=frames,
                                 base=base)
    for i, c in enumerate((compare or {}).get("corrections", [])):
        if f"={CALIBRATED_PSF}" in c and calibrate is None:
            raise s.error(f"{CALIBRATED_PSF} without a calibration", f"compare.corrections[{i}]",
                          "a 'calibrate' block that fits the PSF once before the cases")
    if not simulate and capture is None and compare is None and diagnose is None:
        raise s.error("nothing to do", "", "'compare' and/or 'diagnose' for a batch over sessions")
    report = s.mapping(d.get("report"), "report", allowed=("metrics",))
    metrics = report.get("metrics", [])
    if not isinstance(metrics, list):
        raise s.bad(metrics, "report.metrics", "a list of metric column names")
    metrics = [s.string(m, f"report.metrics[{i}]", nonempty=True) for i, m in enumerate(metrics)]
    name = s.string(d.get("name", Path(source).stem if source != "<spec>" else "sweep"), "name", nonempty=True)
    spec = SweepSpec(name=name, scene=scene, axes=axes, design=kind, n=n, design_seed=dseed, frames=frames,
                     noise=noise, seed=seed, effects=effects, simulate=simulate, capture=capture,
                     calibrate=calibrate, compare=compare, diagnose=diagnose,
                     reference=None, keep_sessions=s.boolean(d.get("keep_sessions", True), "keep_sessions"),
                     report_metrics=metrics, description=s.string(d.get("description", ""), "description"),
                     source=str(source), base_dir=str(base), text=text)
    if scene is not None:
        _check_scene(spec, s)
    return spec


def _parse_capture(s: Schema, value: Any, axes: Mapping[str, Any], *, scene: str | None, sessions: Any,
                   frames: int) -> dict[str, Any] | None:
    """The ``capture`` block: which device, how many frames, the acquisition settings.

    With ``device: emulator`` and a scene, each case captures from an emulated TOFcam635
    looking at the case's scene (scene parameters, effects and seed are the bench's); any
    other device is the bench as it stands, so only ``capture.*`` axes may vary."""
    if value is None:
        if any(a.startswith("capture.") for a in axes):
            raise s.error("a capture axis without a 'capture' block", "capture",
                          "a 'capture: {device: ...}' block for capture.* axes")
        return None
    if sessions is not None:
        raise s.error("both sessions and capture", "capture", "either recorded 'sessions' or a 'capture' device")
    c = s.mapping(value, "capture", allowed=CAPTURE_KEYS, none_ok=False)
    device = s.string(s.require(c, "device", "capture", "a device such as emulator, usb or serial:PORT"),
                      "capture.device", nonempty=True)
    out: dict[str, Any] = {"device": device,
                           "frames": s.integer(c.get("frames", frames), "capture.frames", lo=1, hi=100_000),
                           "mode": s.enum(c.get("mode", "dcs"), "capture.mode", ("dcs",)),
                           "timeout_s": s.number(c.get("timeout_s", 2.0), "capture.timeout_s", lo=0.0, hi=3600.0,
                                                 lo_open=True)}
    if c.get("roi") is not None:
        roi = s.numbers(c["roi"], "capture.roi", n=4, expected="[X0, Y0, X1, Y1] sensor pixels, half-open")
        if any(v != int(v) or v < 0 for v in roi) or roi[2] <= roi[0] or roi[3] <= roi[1]:
            raise s.bad(c["roi"], "capture.roi", "[X0, Y0, X1, Y1] integers >= 0 with X1 > X0 and Y1 > Y0")
        out["roi"] = [int(v) for v in roi]
    for key in CAPTURE_SETTINGS:
        if c.get(key) is not None:
            out[key] = _capture_setting(s, f"capture.{key}", key, c[key])
    for name, values in axes.items():
        if name.startswith("capture."):
            key = name.split(".", 1)[1]
            if isinstance(values, list):
                for i, v in enumerate(values):
                    _capture_setting(s, f"axes.{name}[{i}]", key, v)
    emulated_bench = device == EMULATED_BENCH and scene is not None
    for name in axes:
        if name.startswith("camera."):
            raise s.error("the device is the camera", f"axes.{name}",
                          "capture.* settings (a camera preset or scale cannot be set on a device)")
        if not emulated_bench and not name.startswith("capture."):
            raise s.error(f"a bench axis with device {device!r}", f"axes.{name}",
                          "only capture.* axes: the sweep changes a real bench's settings, not its scene "
                          "(device 'emulator' with a scene emulates the bench of each case)")
    return out


def _parse_calibrate(s: Schema, value: Any, axes: Mapping[str, Any], *, scene: str | None, simulate: bool,
                     frames: int, base: Path) -> dict[str, Any] | None:
    """The ``calibrate`` block: ONE stray-light PSF calibration on scenes that are not the
    cases (the documented bench procedure: a card on black, a bright patch at several field
    positions), simulated through the spec's ``effects`` (the lens), fitted by
    :func:`tofhil.eval.corrections.psf_calibration.calibrate_from_sessions`."""
    if value is None:
        return None
    if not simulate or scene is None:
        raise s.error("a calibration needs simulated cases", "calibrate",
                      "a simulating sweep (calibrate a device with 'tofhil correct --method psf --calibrate')")
    c = s.mapping(value, "calibrate", allowed=CALIBRATE_KEYS, none_ok=False)
    for name, values in axes.items():
        if name.startswith("camera.") and not (isinstance(values, list) and len(values) == 1):
            raise s.error("one calibration for every case", f"axes.{name}",
                          "one camera for all cases with 'calibrate' (a PSF is calibrated for one camera)")
    cal_scene = scene if "scene" not in c else _scene_ref(s.string(c["scene"], "calibrate.scene", nonempty=True), base)
    captures = c.get("captures", [{}])
    if not isinstance(captures, list) or not captures:
        raise s.bad(captures, "calibrate.captures", "a non-empty list of scene parameter sets, one per capture")
    captures = [dict(s.mapping(p, f"calibrate.captures[{i}]")) for i, p in enumerate(captures)]
    gc = c.get("ghost_center")
    if gc is not None and gc != "fit":
        gc = list(s.numbers(gc, "calibrate.ghost_center", n=2, expected="fit, or [X, Y] in pixels"))
    out = {"scene": cal_scene, "captures": captures,
           "reference": s.enum(c.get("reference", "twin"), "calibrate.reference", ("twin", "none")),
           "frames": s.integer(c.get("frames", frames), "calibrate.frames", lo=1, hi=100_000),
           "form": s.enum(c.get("form", "free"), "calibrate.form", ("free", "gaussian")),
           "ghost_center": gc}
    from tofhil.sim.scene import load_scene

    for i, p in enumerate(captures):
        try:
            load_scene(cal_scene, overrides={"params": p} if p else None)
        except TofhilError as exc:
            raise s.error(str(exc), f"calibrate.captures[{i}]", "parameters the calibration scene accepts") from None
    return out


def _capture_setting(s: Schema, f: str, key: str, value: Any) -> Any:
    if key == "channel":
        return s.integer(value, f, lo=0, hi=15)
    if key == "min_amplitude":
        return s.number(value, f, lo=0.0, hi=1e9)
    return s.number(value, f, lo=0.0, hi=1e10, lo_open=True)


def _parse_effect_set(s: Schema, f: str, value: Any) -> dict[str, dict[str, Any]]:
    from tofhil.sim.effects import parse_effects

    m = s.mapping(value, f)
    try:
        parse_effects(m, source=str(s.file))
    except TofhilError as exc:
        raise s.error(str(exc), f, "an effects block as in a scene file") from None
    return {k: dict(v or {}) for k, v in m.items()}


def _parse_axis(s: Schema, f: str, name: str, values: Any, design: str) -> Any:
    """A list of values (both designs; random draws from it), or a form: ``linspace`` /
    ``logspace: [lo, hi, n]`` (grid), ``uniform`` / ``log_uniform`` / ``integers: [lo, hi]``
    (random, ``integers`` inclusive)."""
    if isinstance(values, Mapping):
        m = s.mapping(values, f)
        if len(m) != 1:
            raise s.bad(values, f, "one form, e.g. {uniform: [0.1, 0.5]}")
        (form, args), = m.items()
        if form in GRID_FORMS:
            lo, hi, n = s.numbers(args, f"{f}.{form}", n=3, expected="[lo, hi, n]")
            if n < 1 or n != int(n):
                raise s.bad(args, f"{f}.{form}", "[lo, hi, n] with n an integer >= 1")
            if form == "logspace" and (lo <= 0 or hi <= 0):
                raise s.bad(args, f"{f}.{form}", "[lo, hi, n] with lo, hi > 0")
            pts = np.linspace(lo, hi, int(n)) if form == "linspace" else np.geomspace(lo, hi, int(n))
            return [float(x) for x in pts]
        if form in DISTRIBUTIONS and form != "choice":
            if design != "random":
                raise s.error(f"a random distribution ({form}) in a grid design", f,
                              "a list of values or linspace/logspace (or design type: random)")
            lo, hi = s.numbers(args, f"{f}.{form}", n=2, expected="[lo, hi] with lo <= hi")
            if lo > hi or (form == "log_uniform" and lo <= 0):
                raise s.bad(args, f"{f}.{form}", "[lo, hi] with lo <= hi" + (", lo > 0" if form == "log_uniform" else ""))
            if form == "integers" and (lo != int(lo) or hi != int(hi)):
                raise s.bad(args, f"{f}.{form}", "[lo, hi], integers")
            return {form: [lo, hi]}
        if form == "choice":
            values = args
        else:
            raise s.error(f"unknown form {form!r}", f, "one of " + ", ".join(GRID_FORMS + DISTRIBUTIONS))
    if not isinstance(values, list) or not values:
        raise s.bad(values, f, "a non-empty list of values, or a form such as {linspace: [lo, hi, n]}")
    out = []
    for i, v in enumerate(values):
        fi = f"{f}[{i}]"
        if name == "effects":
            out.append(_parse_effect_set(s, fi, v))
        elif name == "camera.preset" or name == "session":
            out.append(s.string(v, fi, nonempty=True))
        elif name == "seed":
            out.append(s.integer(v, fi, lo=0, hi=2**32 - 1))
        elif name == "camera.scale":
            out.append(s.number(v, fi, lo=0.0, hi=8.0, lo_open=True))
        elif name.startswith("effects."):
            out.append(s.number(v, fi, lo=-1e12, hi=1e12))
        else:  # scene parameters: numbers or strings, as in a scene's params block
            if isinstance(v, bool) or not isinstance(v, (int, float, str)):
                raise s.bad(v, fi, "a number or a string")
            if isinstance(v, float) and not math.isfinite(v):
                raise s.bad(v, fi, "a finite number")
            out.append(v)
    return out


def _check_scene(spec: SweepSpec, s: Schema) -> None:
    """Load the scene once with the first value of every scene axis: a bad scene, an unknown
    parameter or preset is an error of the spec, before anything runs."""
    from tofhil.sim.scene import load_scene

    try:
        base = load_scene(spec.scene)
    except TofhilError as exc:
        raise s.error(str(exc), "scene", "a bundled scene name or a scene YAML file") from None
    for name in spec.axes:
        if name.startswith("params.") and name.split(".", 1)[1] not in (base.params or {}):
            raise s.error(f"the scene has no parameter {name.split('.', 1)[1]!r}", f"axes.{name}",
                          "one of " + ", ".join(sorted(base.params or {})) if base.params else "a scene with params")
    for case in expand_cases(spec)[:1]:
        try:
            case_scene(spec, case.params)
        except TofhilError as exc:
            raise s.error(str(exc), "axes", "values the scene accepts") from None


def load_spec(path: str | Path) -> SweepSpec:
    """Read and validate a sweep spec YAML file."""
    from tofhil.yamlio import load_yaml

    p = Path(path)
    if not p.is_file():
        raise InputFileError("is a directory" if p.is_dir() else "no such file", file=p,
                             expected="a sweep spec YAML file")
    text = p.read_text(encoding="utf-8")
    data = load_yaml(text, p)
    return parse_spec(data, source=str(p), base_dir=p.resolve().parent, text=text)


# ----------------------------------------------------------------------------- cases
@dataclass
class Case:
    """One case: its id (index and a digest of its parameters) and its axis values."""

    id: str
    index: int
    params: dict[str, Any]


def _digest(x: Any) -> str:
    import hashlib

    return hashlib.sha256(json.dumps(x, sort_keys=True, default=str).encode()).hexdigest()[:10]


def _draw(rng: np.random.Generator, dist: Any) -> Any:
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
    return [Case(f"{i:04d}-{_digest(c)}", i, c) for i, c in enumerate(combos)]


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


# ----------------------------------------------------------------------------- one case
_TWINS: "OrderedDict[str, Any]" = OrderedDict()
_TWIN_CACHE_SIZE = 4
#: Renders traced by this process's cached twins (a sweep's test checks the sharing).
RENDER_COUNT = {"renders": 0}


def cached_twin(scene: Any) -> Any:
    """The :class:`Twin` of a scene's content in this process (per Dask worker), so cases
    sharing a scene share its renders."""
    from tofhil.sim.effects import effects_to_block
    from tofhil.sim.pipeline import resolve_effects
    from tofhil.sim.render import content_key
    from tofhil.sim.twin import Twin

    key = content_key(scene, effects_to_block(resolve_effects(scene)))
    twin = _TWINS.get(key)
    if twin is None:
        twin = _TWINS[key] = Twin(scene)
        while len(_TWINS) > _TWIN_CACHE_SIZE:
            _TWINS.popitem(last=False)
    _TWINS.move_to_end(key)
    return twin


def flatten(prefix: str, x: Any, out: dict[str, Any], depth: int = 0) -> None:
    """Numeric and string leaves of nested mappings as ``prefix.a.b`` columns (lists are
    left out: they are maps or per-frame series, not one figure per case)."""
    if isinstance(x, Mapping):
        if depth > 6:
            return
        for k, v in x.items():
            flatten(f"{prefix}.{k}" if prefix else str(k), v, out, depth + 1)
    elif isinstance(x, (bool, np.bool_)):
        out[prefix] = bool(x)
    elif isinstance(x, (int, float, np.integer, np.floating)):
        v = float(x) if isinstance(x, (float, np.floating)) else int(x)
        out[prefix] = None if isinstance(v, float) and not math.isfinite(v) else v
    elif isinstance(x, str) and len(x) <= 200:
        out[prefix] = x
    elif x is None:
        out[prefix] = None


def compare_metrics(metrics: Mapping[str, Any]) -> dict[str, Any]:
    """The figures of a compare run, one column each: every variant's scalar metrics."""
    out: dict[str, Any] = {}
    for label, v in (metrics.get("variants") or {}).items():
        flatten(f"compare.{label}", {k: val for k, val in v.items() if k not in ("params", "notes", "method")}, out)
    return out


def diagnose_metrics(res: Mapping[str, Any], hidden: Mapping[str, Any] | None) -> dict[str, Any]:
    """The figures of a diagnosis: cause(s), misfit per held-out value, gain before/after,
    and (when the case knows what was hidden) whether the named causes are exactly that."""
    out: dict[str, Any] = {"diagnose.causes": "+".join(res.get("causes") or []) or "none",
                           "diagnose.seconds": res.get("seconds")}
    flatten("diagnose.chi2_per_value", res.get("chi2_per_value") or {}, out)
    flatten("diagnose.gain", res.get("gain") or {}, out)
    if hidden is not None:
        out["diagnose.correct"] = sorted(res.get("causes") or []) == sorted(hidden)
    return out


def run_case(spec: SweepSpec, case: Case, out_dir: str) -> dict[str, Any]:
    """Run one case and return its record; never raises for a failing case (the error and
    its traceback are in the record). Writes its files under ``cases/CASE_ID/``."""
    t0 = time.perf_counter()
    record: dict[str, Any] = {"id": case.id, "index": case.index, "params": _plain_params(case.params),
                              "status": "ok", "error": None, "metrics": {}, "host": os.uname().nodename,
                              "pid": os.getpid()}
    cdir = Path(out_dir) / "cases" / case.id
    try:
        if cdir.exists():  # a half-done earlier attempt: its files are not results
            shutil.rmtree(cdir)
        cdir.mkdir(parents=True)
        record["metrics"] = _run_case_steps(spec, case, cdir)
    except BaseException as exc:  # noqa: BLE001 - a failing case is a result, not the end of the sweep
        if isinstance(exc, (KeyboardInterrupt, SystemExit)) and not isinstance(exc, TofhilError):
            raise
        record["status"] = "error"
        record["error"] = f"{type(exc).__name__}: {exc}" if not isinstance(exc, TofhilError) else str(exc)
        record["traceback"] = traceback.format_exc(limit=8)
    record["seconds"] = time.perf_counter() - t0
    return record


def _plain_params(params: Mapping[str, Any]) -> dict[str, Any]:
    return json.loads(json.dumps(dict(params), default=str))


def _run_case_steps(spec: SweepSpec, case: Case, cdir: Path) -> dict[str, Any]:
    from tofhil.sim.pipeline import simulate_session

    metrics: dict[str, Any] = {}
    scene = case_scene(spec, case.params) if spec.scene is not None else None
    hidden: dict[str, Any] | None = case_effects(spec, case.params) if spec.simulate else None
    if spec.capture is not None:
        t = time.perf_counter()
        measured, hidden = capture_case(spec, case, cdir)
        metrics["capture.seconds"] = time.perf_counter() - t
        if scene is not None:  # the twin re-renders with the capture's settings
            scene = twin_scene_for_capture(spec, case, measured, cdir)
    twin = cached_twin(scene) if scene is not None else None
    if spec.simulate:
        from tofhil.sim.effects import effects_to_block
        from tofhil.sim.pipeline import resolve_effects

        eff = effects_to_block(resolve_effects(scene)) | {}
        for k, v in case_effects(spec, case.params).items():
            eff[k] = {**(eff.get(k) or {}), **v}
        t = time.perf_counter()
        before = twin.renders
        measured = simulate_session(scene, cdir / "measured.h5", frames=spec.frames,
                                    seed=int(case.params.get("seed", spec.seed)), noise=spec.noise, effects=eff,
                                    twin=twin)
        RENDER_COUNT["renders"] += twin.renders - before
        metrics["simulate.seconds"] = time.perf_counter() - t
    elif spec.capture is None:
        measured = Path(case.params["session"])
    if spec.compare is not None:
        from tofhil.eval.compare import compare_sessions

        t = time.perf_counter()
        ref = spec.compare["reference"]
        if ref == "twin":
            # The twin's expectation (no noise) of the scene as modelled (its own effects).
            before = twin.renders
            ref = simulate_session(scene, cdir / "twin.h5", frames=1, seed=0, noise=False, effects=None, twin=twin)
            RENDER_COUNT["renders"] += twin.renders - before
        kw = {k: spec.compare[k] for k in ("min_relative_amplitude",) if k in spec.compare}
        psf = str(calibrated_psf_path(cdir.parent.parent))
        m = compare_sessions(measured, ref, cdir / "compare", max_frames=spec.compare["frames"], force=True,
                             corrections=[c.replace(f"={CALIBRATED_PSF}", f"={psf}") for c in spec.compare["corrections"]],
                             **kw)
        # the table names the calibrated PSF by its token, not by this machine's path
        m["variants"] = {k.replace(f"={psf}", f"={CALIBRATED_PSF}"): v for k, v in m["variants"].items()}
        metrics.update(compare_metrics(m))
        metrics["compare.seconds"] = time.perf_counter() - t
    if spec.diagnose is not None:
        from tofhil.eval.diagnose.run import run_diagnosis
        from tofhil.sim.scene import scene_to_yaml

        scene_path = cdir / "twin_scene.yaml"
        scene_path.write_text(scene_to_yaml(scene), encoding="utf-8")
        res = run_diagnosis(measured, scene_path, cdir / "diagnose", force=True, **spec.diagnose)
        metrics.update(diagnose_metrics(res.to_json(), hidden))
    if (spec.simulate or spec.capture is not None) and not spec.keep_sessions:
        for name in ("measured.h5", "twin.h5"):
            (cdir / name).unlink(missing_ok=True)
    return metrics


# ----------------------------------------------------------------------------- the PSF calibration
def calibrated_psf_path(out_dir: str | Path) -> Path:
    return Path(out_dir) / "calibration" / "psf.json"


def run_calibration(spec: SweepSpec, out: Path, say: Callable[[str], None]) -> Path:
    """Fit the sweep's stray-light PSF once (``calibration/psf.json``), before the cases.

    Each calibration capture is the calibration scene with its parameters, simulated with
    the scene's own effects and the spec's ``effects`` (the lens under test; not the cases'
    axes), with the spec's noise; with ``reference: twin`` each is fitted against its
    stray-light-free, noise-free twin, with ``none`` as bright targets on a dark background.
    A finished calibration is reused by ``--resume`` (the spec, and so the calibration, is
    the same)."""
    from tofhil.eval.corrections.psf_calibration import calibrate_from_sessions
    from tofhil.sim.effects import effects_to_block
    from tofhil.sim.pipeline import resolve_effects, simulate_session

    cal = spec.calibrate
    path = calibrated_psf_path(out)
    if path.is_file():
        say(f"calibration: reusing {path}")
        return path
    work = path.parent.with_name("calibration.tmp")
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    captures, refs = [], []
    camera = {k: v[0] for k, v in spec.axes.items() if k.startswith("camera.")}  # one value (validated)
    for i, params in enumerate(cal["captures"]):
        scene = load_with_camera(cal["scene"], camera, {"params": params} if params else None)
        eff = effects_to_block(resolve_effects(scene))
        for k, v in spec.effects.items():
            eff[k] = {**(eff.get(k) or {}), **v}
        say(f"calibration capture {i + 1}/{len(cal['captures'])}: {cal['scene']} {params or ''}".rstrip())
        captures.append(simulate_session(scene, work / f"capture_{i}.h5", frames=cal["frames"], seed=spec.seed + 7919 + i,
                                         noise=spec.noise, effects=eff))
        if cal["reference"] == "twin":
            plain = {k: v for k, v in eff.items() if k != "stray_light"}
            refs.append(simulate_session(scene, work / f"reference_{i}.h5", frames=1, noise=False,
                                         effects=plain))
    gc = cal["ghost_center"]
    psf = calibrate_from_sessions(captures, refs or None, form=cal["form"],
                                  ghost_center_px=tuple(gc) if isinstance(gc, list) else gc)
    for warning in psf.info.get("warnings", []):
        say(f"warning: PSF calibration: {warning}")
    say(f"PSF calibrated: residual {100 * psf.info['relative_residual']:.2f} % of the calibration's stray light, "
        f"condition {psf.info['condition']:.3g}")
    psf.save(work / "psf.json", force=True)
    shutil.rmtree(path.parent, ignore_errors=True)
    os.replace(work, path.parent)
    return path


# ----------------------------------------------------------------------------- capture cases
def capture_settings(spec: SweepSpec, params: Mapping[str, Any]) -> Any:
    """The acquisition settings of a capture case: the spec's, then the case's axes."""
    from tofhil.drivers.base import CaptureSettings

    c = {**spec.capture, **{k.split(".", 1)[1]: v for k, v in params.items() if k.startswith("capture.")}}
    it = c.get("integration_time_us")
    return CaptureSettings(mode=c["mode"], integration_time_s=None if it is None else float(it) * 1e-6,
                           mod_freq_hz=c.get("mod_freq_hz"), channel=c.get("channel"),
                           min_amplitude=c.get("min_amplitude"),
                           roi=None if c.get("roi") is None else tuple(c["roi"]))


def emulates_bench(spec: SweepSpec) -> bool:
    """True when each case captures from an emulator looking at the case's own scene."""
    return spec.capture is not None and spec.capture["device"] == EMULATED_BENCH and spec.scene is not None


@contextlib.contextmanager
def device_lock(device: str) -> Iterator[None]:
    """One capture at a time per device across a Dask cluster's workers (a camera is one
    resource; the cases' compare and diagnose steps still run in parallel). Outside a worker
    (``workers=0``) the cases run one by one anyway."""
    try:
        from distributed import Lock, get_worker

        get_worker()
    except (ImportError, ValueError):
        yield
        return
    with Lock(f"tofhil-device:{device}"):
        yield


def capture_case(spec: SweepSpec, case: Case, cdir: Path) -> tuple[Path, dict[str, Any] | None]:
    """Capture a case's session from the spec's device into ``cdir/measured.h5``.

    Returns the session and the effects the bench really has where the sweep knows them (an
    emulated bench: the case's effects, else the emulator's own hidden truth), else None."""
    from tofhil.drivers.base import create_driver
    from tofhil.drivers.capture import capture

    device = spec.capture["device"]
    hidden = None
    scene_text = ""
    if emulates_bench(spec):
        from tofhil.drivers.tofcam635.emulator import EmulatedTofCam635, Epc635Emulator
        from tofhil.sim.sources import HIDDEN_TRUTH_EFFECTS, TOFCAM635_OVERRIDES, SimulatedSource
        from tofhil.sim.scene import scene_to_yaml

        # the bench as the emulated TOFcam635 sees it (its camera and sensor model); the twin
        # of each capture starts from the same file
        bench = cdir / "bench_scene.yaml"
        scene_text = scene_to_yaml(case_scene(spec, case.params, TOFCAM635_OVERRIDES))
        bench.write_text(scene_text, encoding="utf-8")
        effects = case_effects(spec, case.params)
        hidden = effects or HIDDEN_TRUTH_EFFECTS
        emulator = Epc635Emulator(SimulatedSource(bench, effects=effects or None),
                                  seed=int(case.params.get("seed", spec.seed)))
        driver = EmulatedTofCam635(device, emulator=emulator)
    else:
        driver = create_driver(device)
    out = cdir / "measured.h5"
    with device_lock(device), driver:
        summary = capture(driver, out, spec.capture["frames"], capture_settings(spec, case.params), force=True,
                          scene_text=scene_text, timeout_s=spec.capture["timeout_s"])
    if summary.ended_early or summary.frames_written < summary.requested:
        raise TofhilError(f"capture from {device} ended after {summary.frames_written} of {summary.requested} "
                          f"frames: {summary.ended_early or 'too few frames'}", file=out)
    return out, hidden


def twin_scene_for_capture(spec: SweepSpec, case: Case, session_path: Path, cdir: Path) -> Any:
    """The case's scene as the twin of its capture (``cdir/twin_scene.yaml``): an emulated
    TOFcam635's camera and sensor model where the bench is emulated, and the capture's own
    acquisition settings (:func:`tofhil.sim.session_setup.write_twin_scene`)."""
    from tofhil.sim.scene import load_scene
    from tofhil.sim.session_setup import write_twin_scene

    if emulates_bench(spec):
        scene = load_scene(cdir / "bench_scene.yaml")
    else:
        scene = case_scene(spec, case.params)
    return write_twin_scene(scene, session_path, cdir / "twin_scene.yaml")[0]


# ----------------------------------------------------------------------------- records and table
def write_record(out_dir: str | Path, record: Mapping[str, Any]) -> Path:
    """Write ``cases/CASE_ID.json`` atomically (a temporary file renamed over it)."""
    from tofhil.eval.metrics.core import json_safe

    cases = Path(out_dir) / "cases"
    cases.mkdir(parents=True, exist_ok=True)
    path = cases / f"{record['id']}.json"
    tmp = path.with_suffix(f".json.tmp{os.getpid()}")
    tmp.write_text(json.dumps(json_safe(dict(record)), indent=1), encoding="utf-8")
    os.replace(tmp, path)
    return path


def read_records(out_dir: str | Path) -> dict[str, dict[str, Any]]:
    """The finished cases of a sweep directory, by case id (unreadable files are skipped:
    they are redone)."""
    out = {}
    for p in sorted((Path(out_dir) / "cases").glob("*.json")):
        try:
            r = json.loads(p.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            continue
        if isinstance(r, dict) and r.get("id") == p.stem:
            out[p.stem] = r
    return out


def _param_cell(name: str, value: Any) -> Any:
    if name == "effects" and isinstance(value, Mapping):
        return effects_label(value)
    return value


def results_table(records: Iterable[Mapping[str, Any]], axes: Sequence[str]) -> Any:
    """One row per case: id, status, error, the axis values, seconds, then every metric."""
    import pandas as pd

    rows = []
    for r in sorted(records, key=lambda r: r["index"]):
        row: dict[str, Any] = {"case": r["id"], "status": r["status"], "error": r.get("error")}
        for a in axes:
            row[a] = _param_cell(a, r["params"].get(a))
        row["seconds"] = r.get("seconds")
        row.update(r.get("metrics") or {})
        rows.append(row)
    df = pd.DataFrame(rows)
    for c in df.columns:  # a column of mixed numbers and None stays numeric
        if df[c].dtype == object and c not in axes and c not in ("case", "status", "error"):
            conv = pd.to_numeric(df[c], errors="coerce")
            if conv.notna().sum() == df[c].notna().sum():
                df[c] = conv
    return df


def write_table(df: Any, out_dir: str | Path) -> None:
    """``results.parquet`` and ``results.csv`` (each written to a temporary name first)."""
    out = Path(out_dir)
    pq = out / "results.parquet.tmp"
    df.to_parquet(pq, index=False)
    os.replace(pq, out / "results.parquet")
    csv = out / "results.csv.tmp"
    df.to_csv(csv, index=False)
    os.replace(csv, out / "results.csv")


# ----------------------------------------------------------------------------- report
_PREFERRED = ("correct", "rmse", "chi2", "removed", "mean_abs", "median")


def report_metrics(df: Any, axes: Sequence[str], wanted: Sequence[str] = (), limit: int = 12) -> list[str]:
    """The metric columns to plot: those asked for, else numeric ones that vary, the
    headline figures (RMSE, misfit, correct) first."""
    import pandas as pd

    if wanted:
        return [m for m in wanted if m in df.columns]
    cols = []
    for c in df.columns:
        if c in axes or c in ("case", "status", "error") or c.endswith("seconds") and c != "seconds":
            continue
        v = pd.to_numeric(df[c], errors="coerce") if df[c].dtype != bool else df[c].astype(float)
        if v.notna().sum() >= 1 and v.nunique(dropna=True) > 1:
            cols.append(c)
    cols.sort(key=lambda c: (min((i for i, p in enumerate(_PREFERRED) if p in c), default=len(_PREFERRED)), c))
    return cols[:limit]


def write_report(df: Any, spec: SweepSpec, out_dir: str | Path) -> Path:
    """A self-contained ``report.html``: each metric against each swept axis, the failed
    cases with their errors, and the table."""
    import pandas as pd

    from tofhil.eval.reports import html as H

    out = Path(out_dir)
    axes = [a for a in spec.axes if a in df.columns and df[a].nunique(dropna=True) > 1] or \
        [a for a in spec.axes if a in df.columns]
    ok = df[df["status"] == "ok"] if len(df) else df
    metrics = report_metrics(ok, list(spec.axes), spec.report_metrics)
    figures = []
    for ax_name in axes:
        if not metrics or not len(ok):
            break
        x_raw = ok[ax_name]
        numeric = pd.api.types.is_numeric_dtype(x_raw)
        cats = None if numeric else sorted(map(str, x_raw.dropna().unique()))
        x = x_raw.astype(float) if numeric else x_raw.astype(str).map({c: i for i, c in enumerate(cats)})
        fig, axs = H.grid(len(metrics), width=4.0, height=3.0)
        for a, m in zip(axs, metrics):
            y = ok[m].astype(float)
            a.plot(x, y, "o", alpha=0.6, ms=4)
            means = pd.DataFrame({"x": x, "y": y}).groupby("x")["y"].mean()
            a.plot(means.index, means.values, "-", color="C1", lw=1.2, label="mean")
            a.set_xlabel(ax_name, fontsize=8)
            a.set_title(m, fontsize=8)
            a.tick_params(labelsize=7)
            if cats is not None:
                a.set_xticks(range(len(cats)))
                a.set_xticklabels(cats, rotation=30, ha="right", fontsize=7)
            elif numeric and x.min() > 0 and x.max() / max(x.min(), 1e-300) > 50:
                a.set_xscale("log")
        figures.append((f"metrics against {ax_name}", H.fig_uri(fig),
                        "each point a case; the line the mean over cases with the same value (other axes vary)"))
    n_err = int((df["status"] != "ok").sum()) if len(df) else 0
    body = [f"<p>{H.esc(spec.description or spec.name)}</p>",
            f"<p>{len(df)} cases ({n_err} failed); design {H.esc(spec.design)}; axes: "
            f"{H.esc(', '.join(spec.axes) or '-')}. Scene: {H.esc(spec.scene or '-')}.</p>",
            H.figures_html(figures)]
    if n_err:
        body.append("<h2>failed cases</h2>" + H.notes_html(
            [f"{r['case']}: {r['error']}" for _, r in df[df['status'] != 'ok'].iterrows()]))
    cols = ["case", "status"] + list(spec.axes) + metrics
    cols = [c for c in cols if c in df.columns]
    head = "<tr>" + "".join(f"<th>{H.esc(c)}</th>" for c in cols) + "</tr>"
    rows = "".join("<tr>" + "".join(f"<td>{H.esc(H.fmt(r[c]) if isinstance(r[c], float) else r[c])}</td>"
                                    for c in cols) + "</tr>" for _, r in df.iterrows())
    body.append(f"<h2>cases</h2><table>{head}{rows}</table><p class='note'>every figure per case: results.csv, "
                "results.parquet; each case's files: cases/CASE_ID/</p>")
    H.write_page(out / "report.html", f"sweep: {spec.name}", body)
    return out / "report.html"


# ----------------------------------------------------------------------------- the engine
class SweepInterrupted(Interrupted):
    """Ctrl-C during a sweep: the finished cases are kept, ``--resume`` continues."""

    def __init__(self, path: str | Path, done: int, total: int) -> None:
        KeyboardInterrupt.__init__(self, f"interrupted: {done} of {total} cases finished and kept in {path} "
                                         "(rerun with --resume to continue)")
        self.path, self.frames_kept = str(path), 0


@dataclass
class SweepResult:
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
    if held and not force:
        raise TofhilError("already holds a sweep; refusing to overwrite (use --resume to continue it, "
                          "--force to start over)", file=out / held[0])
    if force:
        for n in held:
            p = out / n
            shutil.rmtree(p) if p.is_dir() else p.unlink()
    return out


def _spec_fingerprint(spec: SweepSpec) -> str:
    d = spec.to_dict()
    for k in ("source", "base_dir", "text", "description", "report_metrics", "name"):
        d.pop(k, None)
    return _digest(d)


def _save_spec(spec: SweepSpec, out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    meta = {"cases": _spec_fingerprint(spec), "source": spec.source, "spec": json.loads(json.dumps(
        {k: v for k, v in spec.to_dict().items() if k != "text"}, default=str))}
    tmp = out / "spec.yaml.tmp"
    tmp.write_text(yaml.safe_dump(meta, sort_keys=False), encoding="utf-8")
    os.replace(tmp, out / "spec.yaml")


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
                rec = {"id": case.id, "index": case.index, "params": _plain_params(case.params), "status": "error",
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


# ----------------------------------------------------------------------------- batch over sessions
def session_list(items: Sequence[str]) -> list[str]:
    """Session files from arguments: paths, glob patterns, or ``@FILE`` (a list file, one path
    a line, ``#`` comments; relative paths are relative to the list file)."""
    out: list[str] = []
    for item in items:
        if item.startswith("@"):
            lf = Path(item[1:])
            if not lf.is_file():
                raise InputFileError("no such list file", file=lf, expected="a text file of session paths, one a line")
            for line in lf.read_text(encoding="utf-8").splitlines():
                line = line.split("#", 1)[0].strip()
                if line:
                    out.append(_resolve_path(line, lf.resolve().parent))
        elif any(ch in item for ch in "*?["):
            hits = sorted(glob.glob(item, recursive=True))
            if not hits:
                raise TofhilError("matches no file", file=item, expected="a glob pattern matching session files")
            out.extend(hits)
        else:
            out.append(item)
    for p in out:
        if not Path(p).is_file():
            raise InputFileError("is a directory" if Path(p).is_dir() else "no such file", file=p,
                                 expected="a session file (.h5)")
    if not out:
        raise TofhilError("no session given", field="SESSIONS", expected="session files, glob patterns or @LIST")
    if len(set(map(os.path.abspath, out))) != len(out):
        raise TofhilError("the same session is given twice", field="SESSIONS", expected="each session once")
    return [str(Path(p).resolve()) for p in out]


def batch_spec(kind: str, sessions: Sequence[str], *, scene: str | None = None, reference: str | None = None,
               corrections: Sequence[str] = (), frames: int = 10, max_effects: int | None = None) -> SweepSpec:
    """A sweep over recorded sessions: ``kind`` 'diagnose' (against ``scene``) or 'compare'
    (against ``reference``, a session, or the twin of ``scene``)."""
    data: dict[str, Any] = {"name": f"batch {kind}", "sessions": list(sessions)}
    if scene is not None:
        data["scene"] = scene
    if kind == "diagnose":
        data["diagnose"] = {} if max_effects is None else {"max_effects": max_effects}
    elif kind == "compare":
        data["compare"] = {"reference": reference or "twin", "corrections": list(corrections), "frames": frames}
    else:
        raise ValueError(kind)
    return parse_spec(data, source="<command line>", base_dir=Path.cwd())


__all__ = ["Case", "SweepResult", "SweepSpec", "batch_spec", "case_effects", "case_scene", "expand_cases",
           "finish_sweep", "load_spec", "local_client", "parse_spec", "read_records", "results_table", "run_case",
           "run_sweep", "session_list", "write_record"]
