"""Campaigns: a capture plan run against a device, one session per capture, resumable.

A plan is data (a YAML file or a dict): a name and a list of steps, each one of

* ``settings: {mode, integration_time_us, mod_freq_hz, channel, min_amplitude, roi}`` -- the
  device settings from here on (merged over the earlier ones);
* ``bench: {PARAM: VALUE, ...}`` with ``by: emulator | prompt | stage`` (default ``emulator``)
  and an optional ``message`` -- a change of the bench: performed by an emulator through its
  scene's parameters, asked of the operator, or made by a motorised stage;
* ``wait: SECONDS`` -- e.g. for a target to settle or a camera to warm up;
* ``capture: {label: NAME, frames: N}`` -- a session ``sessions/NN-NAME.h5`` with the settings
  and bench state as they stand.

The plan is checked against what the device can do (:class:`DeviceCapabilities`) before
anything is captured; a step it cannot perform is refused naming the step. Every finished
capture is recorded at once in ``campaign.json`` (written atomically), so a campaign
interrupted by Ctrl-C or a crash resumes with ``resume=True``: finished captures are not
retaken, a half-written session is removed and taken again, and the bench is brought to the
state the next capture needs. One runner serves the bench procedures (``tofhil.app.bench``)
and any program that designs its own captures.
"""

from __future__ import annotations

import hashlib
import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Protocol, Sequence

from tofhil.errors import InputFileError, Interrupted, TofhilError
from tofhil.outputs import write_text_atomic
from tofhil.progress import Progress, no_progress

MANIFEST = "campaign.json"
SESSIONS = "sessions"
BENCH_BY = ("emulator", "prompt", "stage")
_SETTINGS_KEYS = ("mode", "integration_time_us", "mod_freq_hz", "channel", "min_amplitude", "roi")
_STEP_KINDS = ("settings", "bench", "wait", "capture")


@dataclass(frozen=True)
class Step:
    """One step of a plan (``kind`` one of settings, bench, wait, capture)."""

    index: int
    kind: str
    settings: Mapping[str, Any] = field(default_factory=dict)
    bench: Mapping[str, Any] = field(default_factory=dict)
    by: str = "emulator"
    message: str = ""
    wait_s: float = 0.0
    label: str = ""
    frames: int = 0

    @property
    def name(self) -> str:
        """How messages name the step: ``step 3 (capture 'dark-100us')``."""
        what = f"{self.kind} {self.label!r}" if self.label else self.kind
        return f"step {self.index} ({what})"


@dataclass(frozen=True)
class Plan:
    """A validated capture plan."""

    name: str
    steps: tuple[Step, ...]
    source: str = "<plan>"

    def to_dict(self) -> dict[str, Any]:
        out: list[dict[str, Any]] = []
        for s in self.steps:
            if s.kind == "settings":
                out.append({"settings": dict(s.settings)})
            elif s.kind == "bench":
                out.append({"bench": dict(s.bench), "by": s.by} | ({"message": s.message} if s.message else {}))
            elif s.kind == "wait":
                out.append({"wait": s.wait_s})
            else:
                out.append({"capture": {"label": s.label, "frames": s.frames}})
        return {"name": self.name, "steps": out}

    def fingerprint(self) -> str:
        return hashlib.sha256(json.dumps(self.to_dict(), sort_keys=True).encode()).hexdigest()[:16]

    @property
    def captures(self) -> list[Step]:
        return [s for s in self.steps if s.kind == "capture"]


