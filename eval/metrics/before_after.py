"""Before and after a correction, per region, against the reference, with their noise.

A correction is judged region by region: the residual's median and RMSE against the
reference before and after, and whether the region got worse beyond its noise. The noise
of a region's figure comes from the per-pixel noise of the residual (``noise_floor_m``,
the RMS of the noise expected from the averaged frames, :mod:`tofhil.eval.compare`) over
its ``n`` compared pixels, taken as independent: ``sigma_mean = noise_floor / sqrt(n)``,
the median's ``sqrt(pi / 2) sigma_mean`` (Gaussian). A region is **worse** when its
``|median|`` grows by more than :data:`WORSE_SIGMA` x the median's noise (before and
after combined), or its RMSE by more than that many ``sigma_mean``. The reason is named
where the correction knows it (:func:`worse_reason`).
"""

from __future__ import annotations

import math
from typing import Any, Mapping

import numpy as np

#: A change beyond this many standard deviations is "beyond its noise".
WORSE_SIGMA = 3.0
#: A region with at least this fraction of its pixels untrusted owes its change to them.
UNTRUSTED_SHARE = 0.1


def _noise_of_mean(region: Mapping[str, Any]) -> float | None:
    nf, n = region.get("noise_floor_m"), region["depth_residual_m"].get("n") or 0
    if nf is None or not math.isfinite(nf) or n < 1:
        return None
    return float(nf) / math.sqrt(n)


def region_change(before: Mapping[str, Any], after: Mapping[str, Any]) -> dict[str, Any]:
    """The figures of one region before and after, their noise, and whether it got worse."""
    b, a = before["depth_residual_m"], after["depth_residual_m"]
    sb, sa = _noise_of_mean(before), _noise_of_mean(after)
    out: dict[str, Any] = {"median_before_m": b.get("median"), "median_after_m": a.get("median"),
                           "rmse_before_m": b.get("rmse"), "rmse_after_m": a.get("rmse"),
                           "n_before": b.get("n"), "n_after": a.get("n"),
                           "noise_floor_before_m": before.get("noise_floor_m"),
                           "noise_floor_after_m": after.get("noise_floor_m"),
                           "median_noise_m": None, "worse": False, "worse_in": []}
    if None in (b.get("median"), a.get("median"), sb, sa):
        return out
    sigma = math.hypot(sb, sa)
    med_sigma = math.sqrt(math.pi / 2) * sigma
    out["median_noise_m"] = med_sigma
    if abs(a["median"]) - abs(b["median"]) > WORSE_SIGMA * med_sigma:
        out["worse_in"].append("median")
    if a["rmse"] - b["rmse"] > WORSE_SIGMA * sigma:
        out["worse_in"].append("rmse")
    out["worse"] = bool(out["worse_in"])
    return out


def worse_reason(region_flags: Mapping[str, float], correction: Mapping[str, Any],
                 change: Mapping[str, Any] | None = None) -> str | None:
    """Why a region got worse, where the correction's report says: ``region_flags`` the
    fraction of the region's pixels per flag, ``correction`` the correction's summary
    (:meth:`tofhil.eval.corrections.CorrectionContext.summary`), ``change`` the region's
    :func:`region_change` (a median moved while the RMSE fell: the removed light masked a bias)."""
    untrusted = region_flags.get("untrusted", 0.0)
    if untrusted >= UNTRUSTED_SHARE:
        return (f"its stray light comes from saturated pixels whose light the correction does not know "
                f"({100 * untrusted:.0f} % of its pixels marked untrusted)")
    twin = correction.get("twin") or {}
    left = twin.get("effects_left") or []
    if twin and twin.get("remove") != "all" and left:
        return (f"the twin's {', '.join(left)} stay in the corrected signal (they are not light beyond the direct "
                "path); a reference without them differs by them (twin:remove=all removes them too)")
    if change and change.get("worse_in") == ["median"] and change["rmse_after_m"] < change["rmse_before_m"]:
        return (f"its RMSE fell ({1e3 * change['rmse_before_m']:.1f} -> {1e3 * change['rmse_after_m']:.1f} mm): the "
                "light removed had masked a bias of the region that this correction does not address")
    return None


