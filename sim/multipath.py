"""Where the multipath comes from: per pixel, the share of the returned light by bounce count
and by the object the light came from.

From one render with ``multipath_shares=True`` (the same paths as any render: the renderer
adds each emitter connection to a row per (bounce count, source object), see
:func:`tofhil.sim.kernels.share_row`):

- **bounce**: 0 = direct (emitter -> seen surface -> camera), ``b`` = light that reflected
  off ``b`` surfaces before the one the pixel sees;
- **source object**: for direct light the object the pixel sees; for indirect light the
  object of the vertex *before* the seen surface (the last diffuse vertex before the light
  returns to the seen surface: for one bounce, the wall that lit the seen point). So a map of
  object ``o`` says how much of each pixel's light was reflected onto it from ``o``.

Shares are fractions of the pixel's rendered emitter power (``power_w``); they sum to 1 in
every pixel that receives light and are NaN where none arrives. Separate renders per bounce
count would not give the same: the sampler's points depend on the number of dimensions
(``4 + 2 * bounces``), so bounce ``B`` is not a prefix of a ``B + 1`` render's paths.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass
class MultipathShares:
    """Per-pixel shares of the returned light ``[.., H, W]`` (NaN where no light returns)."""

    by_bounce: np.ndarray        # [B + 1, H, W]: 0 direct, 1 one bounce, ...
    by_object: np.ndarray        # [O, H, W]: the object the light came from
    object_names: tuple[str, ...]
    power_w: np.ndarray          # [H, W] the pixel's emitter power (W)

    @property
    def indirect(self) -> np.ndarray:
        """Share of light that bounced at least once (1 - direct share)."""
        return np.nansum(self.by_bounce[1:], axis=0) + np.where(np.isnan(self.by_bounce[0]), np.nan, 0.0)

    def summary(self) -> dict[str, Any]:
        """Mean shares over the lit pixels (plain numbers for a report's JSON)."""
        lit = np.isfinite(self.by_bounce[0])
        return {"pixels_lit": int(lit.sum()),
                "mean_share_by_bounce": [float(np.mean(b[lit])) if lit.any() else None for b in self.by_bounce],
                "mean_share_by_object": {n: float(np.mean(o[lit])) if lit.any() else None
                                         for n, o in zip(self.object_names, self.by_object)}}


def shares_from_render(result: Any, object_names: tuple[str, ...] | list[str]) -> MultipathShares:
    """The shares of a render made with ``multipath_shares=True``."""
    sp = result.share_power_w
    if sp is None:
        raise ValueError("the render has no share_power_w: render with multipath_shares=True")
    total = sp.sum(axis=(0, 1))
    with np.errstate(invalid="ignore", divide="ignore"):
        inv = np.where(total > 0, 1.0 / total, np.nan)
    return MultipathShares(by_bounce=sp.sum(axis=1) * inv, by_object=sp.sum(axis=0) * inv,
                           object_names=tuple(object_names), power_w=total)


def multipath_shares(scene: Any, **render_kwargs: Any) -> MultipathShares:
    """Render ``scene`` (its ``render:`` settings unless overridden) and return its shares."""
    from tofhil.sim.render import render

    res = render(scene, freq_hz=[0.0], multipath_shares=True, **render_kwargs)
    return shares_from_render(res, [o.name for o in scene.objects])


__all__ = ["MultipathShares", "multipath_shares", "shares_from_render"]
