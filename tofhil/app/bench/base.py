"""What every bench procedure shares: measured figures, the spec sheet and its verdict, results.

A spec sheet is the vendor's stated figures, as YAML::

    name: TOFcam635 data sheet (rev. 2)       # free text
    figures:
      read_noise_e: {max: 20}
      conversion_gain_dn_per_e: {min: 0.1, max: 0.2}
      systematic_error_m: 0.02                # a bare number is a maximum

A figure the procedures do not define is refused with its name (exit 2), before anything is
captured. A figure passes when the measured value lies within its limits, is *marginal*
when a limit lies within two standard uncertainties of it, and fails otherwise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping

from tofhil.errors import InputFileError

#: Every figure a procedure defines: name -> (unit, what it is).
FIGURES: dict[str, tuple[str, str]] = {
    "conversion_gain_dn_per_e": ("DN/e", "conversion gain K (mean-variance slope)"),
    "read_noise_e": ("e", "temporal dark noise (read noise)"),
    "full_well_e": ("e", "saturation capacity of one gate"),
    "dark_current_e_per_s": ("e/s", "dark current"),
    "dsnu_e": ("e", "dark signal non-uniformity (per gate)"),
    "prnu": ("", "photo-response non-uniformity"),
    "linearity_error_pct": ("%", "linearity error (EMVA 1288)"),
    "systematic_error_m": ("m", "largest |mean of N frames - truth| over the captures, in the ROI"),
    "random_error_m": ("m", "largest temporal standard deviation over the captures, in the ROI"),
    "systematic_error_field_m": ("m", "largest |mean - truth| over the captures, whole field (median pixel)"),
    "random_error_field_m": ("m", "largest temporal standard deviation over the captures, whole field (median pixel)"),
    "relative_range_error_m": ("m", "largest |range difference - true difference| against the nearest position"),
    "range_error_e2938_m": ("m", "largest |relative-range error| over the sphere's reference-test position pairs "
                            "(ASTM E2938); its limit is the maximum permissible error"),
    "multipath_error_m": ("m", "mean depth error of a corner's walls against the geometric truth"),
    "multipath_factor": ("", "the corner's depth error over the twin's multipath error (1: as modelled)"),
    "sphere_spacing_error_m": ("m", "measured minus true distance between two sphere centres (VDI/VDE 2634-2 SD)"),
    "probing_error_size_m": ("m", "fitted minus true sphere radius (VDI/VDE 2634-2 PS, as a radius)"),
    "probing_error_form_m": ("m", "range of a sphere fit's radial residuals (VDI/VDE 2634-2 PF)"),
    "flatness_rms_m": ("m", "RMS residual of a plane fitted to a flat target"),
    "flatness_pv_m": ("m", "peak-to-valley (1-99 percentile) residual of the plane fit"),
    "fill_rate": ("", "share of the region's pixels with a valid depth"),
    "precision_m": ("m", "temporal standard deviation on the flat target (frames >= 2)"),
    "interference_error_m": ("m", "largest |range change| a second ToF camera's light makes on the target (ROI mean)"),
    "interference_noise_factor": ("", "largest random error with a second ToF camera's light over that without"),
    "ambient_noise_factor": ("", "random error at the brightest ambient light over that in the dark"),
    "warmup_drift_m_per_c": ("m/degC", "range drift per degree of chip temperature during warm-up"),
    "warmup_time_s": ("s", "time from power-on until the range stays within tolerance of its final value"),
}


@dataclass
class Figure:
    """One measured figure with its 1-sigma uncertainty and the twin's prediction (if any)."""

    name: str
    value: float
    sigma: float = math.nan
    predicted: float = math.nan
    predicted_sigma: float = math.nan
    note: str = ""

    @property
    def unit(self) -> str:
        return FIGURES.get(self.name, ("", ""))[0]

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "value": self.value, "sigma": self.sigma, "unit": self.unit,
                "predicted": self.predicted, "predicted_sigma": self.predicted_sigma, "note": self.note}


@dataclass(frozen=True)
class Limit:
    lo: float = -math.inf
    hi: float = math.inf

    def describe(self) -> str:
        if math.isfinite(self.lo) and math.isfinite(self.hi):
            return f"{self.lo:g} .. {self.hi:g}"
        return f"<= {self.hi:g}" if math.isfinite(self.hi) else f">= {self.lo:g}"


