"""Corrections on frames and sessions: one registry, used by ``tofhil correct`` and ``compare``.

Complex-domain methods (stray light) need raw taps: each frame's taps become
``S[F, H, W]`` (:func:`tofhil.demod.phasor`), ``S`` is corrected, and the taps are
re-synthesised with the same offset ``B`` (:func:`tofhil.demod.taps_from_signal`), so the
corrected session is a valid raw session; its depth is recomputed by
:func:`tofhil.depth.depth_from_raw`. Depth-domain methods (thresholds, jump edges,
smoothing) work on depth frames, computing them from taps first when needed.

One syntax for a correction everywhere (``tofhil correct --method``, ``compare --correct``):
``METHOD[:key=value,...]`` (:func:`parse_method_spec`); parameters are checked here, so
every command refuses the same bad values with the same message. Methods (see
``docs/evaluation.md``)::

    taps               flat                    tap offset/gain calibration only
    uniform            w [twin flat]           thesis method 1: S - w * sum_p S_p
    gaussian-inverse   sigma_h sigma_v w mu    thesis method 2: Wiener inverse of delta + w G
                       [twin flat]
    psf                psf iterations          a PSF (calibrated, diagnosed), fixed-point deconvolution
                       [twin flat]
    twin               scene [remove flat]     remove what the fitted twin predicts beyond each
                                               pixel's direct return (stray light, multipath;
                                               remove=all: every modelled deviation)
    amplitude          min_amplitude           invalidate low-amplitude pixels
    jump-angle         angle_deg               jump-edge filter, angle criterion (8 neighbours)
    jump-distance      max_step_m relative     jump-edge filter, distance criterion
    smooth-gaussian    sigma_px                normalised Gaussian depth smoothing
    smooth-median      size                    median depth smoothing
    smooth-bilateral   sigma_px sigma_m        bilateral depth smoothing

Complex methods are called ``f(S, ctx, **params)`` with a :class:`CorrectionContext`
(camera, acquisition, clipped source pixels, frames averaged) on which they leave their
per-pixel flags and notes. The stray-light methods know their limits (:mod:`.limits`):
with clipped source pixels they restore their light from the twin (``twin=SCENE``) or mark
the pixels whose correction cannot be trusted.

Families live in their own modules: ``straylight`` (thesis methods, PSF deconvolution,
loading a PSF), ``twin`` (the twin correction), ``limits`` (clipped sources), ``context``
(what a correction knows and says), ``psf_calibration`` (fitting a PSF), ``depth`` (depth
filters); tap calibration is ``tofhil.eval.calibration.taps``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable

import numpy as np

from tofhil.demod import offset, phasor, taps_from_signal
from tofhil.depth import depth_from_raw
from tofhil.errors import TofhilError
from tofhil.eval.corrections import depth as dm
from tofhil.eval.corrections import straylight as sl
from tofhil.eval.corrections import twin as tw
from tofhil.eval.corrections.context import (CorrectionContext, context_for_frame, context_for_session,
                                             saturated_pixels)
from tofhil.eval.corrections.limits import clipped_sources
from tofhil.eval.calibration.taps import TapCalibration
from tofhil.frames import DepthFrame, RawFrame
from tofhil.schema import in_range


@dataclass(frozen=True)
class Param:
    """A method parameter: type, default (None: required) and the values it accepts."""

    type: type
    default: Any = None
    lo: float = -math.inf
    hi: float = math.inf
    lo_open: bool = False
    hi_open: bool = False
    odd: bool = False
    expected: str = ""
    choices: tuple[str, ...] = ()  # a str parameter's allowed values (empty: any)

    def check(self, value: Any, field: str) -> Any:
        """The value converted to the type, or a TofhilError naming ``field``."""
        what = self.expected or f"a {self.type.__name__}"
        if self.type is str:
            if self.choices and str(value) not in self.choices:
                raise TofhilError(f"got {value!r}", field=field, expected=what)
            if isinstance(value, (str, Path)):
                return str(value)
            return value  # an already loaded calibration (PSF, tap calibration)
        try:
            if isinstance(value, bool):
                raise ValueError
            x = float(value)
        except (TypeError, ValueError):
            raise TofhilError(f"got {value!r}", field=field, expected=what) from None
        ok = math.isfinite(x) and in_range(x, self.lo, self.hi, lo_open=self.lo_open, hi_open=self.hi_open)
        if self.type is int:
            ok = ok and x.is_integer() and (not self.odd or int(x) % 2 == 1)
        if not ok:
            raise TofhilError(f"got {value!r}", field=field, expected=what)
        return int(x) if self.type is int else x


def _fraction(required: bool = True) -> Param:
    return Param(float, None if required else 0.0, 0.0, 1.0, hi_open=True, expected="a fraction in [0, 1)")


def _positive(default: float | None = None, unit: str = "") -> Param:
    return Param(float, default, 0.0, lo_open=True, expected=f"a finite number > 0{unit}")


def _non_negative(default: float | None = None, unit: str = "") -> Param:
    return Param(float, default, 0.0, expected=f"a finite number >= 0{unit}")


_FLAT = Param(str, "", expected="a tap calibration (.npz from tofhil calibrate-taps)")


@dataclass(frozen=True)
class Method:
    """One correction: its domain, parameters and implementation."""

    name: str
    domain: str  # "complex" (needs raw taps) or "depth"
    params: dict[str, Param]
    summary: str
    #: complex: f(S[F,H,W], CorrectionContext, **p) -> S; depth: f(DepthFrame, **p) -> DepthFrame
    func: Callable[..., Any]


def _flat_param(value: Any) -> TapCalibration | None:
    if isinstance(value, TapCalibration) or value is None:
        return value
    return TapCalibration.load(value) if value else None


def load_params(method: str, params: dict[str, Any]) -> dict[str, Any]:
    """Checked parameters with calibration files (psf, flat) loaded once."""
    p = resolve_params(method, params)
    if "psf" in p:
        p["psf"] = sl.load_psf(p["psf"])
    if "flat" in p:
        p["flat"] = _flat_param(p["flat"])
    return p


def _center(ctx: CorrectionContext | None) -> tuple[float, float] | None:
    return None if ctx is None or ctx.camera is None else (ctx.camera.cx, ctx.camera.cy)


def _complex_psf(s: np.ndarray, ctx: CorrectionContext | None, psf: Any, iterations: int,
                 twin: str = "") -> np.ndarray:
    psf = sl.load_psf(psf)
    s = clipped_sources(s, ctx, lambda x: sl.scatter_psf(x, psf, _center(ctx)), twin)
    return sl.deconvolve(s, psf, center_px=_center(ctx), iterations=iterations)


def _complex_uniform(s: np.ndarray, ctx: CorrectionContext | None, w: float, twin: str = "") -> np.ndarray:
    s = clipped_sources(s, ctx, lambda x: sl.scatter_uniform(x, w), twin)
    return sl.subtract_uniform(s, w)


def _complex_gaussian(s: np.ndarray, ctx: CorrectionContext | None, sigma_h: float, sigma_v: float, w: float,
                      mu: float, twin: str = "") -> np.ndarray:
    s = clipped_sources(s, ctx, lambda x: sl.scatter_gaussian(x, sigma_h, sigma_v, w), twin)
    return sl.inverse_filter_gaussian(s, sigma_h, sigma_v, w, mu)


def _complex_twin(s: np.ndarray, ctx: CorrectionContext | None, scene: str, remove: str = "light") -> np.ndarray:
    if ctx is None:
        raise ValueError("the twin correction needs the signal's camera and acquisition (a CorrectionContext)")
    return tw.correct_twin(s, ctx, scene, remove)


_TWIN = Param(str, "", expected="a twin scene (.yaml) whose prediction restores clipped source pixels")


METHODS: dict[str, Method] = {m.name: m for m in (
    Method("taps", "complex", {"flat": Param(str, None, expected=_FLAT.expected)},
           "per-tap offset and gain calibration (tofhil calibrate-taps)", lambda s, ctx: s),
    Method("uniform", "complex", {"w": _fraction(), "twin": _TWIN, "flat": _FLAT},
           "thesis method 1: S - w * sum of all pixels' S", _complex_uniform),
    Method("gaussian-inverse", "complex",
           {"sigma_h": _positive(unit=" (pixels)"), "sigma_v": _positive(unit=" (pixels)"), "w": _fraction(),
            "mu": _non_negative(0.0), "twin": _TWIN, "flat": _FLAT},
           "thesis method 2: inverse filter of delta + w*Gaussian(sigma_h, sigma_v), regularisation mu",
           _complex_gaussian),
    Method("psf", "complex",
           {"psf": Param(str, None, expected="a PSF file (--save-psf, diagnose) or a diagnosis.json"),
            "iterations": Param(int, 30, 1, 10000, expected="an integer in [1, 10000]"), "twin": _TWIN,
            "flat": _FLAT},
           "a stray-light PSF (calibrated or diagnosed) removed by fixed-point deconvolution", _complex_psf),
    Method("twin", "complex",
           {"scene": Param(str, None, expected="a twin scene (.yaml), e.g. diagnose's extended_scene.yaml"),
            "remove": Param(str, "light", choices=("light", "all"),
                            expected="light (stray light, multipath) or all (every modelled deviation)"),
            "flat": _FLAT},
           "remove what the fitted twin predicts beyond each pixel's direct return (stray light, multipath)",
           _complex_twin),
    Method("amplitude", "depth", {"min_amplitude": _non_negative()},
           "invalidate pixels with amplitude below min_amplitude", dm.amplitude),
    Method("jump-angle", "depth", {"angle_deg": Param(float, 10.0, 0.0, 90.0, expected="an angle in [0, 90] degrees")},
           "jump-edge filter, angle criterion on the 8 neighbours", dm.jump_angle),
    Method("jump-distance", "depth", {"max_step_m": _non_negative(0.05, " (m)"), "relative": _non_negative(0.0)},
           "jump-edge filter, distance criterion on the 8 neighbours", dm.jump_distance),
    Method("smooth-gaussian", "depth", {"sigma_px": _positive(1.0, " (pixels)")},
           "Gaussian depth smoothing over valid pixels", dm.smooth_gaussian),
    Method("smooth-median", "depth", {"size": Param(int, 3, 1, odd=True, expected="an odd integer >= 1")},
           "median depth smoothing", dm.smooth_median),
    Method("smooth-bilateral", "depth", {"sigma_px": _positive(1.5, " (pixels)"), "sigma_m": _positive(0.03, " (m)")},
           "bilateral depth smoothing", dm.smooth_bilateral),
)}


def get_method(name: str) -> Method:
    if name not in METHODS:
        raise TofhilError(f"unknown correction method {name!r}", field="method",
                          expected="one of " + ", ".join(METHODS))
    return METHODS[name]


def resolve_params(method: str | Method, params: dict[str, Any] | None) -> dict[str, Any]:
    """Checked, typed parameters with defaults filled in; unknown, missing or out-of-range
    ones are user errors naming ``METHOD:key``."""
    m = get_method(method) if isinstance(method, str) else method
    params = dict(params or {})
    unknown = set(params) - set(m.params)
    if unknown:
        raise TofhilError(f"method {m.name!r} has no parameter(s) {', '.join(sorted(unknown))}",
                          field=f"{m.name}:{sorted(unknown)[0]}", expected=", ".join(m.params) or "no parameters")
    out: dict[str, Any] = {}
    for key, spec in m.params.items():
        if key in params and params[key] is not None:
            out[key] = spec.check(params[key], f"{m.name}:{key}")
        elif spec.default is None:
            raise TofhilError(f"method {m.name!r} needs parameter {key!r}", field=f"{m.name}:{key}",
                              expected=spec.expected or f"a {spec.type.__name__}")
        else:
            out[key] = spec.default
    return out


def parse_method_spec(spec: str, supplied: tuple[str, ...] = ()) -> tuple[str, dict[str, str]]:
    """The one syntax of a correction: ``METHOD[:key=value,...]`` -> (name, params), e.g.
    ``"uniform:w=1e-4"``, ``"psf:psf=diagnosis.json,iterations=20"``. Keys may be written
    with ``-`` or ``_``. The method and its parameters are checked (:func:`resolve_params`);
    required parameters named in ``supplied`` are left for the caller to fill in."""
    name, _, rest = str(spec).partition(":")
    name = name.strip()
    params: dict[str, str] = {}
    for item in filter(None, (p.strip() for p in rest.split(","))):
        key, eq, value = item.partition("=")
        key = key.strip().replace("-", "_")
        if not eq or not key:
            raise TofhilError(f"bad parameter {item!r} in {spec!r}", field="method",
                              expected="METHOD[:key=value,key=value]")
        if key in params:
            raise TofhilError(f"parameter {key!r} given twice in {spec!r}", field=f"{name}:{key}",
                              expected="each parameter once")
        params[key] = value.strip()
    m = get_method(name)
    resolve_params(m, {**{k: "" for k in supplied if k in m.params and m.params[k].type is str}, **params})
    return name, params


# ---------------------------------------------------------------------------- frames


def check_min_amplitude(value: float, field: str = "min_amplitude") -> float:
    """The demodulation's amplitude threshold: a finite number >= 0."""
    return _non_negative().check(value, field)


