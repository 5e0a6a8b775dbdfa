"""The emulator's simulated source: the twin's scene rendered through a hidden-truth camera
model. Frames read through the real driver must match the twin *with* the hidden effects and
differ measurably from the twin that does not know them."""

from __future__ import annotations

import numpy as np
import pytest

from tofhil.depth import depth_from_raw
from tofhil.drivers.base import CaptureSettings
from tofhil.drivers.tofcam635.emulator import EmulatedTofCam635, Epc635Emulator
from tofhil.sim.sources import HIDDEN_TRUTH_EFFECTS, TOFCAM635_OVERRIDES, SimulatedSource
from tofhil.frames import RawFrame

pytest.importorskip("tofhil.sim.pipeline")


def _twin_radial(scene, effects) -> np.ndarray:
    from tofhil.sim.pipeline import simulate

    raw = simulate(scene, 1, 0, noise=False, effects=effects)[0]
    return depth_from_raw(raw).radial_m


def test_emulated_frames_carry_the_hidden_truth_the_twin_lacks() -> None:
    from tofhil.sim.pipeline import resolve_effects
    from tofhil.sim.scene import load_scene

    source = SimulatedSource("wall")
    emu = Epc635Emulator(source, seed=1)
    with EmulatedTofCam635("emulator", emulator=emu) as dev:
        dev.configure(CaptureSettings(mode="dcs", integration_time_s=250e-6, mod_freq_hz=20e6))
        frames = [f.raw for f in dev.stream(12)]
        assert "simulated scene wall" in dev.info().extra["source"]
    first = frames[0]
    assert isinstance(first, RawFrame) and first.taps.shape == (1, 4, 60, 160)
    mean = RawFrame(taps=np.mean([f.taps for f in frames], axis=0), freq_hz=first.freq_hz,
                    theta_rad=first.theta_rad, integration_time_s=first.integration_time_s, camera=first.camera)
    measured = depth_from_raw(mean).radial_m

    scene = load_scene("wall", overrides={**TOFCAM635_OVERRIDES, "sensor": {
        **TOFCAM635_OVERRIDES["sensor"], "freq_hz": [20e6]}})
    known = resolve_effects(scene, None)
    truth = _twin_radial(scene, {**known, **HIDDEN_TRUTH_EFFECTS})
    twin = _twin_radial(scene, known)

    to_truth = float(np.median(np.abs(measured - truth)))
    to_twin = float(np.median(np.abs(measured - twin)))
    assert to_truth < 5e-3  # ~1 cm per-pixel noise averaged over 12 frames, 12-bit DCS quantisation
    assert to_twin > max(3 * to_truth, 0.01)  # wiggling, delay pattern and stray light the twin does not model
    # the wall is 1.0 m away on the axis: both agree on the gross geometry
    assert abs(float(np.median(measured * first.camera.ray_z)) - 1.0) < 0.06
    # the session records the twin's scene, not the hidden truth
    text = source.scene_text()
    assert "wall" in text and "wiggling" not in text and "h3_amplitude" not in text