@dataclass
class SpecSheet:
    name: str
    limits: dict[str, Limit]
    source: str = ""

    def verdict(self, figures: list[Figure]) -> list[dict[str, Any]]:
        """One row per stated figure: measured, limit, pass / marginal / fail / not measured."""
        by_name = {f.name: f for f in figures}
        rows = []
        for name, lim in self.limits.items():
            f = by_name.get(name)
            if f is None or not math.isfinite(f.value):
                rows.append({"figure": name, "limit": lim.describe(), "lo": lim.lo, "hi": lim.hi, "value": math.nan,
                             "sigma": math.nan, "unit": FIGURES[name][0], "verdict": "not measured"})
                continue
            v, s = f.value, f.sigma if math.isfinite(f.sigma) else 0.0
            inside = lim.lo <= v <= lim.hi
            near = min(abs(v - lim.lo), abs(v - lim.hi)) <= 2.0 * s
            verdict = ("marginal" if near else "pass") if inside else ("marginal" if near else "fail")
            rows.append({"figure": name, "limit": lim.describe(), "lo": lim.lo, "hi": lim.hi, "value": v,
                         "sigma": f.sigma, "unit": f.unit, "verdict": verdict})
        return rows


def load_spec_sheet(path: str | Path) -> SpecSheet:
    """A spec sheet file; an unknown figure or a malformed limit names the file and the field."""
    from tofhil.errors import require_input_file
    from tofhil.yamlio import load_yaml_file

    p = require_input_file(path, expected="a spec sheet (YAML)", field="--spec")
    data = load_yaml_file(p)
    if not isinstance(data, Mapping):
        raise InputFileError("not a mapping", file=p, expected="a spec sheet: name, figures")
    extra = sorted(set(data) - {"name", "figures"})
    if extra:
        raise InputFileError("unknown field", file=p, field=extra[0], expected="name, figures")
    figs = data.get("figures") or {}
    if not isinstance(figs, Mapping):
        raise InputFileError("not a mapping", file=p, field="figures", expected="figure: {min, max} entries")
    limits: dict[str, Limit] = {}
    for name, lim in figs.items():
        if name not in FIGURES:
            raise InputFileError("unknown figure", file=p, field=f"figures.{name}",
                                 expected="one of " + ", ".join(sorted(FIGURES)))
        if isinstance(lim, (int, float)) and not isinstance(lim, bool):
            limits[name] = Limit(hi=float(lim))
            continue
        if not isinstance(lim, Mapping) or not lim or set(lim) - {"min", "max"}:
            bad = sorted(set(lim) - {"min", "max"})[0] if isinstance(lim, Mapping) and set(lim) - {"min", "max"} else None
            raise InputFileError("not a limit", file=p, field=f"figures.{name}" + (f".{bad}" if bad else ""),
                                 expected="a number (maximum) or {min: X, max: Y}")
        try:
            limits[name] = Limit(lo=float(lim.get("min", -math.inf)), hi=float(lim.get("max", math.inf)))
        except (TypeError, ValueError):
            raise InputFileError("not a number", file=p, field=f"figures.{name}",
                                 expected="numeric min and max") from None
    return SpecSheet(str(data.get("name", p.stem)), limits, str(p))


@dataclass
class BenchResult:
    """What a procedure measured: figures (with the twin's prediction), curves (one table per
    curve, for JSON and Parquet), figures drawn for the report, findings in words and files."""

    procedure: str
    device: str
    figures: list[Figure]
    curves: dict[str, list[dict[str, Any]]] = field(default_factory=dict)
    #: Draws the report's figures when the report is written: ``[(title, PNG data URI, caption)]``.
    plots: Callable[[], list[tuple[str, str | None, str]]] | None = None
    findings: list[str] = field(default_factory=list)
    files: dict[str, str] = field(default_factory=dict)
    details: dict[str, Any] = field(default_factory=dict)
    seconds: dict[str, float] = field(default_factory=dict)
    verdict: list[dict[str, Any]] = field(default_factory=list)


@dataclass
class BenchOptions:
    """Options every procedure understands (each reads what it needs)."""

    frames: int = 8
    seed: int = 0
    scene: str | None = None
    distances_m: tuple[float, ...] = (0.6, 1.0, 1.4, 1.8, 2.2)
    integration_time_us: float | None = None
    mod_freq_hz: float | None = None
    roi: tuple[int, int, int, int] | None = None
    hidden: dict[str, Any] = field(default_factory=dict)
    prompt: Callable[[str], None] | None = None
    extra: dict[str, Any] = field(default_factory=dict)


def acquisition(opts: "BenchOptions", rig: Any, integration_time_us: float = 125.0) -> tuple[dict[str, Any], str]:
    """A procedure plan's first step and who performs its bench changes: raw taps where the
    device has them (at the procedure's exposure and 20 MHz unless the user asks otherwise),
    else its depth mode; the bench changed by the emulator where it can, else by prompting the
    operator."""
    raw = "dcs" in rig.capabilities.modes
    settings: dict[str, Any] = {"mode": "dcs" if raw else "distance"}
    if raw:
        settings["integration_time_us"] = opts.integration_time_us or integration_time_us
        settings["mod_freq_hz"] = opts.mod_freq_hz or 20e6
    return {"settings": settings}, "emulator" if "emulator" in rig.capabilities.bench_by else "prompt"
