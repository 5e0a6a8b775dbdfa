"""The twin's forward model (tofhil.sim.twin.Twin): its fast paths against full renders, and
its render cache keyed by content.

Invariants checked (no numbers copied from the code's output):
- a scene-stage effect applied to a cached render (reflectance, ambient) gives the taps of a
  full render with that effect rendered in (pipeline.prepare_render + expected_taps), to
  float rounding; where the rescaling would not be exact (two bounces) the twin re-renders;
- render-, signal- and pixel-stage effects on the twin give bit for bit what the pipeline
  computes from the same render;
- two scenes with the same content share a render, a changed material does not.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from tofhil.sim import pipeline
from tofhil.sim.render import content_key, render, scene_geometry
from tofhil.sim.scene import load_scene, scene_from_yaml, scene_to_yaml
from tofhil.sim.twin import Twin, render_key


@pytest.fixture(scope="module")
def scene():
    # 40 x 30 pixels, direct light only (the bundled scene's render settings)
    s = load_scene("bench_demo")
    return dataclasses.replace(s, camera=s.camera.scaled(0.25))


def _full(scene, effects: dict, render_kwargs: dict | None = None) -> np.ndarray:
    """Taps of a full render with every scene-stage effect rendered in."""
    scene2, rr = pipeline.prepare_render(scene, effects, render_kwargs=render_kwargs)
    return pipeline.expected_taps(scene2, rr, effects)


FAST = [
    {"reflectance": {"scale": 1.3}},
    {"reflectance": {"scale": 0.6}, "stray_light": {"weight": 0.03, "sigma_px": 6.0}},
    {"ambient": {"irradiance_w_m2": 4.0}},
    {"reflectance": {"scale": 1.15}, "ambient": {"irradiance_w_m2": 2.5}, "range_offset": {"path_m": 0.03}},
]


@pytest.mark.parametrize("effects", FAST)
def test_rescaled_render_equals_a_full_render(scene, effects):
    twin = Twin(scene, effects={})
    base = twin.expected_taps()
    got = twin.expected_taps(twin.effects(effects))
    assert twin.renders == 1, "reflectance and ambient must not re-render on this scene"
    want = _full(scene, effects)
    assert not np.allclose(want, base, rtol=1e-3), "the effect must change the taps for the test to mean anything"
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-3)


def test_rescaling_from_a_base_scene_that_already_has_the_effect(scene):
    base = {"reflectance": {"scale": 0.8}, "ambient": {"irradiance_w_m2": 1.0}}
    twin = Twin(scene, effects=base)
    target = {"reflectance": {"scale": 1.25}, "ambient": {"irradiance_w_m2": 3.0}}
    got = twin.expected_taps(twin.effects(target))
    assert twin.renders == 1
    np.testing.assert_allclose(got, _full(scene, target), rtol=1e-5, atol=1e-3)


def test_reflectance_with_one_bounce_rescales_direct_and_indirect_light(scene):
    # one bounce: the indirect light scales with s^2, exactly
    twin = Twin(scene, effects={})
    eff = twin.effects({"multipath": {"scale": 1.0, "bounces": 1}, "reflectance": {"scale": 1.4}})
    got = twin.expected_taps(eff)
    assert twin.renders == 1
    full = {"multipath": {"scale": 1.0, "bounces": 1}, "reflectance": {"scale": 1.4}}
    np.testing.assert_allclose(got, _full(scene, full), rtol=1e-5, atol=1e-3)


def test_reflectance_with_two_bounces_is_rendered_in(scene):
    # light that bounced twice scales with s^3: a rescaled render would be wrong, so the twin renders
    twin = Twin(scene, effects={})
    eff = twin.effects({"multipath": {"scale": 1.0, "bounces": 2}, "reflectance": {"scale": 1.4}})
    got = twin.expected_taps(eff)
    assert twin.renders == 2  # the base values' render, then the exact one
    np.testing.assert_array_equal(got, _full(scene, {"multipath": {"scale": 1.0, "bounces": 2},
                                                     "reflectance": {"scale": 1.4}}))


@pytest.mark.parametrize("effects", [
    {},
    {"stray_light": {"weight": 0.04, "sigma_px": 5.0, "veil": 0.01}, "wiggling": {"h3_amplitude": 0.05}},
    {"fixed_pattern": {"row_delay_s": 3e-12, "col_delay_s": -2e-12},
     "amplitude_dependent": {"error_m": 0.05, "amplitude_e": 3000.0}},
    {"pose": {"rx": 0.01, "tz": 0.02}, "lens_distortion": {"k1": -0.1}},
    {"multipath": {"scale": 1.5, "bounces": 1}},
])
def test_noise_free_taps_equal_the_pipeline_on_the_same_render(scene, effects):
    twin = Twin(scene, effects=effects)
    scene2, rr = twin.render()
    np.testing.assert_array_equal(twin.expected_taps(), pipeline.expected_taps(scene2, rr, effects))
    frame = next(iter(twin.frames(frames=1, noise=False)))
    np.testing.assert_array_equal(frame.taps, pipeline.simulate(scene, 1, noise=False, effects=effects)[0].taps)


def test_render_cache_is_keyed_by_content_not_identity(scene):
    twin = Twin(scene, effects={})
    twin.expected_taps({"stray_light": {"weight": 0.02}})
    twin.expected_taps({"range_offset": {"path_m": 0.01}})
    assert twin.renders == 1  # signal-stage effects reuse the render
    again = scene_from_yaml(scene_to_yaml(scene))  # new objects, same content
    again = dataclasses.replace(again, camera=scene.camera)
    args = {"freq_hz": [20e6], "harmonics": (1,)}
    assert render_key(again, args) == render_key(scene, args)
    assert scene_geometry(again) is scene_geometry(scene)
    darker = dataclasses.replace(scene, materials={k: dataclasses.replace(m, reflectance=m.reflectance * 0.5)
                                                   for k, m in scene.materials.items()})
    assert render_key(darker, args) != render_key(scene, args)
    assert render_key(scene, {**args, "bounces": 1}) != render_key(scene, args)
    assert content_key({"a": 1, "b": 2}) == content_key({"b": 2, "a": 1})
    assert content_key(np.zeros(3)) != content_key(np.zeros(3, np.float32))


def test_base_render_outlives_a_run_of_other_renders_and_is_shared(scene):
    # a pose fit renders many poses in a row: the base render stays cached (pinned), and a
    # twin of the same scene with another effects block (the extended scene) reuses it
    twin = Twin(scene, effects={}, cache_size=2)
    base = twin.expected_taps()
    for i in range(5):
        twin.expected_taps({"pose": {"tz": 0.001 * (i + 1)}})
    assert twin.renders == 6 and len(twin.cache) <= 3
    np.testing.assert_array_equal(twin.expected_taps(), base)
    assert twin.renders == 6
    extended = dataclasses.replace(scene, source="elsewhere.yaml")
    other = Twin(extended, effects={"stray_light": {"weight": 0.02}}, cache=twin.cache)
    other.expected_taps()
    assert other.renders == 0
    np.testing.assert_array_equal(other.expected_taps({}), base)


def test_ambient_power_is_linear_in_the_irradiance(scene):
    lit = dataclasses.replace(scene, ambient_irradiance_w_m2=3.0)
    r = render(lit, freq_hz=[20e6])
    np.testing.assert_allclose(r.ambient_power_w, 3.0 * r.ambient_power_per_irradiance, rtol=1e-12)
    dark = render(scene, freq_hz=[20e6])
    assert np.all(dark.ambient_power_w == 0)
    np.testing.assert_allclose(dark.ambient_power_per_irradiance, r.ambient_power_per_irradiance, rtol=1e-12)



def test_render_cache_bounds_the_bytes_of_its_unpinned_renders():
    # renders as small arrays: a budget of 3 of them keeps the 3 newest, the pinned one
    # aside, and a render larger than the whole budget is still kept when it is the newest
    from tofhil.sim.twin import RenderCache

    @dataclasses.dataclass
    class Fake:
        a: np.ndarray

    each = Fake(np.zeros(128)).a.nbytes
    cache = RenderCache(size=8, max_bytes=3 * each)
    cache.put("base", Fake(np.zeros(128)), pin=True)
    for i in range(5):
        cache.put(f"r{i}", Fake(np.zeros(128)))
    assert list(cache.entries) == ["base", "r2", "r3", "r4"]
    cache.put("big", Fake(np.zeros(1024)))
    assert list(cache.entries) == ["base", "big"]
    assert cache.get("base") is not None and cache.get("r4") is None


def test_a_whole_frame_drops_the_renders_of_some_pixels(scene):
    # the renders of a fit's pixels are not asked for again once a whole frame is rendered
    # (the fit ended): they go, and a pixel asked for again is rendered again, the same
    twin = Twin(scene, effects={})
    pixels = np.zeros(scene.camera.shape, dtype=bool)
    pixels[::7, ::5] = True
    moved = {"pose": {"tz": 0.002}}
    first = twin.expected_taps_at(moved, pixels)
    assert len(twin.pixel_cache) == 1
    whole = twin.expected_taps(moved)
    assert len(twin.pixel_cache) == 0
    again = twin.expected_taps_at(moved, pixels)  # (the whole frame serves now)
    np.testing.assert_array_equal(again, first)
    np.testing.assert_array_equal(again[:, :, 0], whole[:, :, pixels])


POINTWISE = [
    {},
    {"wiggling": {"h3_amplitude": 0.03, "h3_phase_rad": 0.4}},
    {"fixed_pattern": {"row_delay_s": 2e-12, "col_delay_s": -1e-12, "random_delay_s": 5e-12, "seed": 3}},
    {"field_angle": {"c2_m": 0.01, "c4_m": 0.002}},
    {"illumination": {"dn": 0.5, "b4": 0.1, "b6": 0.01}},
    {"amplitude_dependent": {"error_m": 0.01}},
    {"unseen_reflector": {"log_area": -2.0, "azimuth_deg": 170.0}},
    {"offset": {"dark_e": 1000.0}, "range_offset": {"path_m": 0.01}},
    {"range_offset_map": {"values": (0.002 * np.arange(30 * 40).reshape(30, 40) % 0.013).tolist()}},
    {"tap_calibration": {"gain_1": 1.03, "offset_3_dn": 4.0}, "multipath": {"scale": 1.2}},
    # stray light moves light between pixels: the whole frame's signal, then the pixels
    {"stray_light": {"weight": 0.03, "sigma_px": 6.0}, "wiggling": {"h3_amplitude": 0.02}},
]


@pytest.mark.parametrize("effects", POINTWISE, ids=lambda e: "+".join(e) or "base")
def test_taps_at_some_pixels_equal_the_whole_frame_there(scene, effects):
    """A prediction on some pixels runs the pointwise effects on those pixels alone (the
    position-dependent ones take their fields there, unseen_reflector its geometry from the
    whole render): bit for bit the whole frame's taps at those pixels."""
    twin = Twin(scene)
    eff = twin.effects(effects)
    pixels = np.random.default_rng(4).random(scene.camera.shape) < 0.2
    full = twin.expected_taps(eff)
    at = twin.expected_taps_at(eff, pixels)
    assert twin.pointwise(eff) == ("stray_light" not in effects)
    np.testing.assert_array_equal(at[:, :, 0], full[:, :, pixels])