def parse_plan(data: Mapping[str, Any], source: str = "<plan>") -> Plan:
    """A plan from its mapping; every error names ``source`` and the field (``steps[3].wait``)."""
    if not isinstance(data, Mapping):
        raise InputFileError("not a mapping", file=source, expected="a plan: name and steps")
    unknown = sorted(set(data) - {"name", "steps"})
    if unknown:
        raise InputFileError("unknown field", file=source, field=unknown[0], expected="name, steps")
    raw = data.get("steps")
    if not isinstance(raw, Sequence) or isinstance(raw, (str, bytes)) or not raw:
        raise InputFileError("no steps", file=source, field="steps", expected="a non-empty list of steps")
    steps: list[Step] = []
    labels: set[str] = set()
    for i, item in enumerate(raw):
        where = f"steps[{i}]"
        if not isinstance(item, Mapping):
            raise InputFileError("not a mapping", file=source, field=where, expected="one of " + ", ".join(_STEP_KINDS))
        kinds = [k for k in _STEP_KINDS if k in item]
        if len(kinds) != 1:
            raise InputFileError(f"has {len(kinds)} step kinds", file=source, field=where,
                                 expected="exactly one of " + ", ".join(_STEP_KINDS))
        kind = kinds[0]
        allowed = {kind} | ({"by", "message"} if kind == "bench" else set())
        extra = sorted(set(item) - allowed)
        if extra:
            raise InputFileError("unknown field", file=source, field=f"{where}.{extra[0]}",
                                 expected=", ".join(sorted(allowed)))
        value = item[kind]
        if kind == "settings":
            if not isinstance(value, Mapping):
                raise InputFileError("not a mapping", file=source, field=f"{where}.settings",
                                     expected="device settings: " + ", ".join(_SETTINGS_KEYS))
            bad = sorted(set(value) - set(_SETTINGS_KEYS))
            if bad:
                raise InputFileError("unknown setting", file=source, field=f"{where}.settings.{bad[0]}",
                                     expected=", ".join(_SETTINGS_KEYS))
            steps.append(Step(i, kind, settings=dict(value)))
        elif kind == "bench":
            by = item.get("by", "emulator")
            if by not in BENCH_BY:
                raise InputFileError(f"by {by!r}", file=source, field=f"{where}.by", expected=" | ".join(BENCH_BY))
            if not isinstance(value, Mapping) or not value:
                raise InputFileError("not a mapping", file=source, field=f"{where}.bench",
                                     expected="bench parameters and their values")
            steps.append(Step(i, kind, bench=dict(value), by=by, message=str(item.get("message", ""))))
        elif kind == "wait":
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value) and value >= 0):
                raise InputFileError(f"wait {value!r}", file=source, field=f"{where}.wait",
                                     expected="a number of seconds >= 0")
            steps.append(Step(i, kind, wait_s=float(value)))
        else:
            if not isinstance(value, Mapping):
                raise InputFileError("not a mapping", file=source, field=f"{where}.capture",
                                     expected="{label: NAME, frames: N}")
            bad = sorted(set(value) - {"label", "frames"})
            if bad:
                raise InputFileError("unknown field", file=source, field=f"{where}.capture.{bad[0]}",
                                     expected="label, frames")
            label = str(value.get("label", f"capture{i}"))
            frames = value.get("frames", 1)
            if isinstance(frames, bool) or not isinstance(frames, int) or frames < 1:
                raise InputFileError(f"frames {frames!r}", file=source, field=f"{where}.capture.frames",
                                     expected="a whole number of frames >= 1")
            if not label.replace("-", "").replace("_", "").replace(".", "").isalnum() or label in labels:
                raise InputFileError(f"label {label!r}", file=source, field=f"{where}.capture.label",
                                     expected="a unique name of letters, digits, '-', '_' and '.'")
            labels.add(label)
            steps.append(Step(i, kind, label=label, frames=frames))
    plan = Plan(str(data.get("name", "campaign")), tuple(steps), source)
    if not plan.captures:
        raise InputFileError("the plan captures nothing", file=source, field="steps", expected="a capture step")
    return plan


def load_plan(path: str | Path) -> Plan:
    """A plan from a YAML file."""
    from tofhil.yamlio import load_yaml_file

    return parse_plan(load_yaml_file(path), str(path))


# --------------------------------------------------------------------------- what a device can do
@dataclass(frozen=True)
class DeviceCapabilities:
    """What a device (with its bench) can perform; a plan is checked against it."""

    modes: tuple[str, ...]
    #: Modulation frequencies it offers; None: not settable.
    mod_freqs_hz: tuple[float, ...] | None = None
    #: Integration time range (s, inclusive); None: not settable.
    integration_time_s: tuple[float, float] | None = None
    #: How bench changes can be made here (emulator, prompt, stage).
    bench_by: tuple[str, ...] = ("prompt",)
    #: The parameters an emulated bench (or a stage) changes.
    bench_params: tuple[str, ...] = ()
    channels: tuple[int, int] | None = None