def correct_raw(raw: RawFrame, method: str, params: dict[str, Any] | None = None, *,
                min_amplitude: float = 0.0, context: CorrectionContext | None = None) -> tuple[RawFrame, DepthFrame]:
    """Correct one raw frame -> (corrected raw taps, depth recomputed from them).

    Depth-domain methods leave the taps unchanged and filter the depth computed from them.
    ``context`` (default: the frame's own, :func:`context_for_frame`) receives the
    correction's flags and notes.
    """
    m = get_method(method)
    p = resolve_params(m, params)
    check_min_amplitude(min_amplitude)
    if m.domain == "complex":
        taps = raw.taps.astype(np.float64)
        flat = _flat_param(p.pop("flat", None))
        if flat is not None:
            taps = flat.apply(taps)
        s = phasor(taps, raw.theta_rad)
        ctx = context if context is not None else context_for_frame(raw)
        sc = m.func(s, ctx, **p)
        taps = taps_from_signal(np.abs(sc), np.angle(sc), offset(taps), raw.theta_rad)
        out = replace(raw, taps=taps.astype(np.float32), meta=dict(raw.meta, corrected=method))
        return out, depth_from_raw(out, min_amplitude=min_amplitude)
    depth = depth_from_raw(raw, min_amplitude=min_amplitude)
    return raw, m.func(depth, **p)


