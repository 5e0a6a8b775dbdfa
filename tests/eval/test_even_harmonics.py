"""A duty cycle off 50 % adds even harmonics to the correlation waveform: invisible to 4 taps,
seen by 3 (the 2nd folds onto the fundamental as h = -1 mod 3). Diagnosis must try the
harmonics form on a 3-tap sensor even though its simple form (the 3rd harmonic) is invisible."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from tests.eval.hidden_forms import write_session
from tests.eval.hidden_scalar_forms import odd_harmonics


def _three_tap_dark_square():
    from tests.eval.hidden_forms import small_dark_square

    scene = small_dark_square(80)
    return dataclasses.replace(scene, sensor=dataclasses.replace(
        scene.sensor, theta_rad=tuple(2 * math.pi * k / 3 for k in range(3))))


def test_which_harmonics_reach_three_and_four_taps():
    from tofhil.sim.effects import EFFECTS

    wig = EFFECTS["wiggling"]
    seen = {k: sorted(int(p[1]) for p in wig.form_params("harmonics", k) if p.endswith("_amplitude"))
            for k in (3, 4)}
    # h = +-1 mod K: K = 3 sees 2, 4, 5, 7; K = 4 sees 3, 5, 7
    assert seen == {3: [2, 4, 5, 7], 4: [3, 5, 7]}
    assert not wig.form_params("", 3)  # the simple form's 3rd harmonic cancels on 3 taps


@pytest.mark.parametrize("seed", [0, 1])
def test_a_second_harmonic_on_three_taps_is_found(tmp_path, seed):
    from tofhil.eval.diagnose.run import diagnose

    scene = _three_tap_dark_square()
    change = odd_harmonics(np.random.default_rng(seed), orders=(2,), amplitude=(0.03, 0.06))
    hidden = change.coef[2]
    path = write_session(scene, tmp_path / "h2.h5", change, frames=4, seed=seed)
    res = diagnose(path, scene, max_effects=1)
    assert res.causes == ["wiggling"], res.evidence
    p = res.params["wiggling"]
    fitted = p["h2_amplitude"] * np.exp(1j * p["h2_phase_rad"])
    assert abs(fitted - hidden) < 0.2 * abs(hidden)
