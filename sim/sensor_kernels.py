"""Compiled noise-free taps (numba), for :meth:`SensorModel.taps_dn` without noise.

Diagnosis predicts the taps of a whole frame for every evaluation of a fit; as numpy
expressions that is a dozen passes over ``[F, K, H, W]`` float64 temporaries (most of a
prediction on a cached render). Here each pixel's taps are made in registers in one pass.
The arithmetic is the numpy expressions', operation by operation (no fast-math: no
reassociation, no fused multiply-add), so the taps are bit-identical to them.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, error_model="numpy", nogil=True)
def noise_free_taps(s_re, s_im, cos_h, sin_h, dc, gain, offset, e_w, contrast, dark_e, full_well_e,
                    conversion_gain, black_level, adc_max, out):  # pragma: no cover
    """``out[f, k, y, x]`` (float32) = clip((min(gain * max(photo, 0) + dark, full_well) +
    offset) * conversion_gain + black_level, 0, adc_max) with ``photo = e_w * (dc +
    contrast * sum_j (s_re[j] cos_h[j, k] + s_im[j] sin_h[j, k]))``; ``s_*`` ``[J, F, H, W]``
    (each harmonic's light times its correlation coefficient), ``dc`` ``[H, W]``, ``gain``
    and ``offset`` ``[K, H, W]``."""
    nj, nf, h, w = s_re.shape
    nk = cos_h.shape[1]
    for f in range(nf):
        for k in range(nk):
            for y in range(h):
                for x in range(w):
                    mod = 0.0
                    for j in range(nj):
                        mod += s_re[j, f, y, x] * cos_h[j, k] + s_im[j, f, y, x] * sin_h[j, k]
                    photo = e_w * (dc[y, x] + contrast * mod)
                    if photo < 0.0:
                        photo = 0.0
                    q = gain[k, y, x] * photo + dark_e
                    if q > full_well_e:
                        q = full_well_e
                    dn = (q + offset[k, y, x]) * conversion_gain + black_level
                    if dn < 0.0:
                        dn = 0.0
                    elif dn > adc_max:
                        dn = adc_max
                    out[f, k, y, x] = np.float32(dn)


__all__ = ["noise_free_taps"]