def region_flag_fractions(flags: np.ndarray | None, mask: np.ndarray, names: Mapping[int, str]) -> dict[str, float]:
    """Fraction of the region's pixels carrying each flag bit (``names``: bit -> name)."""
    n = int(np.count_nonzero(mask))
    if flags is None or n == 0:
        return {v: 0.0 for v in names.values()}
    f = flags[mask]
    return {name: float(np.count_nonzero(f & bit)) / n for bit, name in names.items()}


def before_after(before: Mapping[str, Mapping[str, Any]], after: Mapping[str, Mapping[str, Any]],
                 flag_fractions: Mapping[str, Mapping[str, float]] | None = None,
                 correction: Mapping[str, Any] | None = None) -> dict[str, dict[str, Any]]:
    """Per region (JSON regions of the measured and the corrected variant): the change, its
    flags and, for a region made worse, the reason (None: not known)."""
    out = {}
    for name, rb in before.items():
        ra = after.get(name)
        if ra is None:
            continue
        ch = region_change(rb, ra)
        fr = dict((flag_fractions or {}).get(name) or {})
        ch["flagged_fraction"] = fr
        ch["reason"] = worse_reason(fr, correction or {}, ch) if ch["worse"] else None
        out[name] = ch
    return out


def worse_notes(label: str, changes: Mapping[str, Mapping[str, Any]]) -> list[str]:
    """One line per region a correction made worse beyond its noise."""
    lines = []
    for name, ch in changes.items():
        if not ch["worse"]:
            continue
        mm = 1e3
        lines.append(f"{label} makes {name} worse beyond its noise ({' and '.join(ch['worse_in'])}): median "
                     f"{ch['median_before_m'] * mm:.1f} -> {ch['median_after_m'] * mm:.1f} mm (noise "
                     f"{ch['median_noise_m'] * mm:.1f} mm), RMSE {ch['rmse_before_m'] * mm:.1f} -> "
                     f"{ch['rmse_after_m'] * mm:.1f} mm; reason: {ch['reason'] or 'not known'}")
    return lines


#: Pixels within this distance of a clipped pixel form the "near clipped" region.
NEAR_CLIPPED_PX = 15


def near_clipped_regions(saturated: np.ndarray | None, radius_px: int = NEAR_CLIPPED_PX) -> list[Any]:
    """The pixels within ``radius_px`` of a clipped one (not clipped themselves): where light
    scattered from a clipped source is strongest (the card's neighbourhood). Empty when
    nothing clipped."""
    from scipy import ndimage

    from tofhil.eval.metrics.core import Region

    if saturated is None or not np.any(saturated):
        return []
    yy, xx = np.mgrid[-radius_px:radius_px + 1, -radius_px:radius_px + 1]
    near = ndimage.binary_dilation(saturated, structure=(xx ** 2 + yy ** 2) <= radius_px ** 2) & ~saturated
    if not near.any():
        return []
    return [Region(f"near clipped ({radius_px} px)", near, "mask")]


def variant_report(label: str, ctx: Any, regions: list[Any], before: Mapping[str, Any],
                   after: Mapping[str, Any]) -> dict[str, Any]:
    """``{"correction": summary, "before_after": per region}`` of a corrected variant; ``ctx``
    its CorrectionContext (None for a depth-domain method: no flags)."""
    from tofhil.eval.corrections.context import FLAGS

    summary = ctx.summary() if ctx is not None else {"notes": [], "flagged_pixels": {}}
    flags = None if ctx is None else ctx.flags
    masks = {r.name: r.mask for r in regions}
    shape = flags.shape if flags is not None else None
    fr = {}
    for name in after:
        mask = masks.get(name)
        if mask is None and name == "all" and shape is not None:
            mask = np.ones(shape, bool)
        fr[name] = region_flag_fractions(flags, mask if mask is not None else np.zeros((1, 1), bool), FLAGS)
    return {"correction": summary, "before_after": before_after(before, after, fr, summary)}
