"""The emitter displaced from where the scene puts it (``emitter_position``): the optical path
and the irradiance follow the geometry, and diagnosis names a hidden displacement."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from tofhil import C_M_PER_S


def _wall(width: int = 40):
    from tofhil.sim.scene import load_scene

    scene = load_scene("wall")
    return dataclasses.replace(scene, camera=scene.camera.scaled(width / scene.camera.width))


@pytest.mark.parametrize("dz", [0.04, -0.05])
def test_an_emitter_moved_along_the_axis_changes_path_and_irradiance_as_geometry_says(dz):
    """A pixel seeing the wall straight ahead at distance D from the lens: the emitter moved by
    ``dz`` along the axis makes the path ``(D - dz) + D`` (range ``D - dz / 2``) and the
    irradiance ``1 / (D - dz)^2`` of the unmoved emitter's ``1 / D^2`` (the beam's angle is 0 there)."""
    from tofhil.sim.twin import Twin

    scene = _wall()
    twin = Twin(scene)
    f = float(scene.sensor.freq_hz[0])
    off = twin.signal()
    moved = twin.signal(twin.effects({"emitter_position": {"dx": 0.0, "dy": 0.0, "dz": dz}}))
    k = off.harmonics.index(1)
    cam = scene.camera
    v, u = int(round(cam.cy)), int(round(cam.cx))
    s0, s1 = off.phasor_w[0, k, v, u], moved.phasor_w[0, k, v, u]
    d = float(np.linalg.norm(np.asarray(scene.emitter.offset_m)))  # the scene's own emitter offset
    assert d < 0.05
    # the range from the phase change (the phasor turns by 2 pi f dL / c)
    dl = float(np.angle(s1 / s0)) * C_M_PER_S / (2 * np.pi * f)
    assert dl == pytest.approx(-dz, abs=2e-3 + 0.05 * abs(dz))
    # the distance straight ahead from the amplitude ratio
    ratio = abs(s1) / abs(s0)
    distance = float(C_M_PER_S * np.angle(s0) / (4 * np.pi * f)) % (C_M_PER_S / (2 * f))
    expected = (distance / (distance - dz)) ** 2
    assert ratio == pytest.approx(expected, rel=0.02)


def test_a_hidden_emitter_displacement_is_named_and_fitted():
    """The issue's case: the emitter 4 cm further from the scene than the scene says (the
    dark_square bench); diagnosis names emitter_position and fits dz = -4 cm."""
    from tests.eval import hidden_forms as hf
    from tofhil.eval.diagnose.run import diagnose

    scene = hf.small_dark_square(80)
    e = scene.emitter
    hidden = dataclasses.replace(scene, emitter=dataclasses.replace(
        e, offset_m=np.asarray(e.offset_m, float) + np.array([0.0, 0.0, -0.04])))
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as td:
        path = hf.write_session(hidden, Path(td) / "e.h5", None, frames=4, seed=3)
        res = diagnose(path, scene, max_effects=2)
    assert res.causes[:1] == ["emitter_position"], res.evidence
    assert res.params["emitter_position"]["dz"] == pytest.approx(-0.04, abs=0.006)
