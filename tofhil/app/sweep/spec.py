"""The sweep spec: what a sweep file may say, validated once (every error names the file and
the field), and the specs the ``batch`` commands build over recorded sessions.

A spec names a scene (or recorded sessions), the axes to vary, a design (``grid`` or
``random``) and the steps of each case (simulate or capture, calibrate once, compare,
diagnose). Parsing checks the keys of each block against the tables below and loads the
scene once with the first case's values, so a bad spec fails before anything runs.
"""

from __future__ import annotations

import dataclasses
import glob
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from tofhil.app.sweep.cases import case_scene, expand_cases
from tofhil.errors import InputFileError, TofhilError
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
#: Most cases of a sweep (a grid's product of axis lengths, a random design's n), checked
#: before any case is expanded: each case is at least a simulation of seconds, so a million is
#: already weeks of CPU, and the case table (a dict a case) stays under a few GB.
MAX_CASES = 1_000_000
#: Most values of one axis (a list, or linspace/logspace's n), checked before the values are
#: made: ``{linspace: [0.5, 2.0, 1e12]}`` would otherwise allocate 7.3 TB.
MAX_AXIS_VALUES = 100_000
GRID_FORMS = ("linspace", "logspace")


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
                      "design.n", lo=1, hi=MAX_CASES)
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
    if kind == "grid" and (total := math.prod(len(v) for v in axes.values())) > MAX_CASES:
        raise s.error(f"a grid of {total:,} cases (" + " x ".join(f"{len(v):,}" for v in axes.values()) + ")",
                      "axes", f"at most {MAX_CASES:,} cases (fewer values per axis, or design type: random with n)")
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
    compare = _parse_compare(s, d.get("compare"), scene=scene, base=base)
    diagnose = _parse_diagnose(s, d.get("diagnose"), scene=scene)
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


def _parse_compare(s: Schema, compare: Any, *, scene: str | None, base: Path) -> dict[str, Any] | None:
    """The ``compare`` block: the reference (``twin``, or a session file resolved against the
    spec's directory), the corrections to try and the frames to average."""
    if compare is None:
        return None
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
    return compare


def _parse_diagnose(s: Schema, diagnose: Any, *, scene: str | None) -> dict[str, Any] | None:
    """The ``diagnose`` block: the keyword arguments of
    :func:`tofhil.eval.diagnose.run.run_diagnosis`, checked (it needs a scene: the twin)."""
    if diagnose is None:
        return None
    from tofhil.sim.effects import EFFECTS

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
    return diagnose


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
            if n < 1 or n != int(n) or n > MAX_AXIS_VALUES:
                raise s.bad(args, f"{f}.{form}", f"[lo, hi, n] with n an integer in [1, {MAX_AXIS_VALUES:,}]")
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
    if len(values) > MAX_AXIS_VALUES:
        raise s.error(f"lists {len(values):,} values", f, f"at most {MAX_AXIS_VALUES:,} values an axis")
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
    from tofhil.yamlio import load_yaml, read_yaml_text

    p = Path(path)
    if not p.is_file():
        raise InputFileError("is a directory" if p.is_dir() else "no such file", file=p,
                             expected="a sweep spec YAML file")
    text = read_yaml_text(p)  # size bounded before it is read
    data = load_yaml(text, p)
    return parse_spec(data, source=str(p), base_dir=p.resolve().parent, text=text)


# ----------------------------------------------------------------------------- batch over recorded sessions
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