def correct_mean(session: Any, method: str, params: dict[str, Any] | None = None, *, n: int | None = None,
                 min_amplitude: float = 0.0, progress: Callable[[Any, int, str], Any] | None = None,
                 context: CorrectionContext | None = None) -> tuple[RawFrame, DepthFrame]:
    """The first ``n`` frames (default all) of a raw session averaged in the complex domain
    and corrected -> (mean raw taps, depth). Complex methods correct the mean signal; depth
    methods filter the depth of the mean. ``context`` (default the session's,
    :func:`context_for_session`) receives the correction's flags and notes."""
    from tofhil.eval.corrections.averaging import session_mean_signal

    m = get_method(method)
    p = resolve_params(m, params)
    flat = _flat_param(p.pop("flat", None))
    ctx = context if context is not None else context_for_session(session, n or session.n_frames)
    correct = (lambda s: m.func(s, ctx, **p)) if m.domain == "complex" else None
    ms = session_mean_signal(session, n, flat=flat, correct=correct, scatter=False, progress=progress)
    raw = ms.raw()
    raw = replace(raw, taps=raw.taps.astype(np.float32), meta=dict(raw.meta, corrected=method))
    depth = depth_from_raw(raw, min_amplitude=min_amplitude)
    return raw, depth if m.domain == "complex" else m.func(depth, **p)


