"""Dark frames: a scene whose emitter is off (``power_w: 0``) renders the offset, ambient and
dark current alone (issue 34: it was refused, and 1e-12 W was the workaround)."""

from __future__ import annotations

import numpy as np

from tofhil.demod import phasor
from tofhil.sim.scene import scene_from_yaml
from tofhil.sim.twin import Twin

from tests.cli.test_hostile_inputs import SMALL_SCENE


def _frame(power: str):
    scene = scene_from_yaml(SMALL_SCENE.replace("power_w: 0.3", f"power_w: {power}"))
    return next(iter(Twin(scene).frames(frames=1, noise=False)))


def test_emitter_off_gives_the_offset_alone() -> None:
    dark, lit = _frame("0"), _frame("0.3")
    assert np.all(np.isfinite(dark.taps))
    s_dark = np.abs(phasor(dark.taps[0], dark.theta_rad))
    s_lit = np.abs(phasor(lit.taps[0], lit.theta_rad))
    assert s_dark.max() < 1e-6 * s_lit.mean()        # no modulated light
    assert dark.taps.mean() > 0                        # the offset (dark current) is still there
