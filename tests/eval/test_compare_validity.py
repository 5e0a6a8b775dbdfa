"""Validity in compare is relative to each object's own amplitude (issue 17): a 1 % square
is dark, not a shadow of the bright card."""

from __future__ import annotations

import numpy as np

from tofhil.eval.metrics.core import lit_pixels


def test_a_dark_object_is_valid_relative_to_its_own_amplitude():
    amp = np.full((20, 30), 1.0)
    amp[:5, :5] = 100.0  # a bright card
    square = np.zeros_like(amp, bool)
    square[10:15, 10:20] = True
    amp[square] = 0.05  # 5 % of the wall, 5e-4 of the card
    amp[12, 12] = 1e-6  # a shadow inside the square stays invalid
    whole = lit_pixels(amp, 1e-3)
    assert not whole[square].any()  # relative to the brightest: the whole square is masked
    own = lit_pixels(amp, 1e-3, [square])
    assert own[square].sum() == square.sum() - 1 and not own[12, 12]
    assert (own[~square] == whole[~square]).all()