def correct_depth(depth: DepthFrame, method: str, params: dict[str, Any] | None = None) -> DepthFrame:
    """Apply a depth-domain method; complex-domain ones refuse with a clear error."""
    m = get_method(method)
    if m.domain == "complex":
        raise TofhilError(f"method {method!r} corrects the complex signal and needs raw taps; "
                          "this session has depth only", field="raw/taps",
                          expected="a session with raw taps, or a depth method "
                                   + "(" + ", ".join(k for k, v in METHODS.items() if v.domain == "depth") + ")")
    return m.func(depth, **resolve_params(m, params))


def correct_session(in_path: str | Path, out_path: str | Path, method: str, params: dict[str, Any] | None = None,
                    *, force: bool = False, min_amplitude: float = 0.0, average: bool = False,
                    progress: Callable[[Any, int, str], Any] | None = None,
                    summary: dict[str, Any] | None = None) -> int:
    """Correct every frame of a session into a new session file; returns the frame count.

    With ``average`` the output is ONE frame: the frames averaged in the complex domain
    (after the tap calibration, before demodulation: :mod:`.averaging`), then corrected.
    For the complex methods (linear in ``S``) that equals averaging the corrected frames;
    it is one correction instead of one per frame. The tap calibration applied (``flat=``
    as a file) is recorded in the output's device header (``tap_calibration``), so compare
    can give the reference the same one.

    A complex correction's report (its notes, flagged pixel counts, the figures it used:
    :meth:`CorrectionContext.summary`) is written to the output's root attribute
    ``correction`` (JSON) and its per-pixel flags (the union over frames, bits
    :data:`~tofhil.eval.corrections.context.FLAGS`) to the dataset ``correction/flags``
    ``[H, W]`` uint8; ``summary`` (a dict), when given, receives the report too."""
    from tofhil.session import copy_session_header, open_session

    in_path, out_path = Path(in_path), Path(out_path)
    if out_path.exists() and out_path.resolve() == in_path.resolve():
        raise TofhilError("the output must differ from the input", file=out_path)
    m = get_method(method)
    check_min_amplitude(min_amplitude)
    flat_file = (params or {}).get("flat")
    p = load_params(m.name, params or {})  # calibration files loaded once, not per frame
    wrap = progress or (lambda it, n, desc: it)
    with open_session(in_path) as s:
        if m.domain == "complex" and not s.has_raw:
            correct_depth(s.depth_frame(0) if s.n_frames else None, method, p)  # raises the clear error
        if average and not s.has_raw:
            raise TofhilError("--average averages raw taps; this session has depth only", file=in_path,
                              field="raw/taps", expected="a session with raw taps")
        if average and s.n_frames == 0:
            raise TofhilError("has no frame to average", file=in_path, field="n_frames", expected="at least one frame")
        note = f"{method} " + " ".join(f"{k}={v if isinstance(v, (int, float, str)) else 'calibrated'}"
                                       for k, v in p.items() if v is not None)
        if average:
            note += f" (mean of {s.n_frames} frames in the complex domain)"
        extra = {}
        if isinstance(flat_file, (str, Path)) and str(flat_file) and m.domain == "complex":
            extra["tap_calibration"] = str(Path(flat_file).expanduser().resolve())
        # a derived writer: an error leaves nothing behind, Ctrl-C keeps the frames done
        with copy_session_header(s, out_path, force=force, note=f"corrected: {note.strip()}",
                                 device_extra=extra) as w:
            ctx = None
            if m.domain == "complex" and s.n_frames:
                ctx = context_for_session(s, s.n_frames if average else 1)
                ctx.flags = np.zeros(ctx.shape, np.uint8)  # shared by the frames' contexts
            if average:
                w.append(*correct_mean(s, m.name, p, min_amplitude=min_amplitude, progress=progress, context=ctx))
                _write_report(w, ctx, summary)
                return w.n_frames
            for i in wrap(range(s.n_frames), s.n_frames, f"correcting ({method})"):
                if m.domain == "complex":
                    raw = s.raw_frame(i)
                    w.append(*correct_raw(raw, m.name, p, min_amplitude=min_amplitude,
                                          context=replace(ctx, saturated=saturated_pixels([raw]))))
                    continue
                # Depth methods filter the stored depth (a device's own) when there is one.
                raw = s.raw_frame(i) if s.has_raw else None
                depth = s.depth_frame(i) if s.has_depth else depth_from_raw(raw, min_amplitude=min_amplitude)
                w.append(raw, correct_depth(depth, m.name, p))
            _write_report(w, ctx, summary)
            n = w.n_frames
    return n


def _write_report(writer: Any, ctx: CorrectionContext | None, summary: dict[str, Any] | None) -> None:
    """A correction's report into the corrected session (root attribute ``correction`` and
    dataset ``correction/flags``) and into ``summary``."""
    import json

    if ctx is None:
        return
    doc = ctx.summary()
    if summary is not None:
        summary.update(doc)
    f = writer._file  # noqa: SLF001 -- an optional group the core writer does not know
    f.attrs["correction"] = json.dumps(doc, default=float)
    f.create_dataset("correction/flags", data=ctx.flags, compression="gzip")
