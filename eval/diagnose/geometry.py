"""Is the residual organised by the scene's objects and edges? The one test behind "the scene
does not match".

A global gain, an offset, a per-frequency or per-tap calibration, a drift or a smooth field
error act on every pixel through the channel they move, whatever object it sees; a wrong
surface, a misplaced or missing object acts object by object and shows at the outlines and
depth steps. So the held-out depth residual (whitened by each pixel's noise) is explained by two
nested linear models:

- ``smooth``: a bivariate cubic over the field (what calibration forms and smooth optics leave);
- ``geometry``: the same plus one constant per object of the twin and one for the pixels on
  an edge (a depth step, an outline between objects, the border of the unusable).

The extra terms are significant when the F statistic of the nested pair exceeds its ``1 -
ALPHA`` quantile (:data:`tofhil.eval.diagnose.verdict.ALPHA`, the false-alarm rate of every
"above noise" test of a diagnosis). The residual is *organised by geometry* when they are
significant and carry most of what the two models explain together: the variance they add is
more than what the smooth field alone explains (:data:`GEOMETRY_SHARE`). With that share a
residual that is a smooth field with object steps on top of it is geometry when the steps are
larger than the field; a smooth field alone never is, at any strength.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np
from scipy import stats

#: The object and edge terms must carry more of the explained variance than the smooth
#: field: a majority, so that the larger of the two readings wins.
GEOMETRY_SHARE = 0.5
#: Fewer pixels than this say nothing about the organisation of a residual.
MIN_PIXELS = 50
#: Whitened residuals are winsorised at this many standard deviations: a few pixels unwrapped to
#: another interval (hundreds of mm) must not make an object's mean, while an object the twin
#: misplaces is tens of sigma off over all its pixels and stays far beyond noise when clipped.
CLIP_SIGMAS = 5.0


@dataclass(frozen=True)
class GeometryEvidence:
    """The nested-model test of a depth residual (module doc)."""

    organised: bool
    f_statistic: float
    p_value: float
    #: Share of the explained whitened variance that the object and edge terms add.
    share: float
    pixels: int
    #: Per object, the mean depth residual (mm) the geometry model gives it beyond the field.
    object_offsets_mm: dict[str, float]
    edge_offset_mm: float
    #: False when the base twin's residual is not organised so and the pattern is the fitted
    #: set's own (then never the scene's geometry).
    base_organised: bool = True

    def text(self) -> str:
        objs = ", ".join(f"{k} {v:+.1f} mm" for k, v in self.object_offsets_mm.items())
        what = "organised by the scene's objects and edges" if self.organised else "not organised by objects and edges"
        if not self.base_organised:
            what += " (the base twin's residual is not: an object pattern the fitted effects put there is theirs)"
        return (f"the depth residual is {what}: object and edge terms beyond a smooth field F = {self.f_statistic:.3g} "
                f"(p = {self.p_value:.2g}), {100 * self.share:.0f} % of the explained variance (needs "
                f"{100 * GEOMETRY_SHARE:.0f} %); median offset per object against the first "
                f"{objs or 'none'}, edges against the rest {self.edge_offset_mm:+.1f} mm")

    def to_json(self) -> dict[str, Any]:
        return {"organised": self.organised, "f_statistic": round(self.f_statistic, 4), "p_value": self.p_value,
                "share": round(self.share, 4), "pixels": self.pixels,
                "object_offsets_mm": {k: round(v, 3) for k, v in self.object_offsets_mm.items()},
                "edge_offset_mm": round(self.edge_offset_mm, 3), "base_organised": self.base_organised,
                "rule": self.text()}


def _field_terms(cols: np.ndarray, rows: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    u = 2.0 * cols / max(shape[1] - 1, 1) - 1.0
    v = 2.0 * rows / max(shape[0] - 1, 1) - 1.0
    return np.stack([u ** i * v ** j for i in range(4) for j in range(4 - i)], axis=1)


def geometry_evidence(depth_residual_m: np.ndarray, sigma_m: np.ndarray, pixels: np.ndarray, object_id: np.ndarray,
                      object_names: Mapping[int, str], edges: np.ndarray, alpha: float) -> GeometryEvidence | None:
    """The test on the pixels of ``pixels`` with a finite residual and noise; None when too
    few pixels carry one."""
    use = pixels & np.isfinite(depth_residual_m) & np.isfinite(sigma_m) & (sigma_m > 0)
    n = int(use.sum())
    if n < MIN_PIXELS:
        return None
    rows, cols = np.nonzero(use)
    w = 1.0 / sigma_m[use]
    y = np.clip(depth_residual_m[use] * w, -CLIP_SIGMAS, CLIP_SIGMAS)
    smooth = _field_terms(cols, rows, use.shape)
    ids = np.asarray(object_id)[use]
    # one indicator per object that holds pixels, less one (the field's constant stands for it)
    present = [i for i in np.unique(ids) if (ids == i).sum() >= 5]
    indicators = [(ids == i).astype(float) for i in present[1:]]
    edge = edges[use].astype(float)
    extra = indicators + ([edge] if 5 <= edge.sum() <= n - 5 else [])
    x0 = smooth * w[:, None]
    rss_none = float(y @ y)
    coef0, *_ = np.linalg.lstsq(x0, y, rcond=None)
    rss0 = float(np.sum((y - x0 @ coef0) ** 2))
    if not extra:
        return GeometryEvidence(False, 0.0, 1.0, 0.0, n, {}, 0.0)
    x1 = np.concatenate([x0, np.stack(extra, axis=1) * w[:, None]], axis=1)
    coef1, *_ = np.linalg.lstsq(x1, y, rcond=None)
    rss1 = float(np.sum((y - x1 @ coef1) ** 2))
    p0, p1 = x0.shape[1], x1.shape[1]
    dof = max(n - p1, 1)
    f = ((rss0 - rss1) / (p1 - p0)) / max(rss1 / dof, 1e-300)
    p = float(stats.f.sf(f, p1 - p0, dof))
    explained = rss_none - rss1
    share = (rss0 - rss1) / explained if explained > 0 else 0.0
    # each object's (and the edges') offset beyond the field, in mm: the median residual there
    # minus the first object's (the coefficients are in clipped sigma units)
    r_mm = depth_residual_m[use] * 1e3
    ref = float(np.median(r_mm[ids == present[0]])) if present else 0.0
    offsets = {object_names.get(int(i), f"object {int(i)}"): float(np.median(r_mm[ids == i])) - ref
               for i in present[1:]}
    edge_mm = float(np.median(r_mm[edge > 0]) - np.median(r_mm[edge == 0])) if len(extra) > len(indicators) else 0.0
    return GeometryEvidence(bool(p < alpha and share > GEOMETRY_SHARE), float(f), p, float(share), n, offsets, edge_mm)