def check_plan(plan: Plan, caps: DeviceCapabilities, device: str) -> None:
    """Refuse, before anything is captured, a plan the device cannot perform (naming the step)."""
    for s in plan.steps:
        def refuse(what: str, fld: str, expected: str) -> None:
            raise TofhilError(f"{s.name}: {what} on {device}", file=plan.source, field=f"steps[{s.index}].{fld}",
                              expected=expected)

        if s.kind == "settings":
            v = s.settings
            if "mode" in v and v["mode"] not in caps.modes:
                refuse(f"mode {v['mode']!r} is not available", "settings.mode", " | ".join(caps.modes))
            if v.get("mod_freq_hz") is not None:
                if caps.mod_freqs_hz is None:
                    refuse("the modulation frequency cannot be set", "settings.mod_freq_hz", "no mod_freq_hz")
                try:
                    f = float(v["mod_freq_hz"])
                except (TypeError, ValueError):
                    f = math.nan
                if not any(abs(f - g) <= 1e-6 * g for g in caps.mod_freqs_hz):
                    refuse(f"modulation frequency {v['mod_freq_hz']} Hz is not offered", "settings.mod_freq_hz",
                           " or ".join(f"{g:g}" for g in caps.mod_freqs_hz) + " Hz")
            if v.get("integration_time_us") is not None:
                if caps.integration_time_s is None:
                    refuse("the integration time cannot be set", "settings.integration_time_us", "none")
                lo, hi = caps.integration_time_s
                try:
                    t = float(v["integration_time_us"]) * 1e-6
                except (TypeError, ValueError):
                    t = math.nan
                if not (lo - 1e-12 <= t <= hi + 1e-12):
                    refuse(f"integration time {v['integration_time_us']} us is out of range",
                           "settings.integration_time_us", f"{lo * 1e6:g}..{hi * 1e6:g} us")
            if v.get("channel") is not None and caps.channels is not None:
                lo, hi = caps.channels
                if not (isinstance(v["channel"], int) and lo <= v["channel"] <= hi):
                    refuse(f"channel {v['channel']!r}", "settings.channel", f"{lo}..{hi}")
        elif s.kind == "bench":
            if s.by not in caps.bench_by:
                refuse(f"a bench change by {s.by} is not possible", "by", " | ".join(caps.bench_by))
            if s.by in ("emulator", "stage"):
                bad = sorted(set(s.bench) - set(caps.bench_params))
                if bad:
                    refuse(f"the bench has no parameter {bad[0]!r}", f"bench.{bad[0]}",
                           ", ".join(caps.bench_params) or "no parameters")


# --------------------------------------------------------------------------- the rig
class Rig(Protocol):
    """A device on its bench: the driver, what it can do, and how bench changes are made."""

    device: str
    capabilities: DeviceCapabilities

    def driver(self) -> Any:
        """The opened driver (``tofhil.drivers.base.Driver``)."""

    def apply_bench(self, params: Mapping[str, Any], by: str, message: str) -> None:
        """Bring the bench to ``params`` (an emulator's scene parameters, a stage, a prompt)."""

    def scene_text(self) -> str:
        """What the session records as its scene (the twin's, never an emulator's hidden truth)."""

    def close(self) -> None: ...


@dataclass
class CampaignResult:
    """The campaign as recorded: one entry per capture label (manifest order = plan order)."""

    out_dir: Path
    plan: Plan
    captures: dict[str, dict[str, Any]]
    taken: int = 0
    skipped: int = 0
    seconds: dict[str, float] = field(default_factory=dict)

    def session(self, label: str) -> Path:
        return self.out_dir / self.captures[label]["file"]


class CampaignInterrupted(Interrupted):
    """Ctrl-C during a campaign: what is recorded, and how to go on (the CLI prints it, exit 130)."""

    def __init__(self, out_dir: Path, done: int, total: int) -> None:
        self.out_dir = out_dir
        self.path = str(out_dir / MANIFEST)
        self.frames_kept = done
        KeyboardInterrupt.__init__(self, f"interrupted: {done} of {total} captures recorded in {out_dir / MANIFEST} "
                                         "(run again with --resume to continue)")


def _read_manifest(out_dir: Path) -> dict[str, Any] | None:
    p = out_dir / MANIFEST
    if not p.exists():
        return None
    try:
        return json.loads(p.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError) as exc:
        raise InputFileError(f"unreadable ({exc})", file=p, expected="a campaign manifest (JSON)") from None


def _write_manifest(out_dir: Path, manifest: dict[str, Any]) -> None:
    write_text_atomic(out_dir / MANIFEST, json.dumps(manifest, indent=1, default=_jsonable))


def _jsonable(v: Any) -> Any:
    try:
        return float(v)
    except (TypeError, ValueError):
        return str(v)


def capture_settings(values: Mapping[str, Any]) -> Any:
    """The driver's CaptureSettings from a plan's accumulated settings."""
    from tofhil.drivers.base import CaptureSettings

    it = values.get("integration_time_us")
    roi = values.get("roi")
    return CaptureSettings(mode=values.get("mode", "dcs"),
                           integration_time_s=None if it is None else float(it) * 1e-6,
                           mod_freq_hz=None if values.get("mod_freq_hz") is None else float(values["mod_freq_hz"]),
                           channel=values.get("channel"), min_amplitude=values.get("min_amplitude"),
                           roi=None if roi is None else tuple(int(r) for r in roi))


