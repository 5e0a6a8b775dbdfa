"""The light from a surface the scene lacks, against closed forms and against the path tracer.

A reflector straight behind the camera on its axis at distance d lights the centre of a wall
at distance D head-on: the extra path is ``d + (D + d) - D = 2 d`` and the share of the direct
light is ``area D^2 / (D + d)^2`` (inverse-square law, all cosines 1, the beam 1 on the
axis). A panel that the path tracer renders as a real object outside the view gives the same
smooth extra light and phase as the fitted patch.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from tofhil import C_M_PER_S
from tofhil.sim.effects import EFFECTS, EffectContext
from tofhil.sim.effects.unseen_reflector import scene_points
from tofhil.sim.scene import load_scene
from tofhil.sim.twin import Twin

EFFECT = EFFECTS["unseen_reflector"]


@pytest.fixture(scope="module")
def wall():
    scene = load_scene("dark_square")
    twin = Twin(scene)
    _, result = twin.render()
    return scene, twin, result


def _ctx(scene, result) -> EffectContext:
    return EffectContext(camera=scene.camera, radial_m=result.radial_m, emitter=None)  # emitter at the lens


def _behind(scene, d: float) -> dict[str, float]:
    # polar angle pi: straight behind the camera, whatever the view's half-diagonal
    return {"azimuth_deg": 0.0, "beyond_deg": 150.0, "distance_m": d, "log_area": math.log10(0.02),
            "turn_deg": 0.0, "tilt_deg": 0.0}


@pytest.mark.parametrize("d", [0.3, 1.0])
def test_behind_the_camera_closed_form(wall, d: float) -> None:
    scene, _, result = wall
    values = _behind(scene, d)
    p = EFFECT.position(values, scene.camera)
    assert np.allclose(p, [0.0, 0.0, -d], atol=1e-9)
    ratio, excess = EFFECT.share(values, _ctx(scene, result), scene.camera.shape)
    h, w = scene.camera.shape
    # the pixel nearest the axis: its wall point is at D, its ray 0.5 px off axis at most
    i, j = h // 2, w // 2
    big_d = float(result.radial_m[i, j])
    assert excess[i, j] == pytest.approx(2 * d, abs=2e-4 * big_d)
    assert ratio[i, j] == pytest.approx(0.02 * big_d ** 2 / (big_d + d) ** 2, rel=2e-3)


def test_phase_of_the_extra_light_follows_its_path(wall) -> None:
    scene, twin, result = wall
    values = _behind(scene, 0.5)
    sig = twin.signal()
    out = EFFECT.apply_signal(sig, values, _ctx(scene, result))
    ratio, excess = EFFECT.share(values, _ctx(scene, result), sig.shape)
    f = float(sig.freq_hz[0])
    added = out.phasor_w[0, 0] - sig.phasor_w[0, 0]
    lit = ratio > 0
    # added light = direct * ratio * exp(i 2 pi f excess / c), and its power adds to dc
    expect = sig.phasor_w[0, 0] * ratio * np.exp(2j * np.pi * f * excess / C_M_PER_S)
    assert np.allclose(added[lit], expect[lit], rtol=1e-9, atol=0)
    assert np.allclose(out.dc_w, np.asarray(sig.dc_w) * (1 + ratio), rtol=1e-12)


def test_off_changes_nothing(wall) -> None:
    scene, twin, result = wall
    sig = twin.signal()
    assert EFFECT.is_off(EFFECT.off_values())
    out = EFFECT.apply_signal(sig, EFFECT.off_values(), _ctx(scene, result))
    assert np.allclose(out.phasor_w, sig.phasor_w, rtol=1e-9)


def test_plane_normals_from_hits(wall) -> None:
    scene, _, result = wall
    _, n, hit = scene_points(result.radial_m, scene.camera)
    inner = n[5:-5, 5:-5][hit[5:-5, 5:-5]]
    assert np.median(inner[:, 2]) == pytest.approx(-1.0, abs=1e-6)  # the wall faces the camera


def test_needs_first_hit_distances(wall) -> None:
    scene, twin, _ = wall
    with pytest.raises(ValueError, match="first-hit distances"):
        EFFECT.apply_signal(twin.signal(), _behind(scene, 0.5), EffectContext(camera=scene.camera))


def test_against_the_path_tracer(tmp_path, wall) -> None:
    """A 0.5 m white panel beside the camera, rendered with one bounce by the path tracer,
    against the patch fitted to it: the share of the extra light agrees to a small part of it."""
    import yaml

    from tofhil.sim.render import render
    from tofhil.sim.scene import scenes_dir

    scene, _, result = wall
    d = yaml.safe_load((scenes_dir() / "dark_square.yaml").read_text())
    centre, aim, size, albedo = np.array([-0.42, 0.0, 0.33]), np.array([0.0, 0.0, 0.6]), 0.5, 0.9
    d["materials"]["panel"] = {"reflectance": albedo}
    d["objects"].append({"name": "panel", "type": "plane", "size": [size, size], "material": "panel",
                         "pose": {"position": centre.tolist(), "look_at": aim.tolist()}})
    d["render"] = {"samples_per_pixel": 32, "bounces": 1}
    path = tmp_path / "panel.yaml"
    path.write_text(yaml.safe_dump(d))
    with_panel = render(load_scene(path), separate_direct=True)
    assert int((with_panel.object_id == 2).sum()) == 0   # the panel is outside the view
    share = with_panel.phasor_indirect[0, 0] / with_panel.phasor_direct[0, 0]
    # the extra light is smooth over the wall, the Monte Carlo noise of 32 samples per pixel
    # is not: the share averaged over 9 x 9 pixels
    from scipy.ndimage import uniform_filter
    share = uniform_filter(share.real, 9) + 1j * uniform_filter(share.imag, 9)
    # the patch at the panel's centre, facing where the panel faces; its effective area from
    # the panel: the emitter's beam toward it (cos^2) and its cosine there, albedo / pi, size
    dist = float(np.linalg.norm(centre))
    edge = float(np.max(np.arccos(scene.camera.rays[..., 2])))
    normal = (aim - centre) / np.linalg.norm(aim - centre)
    area = ((centre[2] / dist) ** 2 * float(normal @ (-centre / dist)) / dist ** 2) * albedo / math.pi * size ** 2
    values = {"azimuth_deg": 180.0, "beyond_deg": math.degrees(math.acos(centre[2] / dist) - edge),
              "distance_m": dist, "log_area": math.log10(area), "turn_deg": 0.0, "tilt_deg": 0.0}
    x, _, hit = scene_points(result.radial_m, scene.camera)
    toward = EFFECT.normal(values, centre, x, hit)
    turn = math.degrees(math.atan2(normal[0], normal[2]) - math.atan2(toward[0], toward[2]))
    values["turn_deg"] = turn   # the panel looks at a point nearer than the wall's centre
    ctx = EffectContext(camera=scene.camera, radial_m=result.radial_m, emitter=scene.emitter)
    ratio, excess = EFFECT.share(values, ctx, scene.camera.shape)
    f = float(scene.sensor.freq_hz[0])
    model = ratio * np.exp(2j * np.pi * f * excess / C_M_PER_S)
    inner = (slice(10, -10), slice(10, -10))
    a = float(np.real(np.vdot(model[inner], share[inner]) / np.vdot(model[inner], model[inner])))
    assert a == pytest.approx(1.0, abs=0.25)      # the closed-form area, to the panel's extent
    resid = share[inner] - a * model[inner]
    rms_share = float(np.sqrt(np.mean(np.abs(share[inner]) ** 2)))
    # the panel is 0.5 m wide at 0.5 m: a patch is its first-order form, so the shape agrees
    # to a fraction of the extra light
    print("patch vs path tracer: rms residual / rms share", float(np.sqrt(np.mean(np.abs(resid) ** 2))) / rms_share)
    assert float(np.sqrt(np.mean(np.abs(resid) ** 2))) < 0.2 * rms_share
    assert np.angle(np.mean(share[inner])) == pytest.approx(np.angle(np.mean(model[inner])), abs=0.05)
