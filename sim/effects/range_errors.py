"""Range errors: a constant optical-path offset, an error growing with the field angle, and a
fixed-pattern offset map per pixel. Each moves every harmonic's phase (:func:`_rotate_phase`)."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

import numpy as np

from tofhil.camera import CameraModel
from tofhil.errors import InputFileError
from tofhil.sim.effects.base import BENCH_CHANGE, Effect, EffectContext, Param, Separation, _rotate_phase
from tofhil.sim.effects.registry import register
from tofhil.sim.sensor import OpticalSignal


@register
class RangeOffsetEffect(Effect):
    name = "range_offset"
    mimicked_by = {
        "pose": Separation(BENCH_CHANGE, "known_target",
                           "a known target (its pose from the amplitude image, not from depth)"),
        "wiggling": Separation(BENCH_CHANGE, "distance",
                               "a second distance (wiggling changes with distance, an offset does not)"),
        "amplitude_dependent": Separation(BENCH_CHANGE, "target_reflectance",
                                          "a darker and a brighter target at one distance"),
    }
    calibrates = "depth"
    stage = "signal"
    rank = 90
    summary = 'constant optical-path offset: reads `path_m / 2` farther'
    doc = ("A constant optical-path offset (e.g. an electronic delay between the emitter drive and "
           "the pixel clock): L -> L + path_m on every pixel, so the radial distance reads "
           "path_m / 2 farther.")
    params = {"path_m": Param(0.0, -2.0, 2.0, "m", "optical path length added (radial shift = half)",
                              default=0.02, fit=(-2.0, 2.0), step=0.01)}

    def apply_signal(self, signal: OpticalSignal, values: Mapping[str, Any], ctx: EffectContext) -> OpticalSignal:
        return _rotate_phase(signal, float(values["path_m"]))


@register
class FieldAngleEffect(Effect):
    name = "field_angle"
    mimicked_by_shape = "a range error growing with the field angle looks the same as a surface curved about the optical axis"
    stage = "signal"
    rank = 100
    summary = 'radial error growing with the field angle: `c2 t^2 + c4 t^4`, t = tan(field angle) of the pixel ray'
    doc = ("Range error that depends on the field angle (lens and illumination path differences, "
           "optical path through the lens varying over the field): radial error = c2 t^2 + c4 t^4 "
           "with t the tangent of the pixel ray's angle to the optical axis (undistorted pinhole). "
           "Even in t: a rotationally symmetric lens.")
    params = {
        "c2_m": Param(0.0, -1.0, 1.0, "m", "radial error per tan^2 of the field angle", default=0.01,
                      fit=(-0.5, 0.5), step=0.002),
        "c4_m": Param(0.0, -1.0, 1.0, "m", "radial error per tan^4 of the field angle",
                      fit=(-0.5, 0.5), step=0.002),
    }

    @staticmethod
    def tan2(camera: CameraModel, shape: tuple[int, int], ctx: EffectContext | None = None) -> np.ndarray:
        """tan^2 of each pixel's field angle on a frame of ``shape``; with ``ctx``, at the
        pixels its signal holds."""
        v, u = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float64) if ctx is None else ctx.pixel_grid(shape)
        return ((u - camera.cx) / camera.fx) ** 2 + ((v - camera.cy) / camera.fy) ** 2

    def apply_signal(self, signal: OpticalSignal, values: Mapping[str, Any], ctx: EffectContext) -> OpticalSignal:
        t2 = self.tan2(ctx.camera, ctx.frame_shape(signal.shape), ctx)
        err = float(values["c2_m"]) * t2 + float(values["c4_m"]) * t2 * t2
        return _rotate_phase(signal, 2.0 * err)  # radial error -> optical path


@register
class RangeOffsetMapEffect(Effect):
    name = "range_offset_map"
    mimicked_by_shape = "a range pattern along rows or columns looks the same as a surface that bends along them"
    calibrates = "depth"
    stage = "pixel"
    rank = 120
    summary = ('fixed-pattern radial offset map `[H, W]` (m): per-column, per-row and per-pixel offsets of the readout; '
               'option `file` (.npy beside the scene) or `values` (inline rows); diagnosis fits it in closed form')
    doc = ("Fixed-pattern range offsets a real readout has and no parametric form names: a radial offset "
           "per pixel, read from a map [H, W] in metres (the camera's size). Every harmonic's phase moves "
           "as if the pixel read map[v, u] farther (optical path 2 map). Diagnosis fits the map in closed "
           "form (per-column + per-row + per-pixel, ridge-regularised; eval/diagnose/linear_forms.py) and writes "
           "it as range_offset_map.npy beside diagnosis.json.")
    params: dict[str, Param] = {}
    options = {"file": ".npy file holding the map [H, W] in metres (relative to the scene file)",
               "values": "the map inline: H rows of W radial offsets in metres"}

    def is_off(self, values: Mapping[str, Any]) -> bool:
        return values.get("file") is None and values.get("values") is None

    def check_options(self, values: dict[str, Any], *, source: str | Path, prefix: str) -> None:
        f = values.get("file")
        if f is not None and values.get("values") is not None:
            raise InputFileError("both file and values given", file=source, field=f"{prefix}.file",
                                 expected="one of file or values")
        if f is not None:
            if not isinstance(f, (str, Path)) or not str(f):
                raise InputFileError(f"got {f!r}", file=source, field=f"{prefix}.file",
                                     expected="the path of a .npy map")
            base = Path(str(source)).parent if Path(str(source)).is_file() else None
            if base is not None or Path(str(f)).is_absolute():  # resolvable now: check it at load time
                self.load(values, base_dir=base, source=source, prefix=prefix)
        elif values.get("values") is not None:
            self.load(values, source=source, prefix=prefix)

    @staticmethod
    def load(values: Mapping[str, Any], *, base_dir: Path | None = None, source: str | Path = "<effects>",
             prefix: str = "effects.range_offset_map", shape: tuple[int, int] | None = None) -> np.ndarray:
        """The map [H, W] (m), from ``file`` or ``values``; errors name the file and the field."""
        expected = "a finite 2-D array of radial offsets in metres" + (
            f" of shape {shape[0]} x {shape[1]} (the camera's rows x columns)" if shape else "")
        if values.get("file") is not None:
            f = Path(str(values["file"]))
            if not f.is_absolute() and base_dir is not None:
                f = base_dir / f
            where, field_ = f, prefix + ".file"
            try:
                m = np.load(f, allow_pickle=False)
            except (OSError, ValueError) as exc:
                raise InputFileError(f"cannot read the map {f}: {exc}", file=source, field=field_,
                                     expected="a readable .npy file") from None
        else:
            where, field_ = Path(str(source)), prefix + ".values"
            try:
                m = np.asarray(values["values"], dtype=np.float64)
            except (TypeError, ValueError):
                raise InputFileError("not a numeric array", file=source, field=field_, expected=expected) from None
        if m.ndim != 2 or not np.issubdtype(m.dtype, np.number) or not np.all(np.isfinite(m)) \
                or (shape is not None and m.shape != tuple(shape)):
            got = f"shape {m.shape}, dtype {m.dtype}" if m.ndim else f"{m!r}"
            raise InputFileError(f"got {got} ({where})", file=source, field=field_, expected=expected)
        return m.astype(np.float64, copy=False)

    def apply_signal(self, signal: OpticalSignal, values: Mapping[str, Any], ctx: EffectContext) -> OpticalSignal:
        m = ctx.at_pixels(self.load(values, base_dir=ctx.base_dir, source=ctx.source,
                                    shape=ctx.frame_shape(signal.shape)))
        return _rotate_phase(signal, 2.0 * m)  # radial offset -> optical path
