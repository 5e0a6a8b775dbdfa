"""Corrections on frames and sessions: one registry, used by ``tofhil correct`` and ``compare``.

Complex-domain methods (stray light) need raw taps: each frame's taps become
``S[F, H, W]`` (:func:`tofhil.demod.phasor`), ``S`` is corrected, and the taps are
re-synthesised with the same offset ``B`` (:func:`tofhil.demod.taps_from_signal`), so the
corrected session is a valid raw session; its depth is recomputed by
:func:`tofhil.depth.depth_from_raw`. Depth-domain methods (thresholds, jump edges,
smoothing) work on depth frames, computing them from taps first when needed.

Methods and parameters (see ``docs/evaluation.md``)::

    taps               flat                    tap offset/gain calibration only
    uniform            w [flat]                thesis method 1: S - w * sum_p S_p
    gaussian-inverse   sigma_h sigma_v w mu    thesis method 2: Wiener inverse of delta + w G
                       [flat]
    psf                psf iterations [flat]   calibrated PSF, fixed-point deconvolution
    amplitude          min_amplitude           invalidate low-amplitude pixels
    jump-angle         angle_deg               jump-edge filter, angle criterion (8 neighbours)
    jump-distance      max_step_m relative     jump-edge filter, distance criterion
    smooth-gaussian    sigma_px                normalised Gaussian depth smoothing
    smooth-median      size                    median depth smoothing
    smooth-bilateral   sigma_px sigma_m        bilateral depth smoothing
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable

import numpy as np

from tofhil.demod import offset, phasor, taps_from_signal
from tofhil.depth import depth_from_raw
from tofhil.errors import TofhilError
from tofhil.eval import depth_filters as df
from tofhil.eval import straylight_correction as sl
from tofhil.eval.fixed_pattern import TapCalibration
from tofhil.frames import DepthFrame, RawFrame


@dataclass(frozen=True)
class Method:
    """One correction: its domain, parameters (name -> (type, default)) and implementation."""

    name: str
    domain: str  # "complex" (needs raw taps) or "depth"
    params: dict[str, tuple[type, Any]]
    summary: str
    #: complex: f(S[F,H,W], **p) -> S; depth: f(DepthFrame, **p) -> DepthFrame
    func: Callable[..., Any]


def _flat_param(value: Any) -> TapCalibration | None:
    if isinstance(value, TapCalibration) or value is None:
        return value
    return TapCalibration.load(value) if value else None


def load_params(method: str, params: dict[str, Any]) -> dict[str, Any]:
    """Resolved parameters with calibration files (psf, flat) loaded once."""
    p = resolve_params(method, params)
    if "psf" in p:
        p["psf"] = _psf_param(p["psf"])
    if "flat" in p:
        p["flat"] = _flat_param(p["flat"])
    return p


def _psf_param(value: Any) -> sl.StrayLightPSF:
    if isinstance(value, sl.StrayLightPSF):
        return value
    if value is None or value == "":
        raise TofhilError("method 'psf' needs a calibrated PSF", field="psf",
                          expected="--psf FILE.npz (written by --save-psf)")
    return sl.StrayLightPSF.load(value)


def _complex_psf(s: np.ndarray, psf: Any, iterations: int) -> np.ndarray:
    return sl.deconvolve(s, _psf_param(psf), iterations=iterations)


def _depth_amplitude(d: DepthFrame, min_amplitude: float) -> DepthFrame:
    if d.amplitude is None or not np.isfinite(d.amplitude).any():
        raise TofhilError("amplitude thresholding needs an amplitude image", field="depth/amplitude",
                          expected="a session with amplitude or raw taps")
    return replace(d, valid=df.amplitude_threshold(d.amplitude, d.valid, min_amplitude))


def _radial(d: DepthFrame) -> np.ndarray:
    return np.asarray(d.radial_m, dtype=np.float64)


def _with_radial(d: DepthFrame, radial: np.ndarray, valid: np.ndarray | None = None) -> DepthFrame:
    dist = radial if d.kind == "radial" else d.camera.radial_to_z(radial)
    return replace(d, distance_m=dist, valid=d.valid if valid is None else valid)


def _depth_jump_angle(d: DepthFrame, angle_deg: float) -> DepthFrame:
    flag = df.jump_edge_angle(_radial(d), d.valid, d.camera, angle_deg)
    return replace(d, valid=d.valid & ~flag)


def _depth_jump_distance(d: DepthFrame, max_step_m: float, relative: float) -> DepthFrame:
    flag = df.jump_edge_distance(_radial(d), d.valid, max_step_m, relative)
    return replace(d, valid=d.valid & ~flag)


def _depth_gauss(d: DepthFrame, sigma_px: float) -> DepthFrame:
    return _with_radial(d, df.gaussian_smooth(_radial(d), d.valid, sigma_px))


def _depth_median(d: DepthFrame, size: int) -> DepthFrame:
    return _with_radial(d, df.median_smooth(_radial(d), d.valid, size))


def _depth_bilateral(d: DepthFrame, sigma_px: float, sigma_m: float) -> DepthFrame:
    return _with_radial(d, df.bilateral_smooth(_radial(d), d.valid, sigma_px, sigma_m))


METHODS: dict[str, Method] = {m.name: m for m in (
    Method("taps", "complex", {"flat": (str, None)},
           "per-tap offset and gain calibration (tofhil calibrate-taps)", lambda s: s),
    Method("uniform", "complex", {"w": (float, None), "flat": (str, "")},
           "thesis method 1: S - w * sum of all pixels' S", sl.subtract_uniform),
    Method("gaussian-inverse", "complex",
           {"sigma_h": (float, None), "sigma_v": (float, None), "w": (float, None), "mu": (float, 0.0),
            "flat": (str, "")},
           "thesis method 2: inverse filter of delta + w*Gaussian(sigma_h, sigma_v), regularisation mu",
           sl.inverse_filter_gaussian),
    Method("psf", "complex", {"psf": (str, None), "iterations": (int, 30), "flat": (str, "")},
           "calibrated stray-light PSF removed by fixed-point deconvolution", _complex_psf),
    Method("amplitude", "depth", {"min_amplitude": (float, None)},
           "invalidate pixels with amplitude below min_amplitude", _depth_amplitude),
    Method("jump-angle", "depth", {"angle_deg": (float, 10.0)},
           "jump-edge filter, angle criterion on the 8 neighbours", _depth_jump_angle),
    Method("jump-distance", "depth", {"max_step_m": (float, 0.05), "relative": (float, 0.0)},
           "jump-edge filter, distance criterion on the 8 neighbours", _depth_jump_distance),
    Method("smooth-gaussian", "depth", {"sigma_px": (float, 1.0)},
           "Gaussian depth smoothing over valid pixels", _depth_gauss),
    Method("smooth-median", "depth", {"size": (int, 3)}, "median depth smoothing", _depth_median),
    Method("smooth-bilateral", "depth", {"sigma_px": (float, 1.5), "sigma_m": (float, 0.03)},
           "bilateral depth smoothing", _depth_bilateral),
)}


def get_method(name: str) -> Method:
    if name not in METHODS:
        raise TofhilError(f"unknown correction method {name!r}", field="method",
                          expected="one of " + ", ".join(METHODS))
    return METHODS[name]


def resolve_params(method: str | Method, params: dict[str, Any] | None) -> dict[str, Any]:
    """Typed parameters with defaults filled in; unknown or missing ones are user errors."""
    m = get_method(method) if isinstance(method, str) else method
    params = dict(params or {})
    unknown = set(params) - set(m.params)
    if unknown:
        raise TofhilError(f"method {m.name!r} has no parameter(s) {', '.join(sorted(unknown))}",
                          field="params", expected=", ".join(m.params) or "no parameters")
    out: dict[str, Any] = {}
    for key, (typ, default) in m.params.items():
        if key in params and params[key] is not None:
            value = params[key]
            if typ is not str or isinstance(value, str):
                try:
                    value = typ(value)
                except (TypeError, ValueError):
                    raise TofhilError(f"got {value!r}", field=key, expected=f"a {typ.__name__}") from None
            out[key] = value
        elif default is None:
            raise TofhilError(f"method {m.name!r} needs parameter {key!r}", field=key,
                              expected=f"a {typ.__name__}")
        else:
            out[key] = default
    return out


def parse_method_spec(spec: str) -> tuple[str, dict[str, str]]:
    """``"uniform:w=1e-4"`` or ``"psf:psf=cal.npz,iterations=20"`` -> (name, params)."""
    name, _, rest = spec.partition(":")
    params: dict[str, str] = {}
    for item in filter(None, (p.strip() for p in rest.split(","))):
        key, eq, value = item.partition("=")
        if not eq:
            raise TofhilError(f"bad parameter {item!r} in {spec!r}", field="--correct",
                              expected="METHOD[:key=value,key=value]")
        params[key.strip().replace("-", "_")] = value.strip()
    get_method(name.strip())
    return name.strip(), params


# ---------------------------------------------------------------------------- frames


def correct_signal(s: np.ndarray, method: str, params: dict[str, Any] | None = None) -> np.ndarray:
    """Apply a complex-domain method to ``S[..., H, W]``."""
    m = get_method(method)
    if m.domain != "complex":
        raise TofhilError(f"method {method!r} works on depth, not on complex signals", field="method")
    p = resolve_params(m, params)
    if p.pop("flat", None):
        raise TofhilError("a tap calibration (flat) applies to raw taps, not to a complex signal", field="flat",
                          expected="correct_raw() or a session with raw taps")
    return m.func(np.asarray(s), **p)


def correct_raw(raw: RawFrame, method: str, params: dict[str, Any] | None = None, *,
                min_amplitude: float = 0.0) -> tuple[RawFrame, DepthFrame]:
    """Correct one raw frame -> (corrected raw taps, depth recomputed from them).

    Depth-domain methods leave the taps unchanged and filter the depth computed from them.
    """
    m = get_method(method)
    p = resolve_params(m, params)
    if m.domain == "complex":
        taps = raw.taps.astype(np.float64)
        flat = _flat_param(p.pop("flat", None))
        if flat is not None:
            taps = flat.apply(taps)
        s = phasor(taps, raw.theta_rad)
        sc = m.func(s, **p)
        taps = taps_from_signal(np.abs(sc), np.angle(sc), offset(taps), raw.theta_rad)
        out = replace(raw, taps=taps.astype(np.float32), meta=dict(raw.meta, corrected=method))
        return out, depth_from_raw(out, min_amplitude=min_amplitude)
    depth = depth_from_raw(raw, min_amplitude=min_amplitude)
    return raw, m.func(depth, **p)


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
                    *, force: bool = False, min_amplitude: float = 0.0,
                    progress: Callable[[Any, int, str], Any] | None = None) -> int:
    """Correct every frame of a session into a new session file; returns the frame count."""
    from tofhil.session import copy_session_header, open_session

    in_path, out_path = Path(in_path), Path(out_path)
    if out_path.exists() and out_path.resolve() == in_path.resolve():
        raise TofhilError("the output must differ from the input", file=out_path)
    m = get_method(method)
    p = load_params(m.name, params or {})  # calibration files loaded once, not per frame
    wrap = progress or (lambda it, n, desc: it)
    with open_session(in_path) as s:
        if m.domain == "complex" and not s.has_raw:
            correct_depth(s.depth_frame(0) if s.n_frames else None, method, p)  # raises the clear error
        note = f"{method} " + " ".join(f"{k}={v if isinstance(v, (int, float, str)) else 'calibrated'}"
                                       for k, v in p.items() if v is not None)
        # a derived writer: an error leaves nothing behind, Ctrl-C keeps the frames done
        with copy_session_header(s, out_path, force=force, note=f"corrected: {note.strip()}") as w:
            for i in wrap(range(s.n_frames), s.n_frames, f"correcting ({method})"):
                if m.domain == "complex":
                    w.append(*correct_raw(s.raw_frame(i), m.name, p, min_amplitude=min_amplitude))
                    continue
                # Depth methods filter the stored depth (a device's own) when there is one.
                raw = s.raw_frame(i) if s.has_raw else None
                depth = s.depth_frame(i) if s.has_depth else depth_from_raw(raw, min_amplitude=min_amplitude)
                w.append(raw, correct_depth(depth, m.name, p))
            n = w.n_frames
    return n
