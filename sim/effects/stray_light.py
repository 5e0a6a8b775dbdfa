"""Lens scattering: the ``stray_light`` effect, a view of the one PSF type
(:class:`tofhil.sim.straylight.StrayLightPSF`) as effect parameters."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from tofhil.sim.effects.base import BENCH_CHANGE, Effect, EffectContext, Param, Separation
from tofhil.sim.effects.registry import register
from tofhil.sim.sensor import OpticalSignal
from tofhil.sim.straylight import StrayLightOperator, StrayLightPSF, apply_lobes, lobes_only


@register
class StrayLightEffect(Effect):
    name = "stray_light"
    mimicked_by = {
        "multipath": Separation(BENCH_CHANGE, "background",
                                "a dark target in front of a bright background, then without the background"),
        "reflectance": Separation(BENCH_CHANGE, "distance", "the same scene at a second distance"),
    }
    stage = "signal"
    rank = 70
    beyond_direct = "stray_light"
    pixel_local = False
    summary = 'lens scattering `S_meas = (delta + h) * S`; options below'
    doc = ("Lens scattering: S_meas = (delta + h) * S on every frequency, harmonic and on the "
           "unmodulated light (sim/straylight/). h = a Gaussian (weight, sigma_px) + more Gaussians "
           "+ a uniform veil + a ghost mirrored through the optical centre, or a measured PSF image; "
           "each weight is the fraction of light it moves.")
    params = {
        "weight": Param(0.0, 0.0, 0.5, "", "fraction of light in the main Gaussian lobe", default=0.02,
                        fit=(0.0, 0.3), step=0.01, start=0.02),
        "sigma_px": Param(20.0, 0.3, 1000.0, "px", "sigma of the main lobe (x, and y unless sigma_y_px)",
                          fit=(0.5, 300.0), step=5.0, start=15.0, starts=(4.0, 50.0)),
        "veil": Param(0.0, 0.0, 0.5, "", "fraction spread uniformly over the sensor", fit=(0.0, 0.2), step=0.002,
                      starts=(0.01,)),
        "ghost_weight": Param(0.0, 0.0, 0.2, "", "fraction imaged mirrored through the optical centre"),
        "ghost_sigma_px": Param(2.0, 0.0, 100.0, "px", "blur of the ghost"),
    }
    options = {"sigma_y_px": "sigma of the main lobe along y (default sigma_px)",
               "gaussians": "more lobes: [[weight, sigma_x_px, sigma_y_px(, field_weight(, field_weight4))], ...]; "
                            "field_weight makes a lobe shift-variant: weight + field_weight rho^2 "
                            "(+ field_weight4 rho^4; rho = 0 at the principal point, 1 at the sensor's corner)",
               "radial": "free-form lobe: {radii_px: [...], values: [per-pixel fraction at each radius], "
                         "field_values: [...], aspect: A}; piecewise linear in log r, heavy tails allowed",
               "ghost_center_px": "[x, y] the ghost mirrors through (default the principal point)",
               "ghosts": "more ghosts: [[weight, sigma_px], ...] or [[weight, sigma_px, cx, cy], ...], or mappings "
                         "{weight, sigma_px, magnification, extra_path_m, center_px} (light at p lands at "
                         "c + m (p - c), delayed by extra_path_m; a lens prescription's ghosts)",
               "psf_file": "measured PSF image (.npy/.png/.tif; its peak pixel is the direct light)",
               "psf_center_px": "[x, y] of the PSF image's direct pixel (default its maximum)",
               "psf_scale": "factor on the measured PSF's scattered part (default 1)",
               "conserve": "true: h moves light (energy conserved); false: h adds light",
               "direct": "fraction of a pixel's light kept on it (default 1 - total weight, or 1 "
                         "without conserve); a calibration fits it"}

    def validate(self, values: Mapping[str, Any] | None, *, source: str | Path = "<effects>",
                 prefix: str | None = None) -> dict[str, Any]:
        out = super().validate(values, source=source, prefix=prefix)
        given = values or {}
        components = ("veil", "ghost_weight", "gaussians", "ghosts", "psf_file", "radial")
        if "weight" not in given and any(given.get(c) for c in components):
            out["weight"] = 0.0  # the default lobe only stands in when no component is named
        self.psf(out, source=source, prefix=prefix or "effects.stray_light", check_file=False)
        return out

    def is_off(self, values: Mapping[str, Any]) -> bool:
        extra = values.get("gaussians") or values.get("ghosts") or values.get("psf_file") or values.get("radial")
        direct = values.get("direct")
        return super().is_off(values) and not extra and (direct is None or float(direct) == 1.0)

    @staticmethod
    def psf(values: Mapping[str, Any], *, source: str | Path = "<effects>", prefix: str = "effects.stray_light",
            base_dir: Path | None = None, check_file: bool = True) -> StrayLightPSF:
        """The effect's parameters -> the one PSF type of sim/straylight/."""
        p = dict(values)
        if not check_file:
            p.pop("psf_file", None)
        return StrayLightPSF.from_params(p, source=source, prefix=prefix, base_dir=base_dir)

    @staticmethod
    def values(psf: StrayLightPSF, measured_file: str | None = None) -> dict[str, Any]:
        """A PSF (calibrated, diagnosed or loaded) -> this effect's parameters."""
        return psf.to_params(measured_file)

    def apply_signal(self, signal: OpticalSignal, values: Mapping[str, Any], ctx: EffectContext) -> OpticalSignal:
        psf = self.psf(values, source=ctx.source, base_dir=ctx.base_dir)
        if psf.is_identity:
            return signal
        if ctx.pixels is not None:
            raise ValueError("stray light moves light between pixels: it needs the whole frame's signal")
        if lobes_only(psf):
            # (the form diagnosis fits: the light's transform is kept while only the PSF changes)
            n = signal.phasor_w.shape[:-2]
            shape = signal.shape
            stack = np.concatenate([signal.phasor_w.reshape((-1,) + shape),
                                    np.broadcast_to(signal.dc_w, shape)[None], np.broadcast_to(signal.ambient_w, shape)[None]])
            res = apply_lobes(psf, stack)
            k = int(np.prod(n))
            return dataclasses.replace(signal, phasor_w=res[:k].reshape(signal.phasor_w.shape), dc_w=res[k].real.copy(),
                                       ambient_w=res[k + 1].real.copy(), waveform=dict(signal.waveform))
        op = StrayLightOperator(psf, signal.shape, (ctx.camera.cx, ctx.camera.cy))
        out = signal.copy()
        # Each channel's modulation frequency: a ghost's extra optical path delays its phasor.
        freq = (signal.freq_hz[:, None] * np.asarray(signal.harmonics, dtype=np.float64)[None, :])[..., None, None]
        out.phasor_w = op.apply(signal.phasor_w, freq_hz=freq)
        both = op.apply(np.stack([signal.dc_w, signal.ambient_w]))  # unmodulated light scatters too
        out.dc_w, out.ambient_w = both[0], both[1]
        return out