def run_campaign(plan: Plan, rig: Rig, out_dir: str | Path, *, resume: bool = False, force: bool = False,
                 progress: Progress = no_progress, sleep: Callable[[float], None] = time.sleep,
                 timeout_s: float = 5.0, extra: Mapping[str, Any] | None = None) -> CampaignResult:
    """Run ``plan`` on ``rig`` into ``out_dir`` (``sessions/`` and ``campaign.json``).

    ``resume``: captures the manifest records are kept (the plan must be the same);
    ``force``: start over. Without either, a directory holding a campaign is refused.
    ``extra`` is stored in the manifest (what the procedure needs to read it back)."""
    from tofhil.drivers.capture import capture
    from tofhil.outputs import REFUSAL

    out = Path(out_dir)
    check_plan(plan, rig.capabilities, rig.device)
    manifest = _read_manifest(out) if out.exists() else None
    if manifest is not None and not resume and not force:
        raise TofhilError(f"already holds a campaign; {REFUSAL} or --resume to continue it", file=out / MANIFEST)
    if manifest is not None and resume and manifest.get("fingerprint") != plan.fingerprint():
        raise TofhilError("holds a campaign of another plan; --resume continues only the same plan",
                          file=out / MANIFEST, expected="the same procedure and options, or --force")
    if manifest is None or force:
        if force and (out / SESSIONS).exists():
            for old in (out / SESSIONS).glob("*.h5"):
                old.unlink()
        manifest = {"plan": plan.to_dict(), "fingerprint": plan.fingerprint(), "device": rig.device,
                    "captures": {}, "extra": dict(extra or {})}
    (out / SESSIONS).mkdir(parents=True, exist_ok=True)
    _write_manifest(out, manifest)
    done: dict[str, Any] = manifest["captures"]
    result = CampaignResult(out, plan, done, seconds={"capture": 0.0, "bench": 0.0, "wait": 0.0})
    settings: dict[str, Any] = {}
    bench: dict[str, Any] = {}
    bench_by, bench_msg = "emulator", ""
    applied: dict[str, Any] | None = None  # the bench state last brought about (None: unknown)
    n_total = len(plan.captures)
    n_caps = 0
    try:
        for s in progress(plan.steps, len(plan.steps), f"{plan.name}: {n_total} captures"):
            if s.kind == "settings":
                settings.update(s.settings)
            elif s.kind == "bench":
                bench.update(s.bench)
                bench_by, bench_msg = s.by, s.message
            elif s.kind == "wait":
                nxt = next((c for c in plan.steps[s.index:] if c.kind == "capture"), None)
                if nxt is not None and nxt.label not in done:  # waits before finished captures are not redone
                    t0 = time.monotonic()
                    sleep(s.wait_s)
                    result.seconds["wait"] += time.monotonic() - t0
            else:
                n_caps += 1
                if s.label in done and (out / done[s.label]["file"]).exists():
                    result.skipped += 1
                    continue
                if applied != bench and bench:
                    t0 = time.monotonic()
                    rig.apply_bench(dict(bench), bench_by, bench_msg)
                    result.seconds["bench"] += time.monotonic() - t0
                    applied = dict(bench)
                rel = f"{SESSIONS}/{n_caps:03d}-{s.label}.h5"
                path = out / rel
                path.unlink(missing_ok=True)  # a half-written session of an interrupted run
                t0 = time.monotonic()
                summary = capture(rig.driver(), path, s.frames, capture_settings(settings), force=True,
                                  scene_text=rig.scene_text(), timeout_s=timeout_s)
                result.seconds["capture"] += time.monotonic() - t0
                if summary.ended_early == "interrupted":
                    raise KeyboardInterrupt
                if summary.ended_early or summary.frames_written < s.frames:
                    raise TofhilError(f"{s.name}: capture ended after {summary.frames_written} of {s.frames} "
                                      f"frames: {summary.ended_early or 'too few frames'}", file=path)
                done[s.label] = {"file": rel, "step": s.index, "frames": s.frames, "settings": dict(settings),
                                 "bench": dict(bench), "bench_by": bench_by, "seconds": summary.elapsed_s,
                                 "finished_unix_s": time.time()}
                _write_manifest(out, manifest)
                result.taken += 1
    except KeyboardInterrupt:
        raise CampaignInterrupted(out, len(done), n_total) from None
    return result
