"""The pixels a part of the data is scored on are chosen without that part's noise.

A pixel is usable when its amplitude is above a few noise sigma. Chosen on the frames it is
scored on, a pixel near the threshold is kept when its own noise lifted its amplitude, so its
residual points outward along its signal (about half a sigma at 3 to 5 sigma of signal): a
gain or a tap calibration then "explains" noise. Each frame set is therefore compared on
pixels chosen on the other set's amplitude. Statistics against statistics: over seeds of a
dim session with nothing hidden, the held-out residual along the signal has mean zero within
its standard error, where choosing on the held-out frames themselves shows the bias.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from tofhil.demod import phasor
from tofhil.eval.diagnose.heldout import split_session
from tofhil.session import open_session
from tofhil.sim.pipeline import simulate_session
from tofhil.sim.scene import load_scene

pytestmark = pytest.mark.slow


def _radial(data, truth: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Whitened held-out residual along the true signal, on ``mask`` pixels near the threshold."""
    s, var = data.s_test[0], data.var_test[0]
    u = truth / np.maximum(np.abs(truth), 1e-12)
    r = ((s - truth) * np.conj(u)).real / np.sqrt(var)
    snr = np.abs(truth) / np.sqrt(data.var_frame[0])
    near = mask & (snr > 2.0) & (snr < 6.0)
    return r[near]


def test_held_out_pixels_near_the_amplitude_threshold_carry_no_selection_bias(tmp_path):
    scene = load_scene("bench_demo")
    scene = dataclasses.replace(scene, camera=scene.camera.scaled(0.5),
                                emitter=dataclasses.replace(scene.emitter, power_w=scene.emitter.power_w * 0.03))
    clean = tmp_path / "clean.h5"
    simulate_session(scene, clean, frames=1, seed=0, noise=False)
    with open_session(clean) as s:
        f = s.raw_frame(0)
        truth = phasor(f.taps.astype(np.float64), f.theta_rad)[0]
    ours, own = [], []
    for seed in range(4):
        path = tmp_path / f"m{seed}.h5"
        simulate_session(scene, path, frames=4, seed=seed, noise=True)
        with open_session(path) as s:
            data = split_session(s)
        ours.append(_radial(data, truth, data.test_pixels))
        # the same pixels' choice made on the held-out frames themselves (what the split avoids)
        own_choice = np.abs(data.s_test[0]) > 3.0 * np.sqrt(data.var_frame[0])
        own.append(_radial(data, truth, own_choice & ~np.isnan(truth.real)))
    ours_all, own_all = np.concatenate(ours), np.concatenate(own)
    assert ours_all.size > 500 and own_all.size > 500
    se = ours_all.std() / np.sqrt(ours_all.size)
    assert abs(ours_all.mean()) < 4.0 * se + 0.02, (ours_all.mean(), se)
    # the bias the test exists for is there when the choice sees the noise it scores
    assert own_all.mean() > 0.1, own_all.mean()
