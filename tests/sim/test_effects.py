"""The effect library: every effect is identity at its off values, and each changes the model
the way its physics says (checked through the sensor and demodulation, against closed forms)."""

from __future__ import annotations

import dataclasses

import math
from types import SimpleNamespace

import numpy as np
import pytest

from tofhil.camera import CameraModel
from tofhil.depth import depth_from_raw
from tofhil.errors import InputFileError
from tofhil.sim.effects import (EFFECTS, ORDER, STAGES, EffectContext, apply_scene_effects,
                                apply_signal_effects, parse_effects)
from tofhil.sim.scene import RenderSettings
from tofhil.sim.sensor import OpticalSignal, SensorConfig, SensorModel

C = 299_792_458.0
F = 44.0e6
NAMES = {"stray_light", "multipath", "wiggling", "range_offset", "fixed_pattern", "amplitude_dependent",
         "lens_distortion", "ambient", "reflectance", "pose", "offset", "field_angle", "illumination",
         "range_offset_map", "frequency_calibration", "tap_calibration", "unseen_reflector", "emitter_position",
         "gain_field", "offset_field"}
#: Effects whose data are an option (a map), not parameters with defaults: switched on with these.
ON_OPTIONS = {"range_offset_map": lambda cam: {"values": np.full(cam.shape, 0.01)}}


def _cam(w: int = 24, h: int = 18) -> CameraModel:
    return CameraModel.from_fov(w, h, 60.0)


def _signal(cam: CameraModel, d: np.ndarray | float, p: np.ndarray | float = 1e-11) -> OpticalSignal:
    d = np.broadcast_to(np.asarray(d, float), cam.shape)
    p = np.broadcast_to(np.asarray(p, float), cam.shape)
    s = (p * np.exp(1j * 4 * np.pi * F * d / C))[None, None]
    return OpticalSignal(freq_hz=[F], harmonics=(1,), phasor_w=s, dc_w=p, ambient_w=np.zeros(cam.shape))


def _sensor(cam: CameraModel) -> SensorModel:
    cfg = SensorConfig.from_dict({"freq_hz": [F], "read_noise_e": 0, "dark_current_e_per_s": 0,
                                  "adc_bits": 20, "full_well_e": 1e7}, camera=cam)
    return SensorModel(cfg, cam)


def _read(cam: CameraModel, signal: OpticalSignal) -> np.ndarray:
    return depth_from_raw(_sensor(cam).expose(signal, noise=False)).distance_m


def _ctx(cam: CameraModel) -> EffectContext:
    return EffectContext(camera=cam, sensor=_sensor(cam).config)


def test_registry_has_the_shared_vocabulary_with_sane_declarations() -> None:
    assert set(EFFECTS) == NAMES and set(ORDER) == NAMES
    for name, eff in EFFECTS.items():
        assert eff.name == name and eff.stage in STAGES and eff.doc and (eff.params or name in ON_OPTIONS)
        for pname, p in eff.params.items():
            assert p.lo <= p.off <= p.hi, (name, pname)
            assert p.lo <= p.on_default <= p.hi, (name, pname)
            assert p.lo < p.hi and p.doc


def test_forward_model_order_is_fixed_whatever_the_registration_order() -> None:
    # the effects register themselves from their family modules; the order they apply in is
    # by rank, and it is this one (optics before the pixel; per-pixel effects after the
    # spatial mixing): a new module must not move it
    order = ("pose", "emitter_position", "lens_distortion", "reflectance", "ambient", "multipath", "unseen_reflector", "illumination",
             "gain_field", "stray_light", "offset", "offset_field", "range_offset", "field_angle", "fixed_pattern", "range_offset_map", "frequency_calibration",
             "amplitude_dependent", "wiggling", "tap_calibration")
    assert ORDER == order and tuple(EFFECTS) == order


def test_registry_refuses_a_taken_name_or_rank_and_a_missing_hook() -> None:
    from tofhil.sim.effects import Effect, register

    class Twice(Effect):
        name, stage, rank = "pose", "scene", 999

        def apply_scene(self, scene, values):
            return scene

    class SameRank(Twice):
        name, rank = "new_effect", EFFECTS["wiggling"].rank

    class NoHook(Effect):
        name, stage, rank = "no_hook", "signal", 998

    for cls in (Twice, SameRank, NoHook):
        with pytest.raises(TypeError):
            register(cls)
    assert tuple(EFFECTS) == ORDER and "no_hook" not in EFFECTS


# (frequency_calibration acts on a second frequency, which this one-frequency signal lacks:
# tests/sim/test_calibration_effects.py)
@pytest.mark.parametrize("name", [n for n in ORDER if EFFECTS[n].stage in ("signal", "pixel")
                                  and n != "frequency_calibration"])
def test_signal_effects_are_identity_at_their_off_values(name: str) -> None:
    cam = _cam()
    rng = np.random.default_rng(0)
    dist = rng.uniform(0.5, 3, cam.shape)
    sig = _signal(cam, dist, rng.uniform(1e-12, 1e-11, cam.shape))
    eff = parse_effects({name: EFFECTS[name].off_values()})
    ctx = dataclasses.replace(_ctx(cam), radial_m=dist)   # (the scene's geometry, for unseen_reflector)
    out = apply_signal_effects(sig, eff, ctx)
    np.testing.assert_allclose(out.phasor_w, sig.phasor_w, rtol=1e-12, atol=0)
    np.testing.assert_allclose(out.dc_w, sig.dc_w, rtol=1e-12)
    assert out.waveform == sig.waveform
    # ... and not identity when switched on with its defaults (an effect that does nothing
    # would pass the test above trivially).
    on = apply_signal_effects(sig, parse_effects({name: ON_OPTIONS[name](cam) if name in ON_OPTIONS else {}}), ctx)
    assert (not np.allclose(on.phasor_w, sig.phasor_w, rtol=1e-6, atol=0) or on.waveform != sig.waveform
            or not np.allclose(on.ambient_w, sig.ambient_w, rtol=1e-6, atol=0))


def test_range_offset_shifts_radial_distance_by_half_the_path() -> None:
    cam = _cam()
    d = np.linspace(0.5, 2.0, cam.width)[None].repeat(cam.height, 0)
    sig = _signal(cam, d)
    got = _read(cam, apply_signal_effects(sig, parse_effects({"range_offset": {"path_m": 0.24}}), _ctx(cam)))
    np.testing.assert_allclose(got, d + 0.12, atol=2e-5)
    # A path offset of one modulation wavelength c/f is invisible (phase wraps at 2 pi).
    quarter = parse_effects({"range_offset": {"path_m": C / F / 4}})  # 1.70 m, four times
    s = sig
    for _ in range(4):
        s = apply_signal_effects(s, quarter, _ctx(cam))
    np.testing.assert_allclose(_read(cam, s), d, atol=2e-5)


def test_field_angle_error_follows_the_tangent_of_the_pixel_ray() -> None:
    cam = _cam(30, 20)
    sig = _signal(cam, 1.5)
    c2, c4 = 0.03, -0.02
    got = _read(cam, apply_signal_effects(sig, parse_effects({"field_angle": {"c2_m": c2, "c4_m": c4}}), _ctx(cam)))
    # independent: the angle of each pixel's ray to the optical axis, from the camera's rays
    v, u = np.mgrid[0:20, 0:30].astype(float)
    ray = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u)], axis=-1)
    t = np.tan(np.arccos(ray[..., 2] / np.linalg.norm(ray, axis=-1)))
    np.testing.assert_allclose(got, 1.5 + c2 * t ** 2 + c4 * t ** 4, atol=2e-5)


def test_offset_adds_unmodulated_electrons_and_keeps_the_phase() -> None:
    cam = _cam(12, 8)
    sig = _signal(cam, 1.2)
    dark = 5000.0
    sensor = _sensor(cam)
    base = sensor.expose(sig, noise=False)
    on = sensor.expose(apply_signal_effects(sig, parse_effects({"offset": {"dark_e": dark}}), _ctx(cam)), noise=False)
    gain = sensor.config.conversion_gain_dn_per_e
    # every tap rises by dark_e electrons (times the pixel's response, 1 +- PRNU)
    np.testing.assert_allclose((on.taps - base.taps).astype(float), dark * gain, rtol=0.05)
    np.testing.assert_allclose(depth_from_raw(on).distance_m, depth_from_raw(base).distance_m, atol=1e-4)


def test_fixed_pattern_row_and_column_delays_follow_the_clock_gradient() -> None:
    cam = _cam(30, 20)
    sig = _signal(cam, 1.5)
    row, col = 4e-12, -2.5e-12
    eff = parse_effects({"fixed_pattern": {"row_delay_s": row, "col_delay_s": col, "random_delay_s": 0.0}})
    got = _read(cam, apply_signal_effects(sig, eff, _ctx(cam)))
    v, u = np.mgrid[0:20, 0:30]
    expect = 1.5 + C * (row * (v - 9.5) + col * (u - 14.5)) / 2  # a delay tau reads c tau / 2 farther
    np.testing.assert_allclose(got, expect, atol=2e-5)


def test_fixed_pattern_random_part_is_seeded_with_the_stated_spread() -> None:
    cam = _cam(160, 120)
    sig = _signal(cam, 1.0)
    sd = 20e-12
    a = _read(cam, apply_signal_effects(sig, parse_effects({"fixed_pattern": {"random_delay_s": sd, "seed": 3}}),
                                        _ctx(cam)))
    b = _read(cam, apply_signal_effects(sig, parse_effects({"fixed_pattern": {"random_delay_s": sd, "seed": 3}}),
                                        _ctx(cam)))
    c = _read(cam, apply_signal_effects(sig, parse_effects({"fixed_pattern": {"random_delay_s": sd, "seed": 4}}),
                                        _ctx(cam)))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    assert np.std(a) == pytest.approx(C * sd / 2, rel=0.03)  # 3 mm


def test_amplitude_dependent_error_follows_its_law() -> None:
    cam = _cam(40, 4)
    p = np.geomspace(1e-14, 3e-11, 40)[None].repeat(4, 0)
    sig = _signal(cam, 1.2, p)
    err_m, a0 = 0.03, 2000.0
    got = _read(cam, apply_signal_effects(sig, parse_effects(
        {"amplitude_dependent": {"error_m": err_m, "amplitude_e": a0}}), _ctx(cam)))
    # Amplitude per tap in electrons, written out: tap share x contrast x QE T lambda/(h c) x P.
    cfg = _sensor(cam).config
    amp_e = cfg.tap_fraction * cfg.modulation_contrast * cfg.quantum_efficiency * cfg.integration_time_s \
        * cfg.wavelength_m / (6.62607015e-34 * C) * p
    np.testing.assert_allclose(got, 1.2 + err_m * np.exp(-amp_e / a0), atol=3e-5)
    assert got[0, 0] - 1.2 > 0.9 * err_m and abs(got[0, -1] - 1.2) < 1e-3  # weak pixels err most


def test_wiggling_effect_gives_the_closed_form_cyclic_error() -> None:
    cam = _cam(64, 2)
    r_amb = C / (2 * F)
    d = np.linspace(0.05, r_amb - 0.05, 64)[None].repeat(2, 0)
    a3, psi = 0.06, -1.1
    sig = apply_signal_effects(_signal(cam, d, 1e-9),
                               parse_effects({"wiggling": {"h3_amplitude": a3, "h3_phase_rad": psi}}), _ctx(cam))
    got = _read(cam, sig)
    phi = 4 * np.pi * F * d / C
    np.testing.assert_allclose(got - d, np.angle(1 + a3 * np.exp(-1j * (4 * phi + psi))) * C / (4 * np.pi * F),
                               atol=2e-5)


def test_stray_light_on_a_single_distance_moves_light_but_not_phase() -> None:
    # All pixels at one distance: mixing equal phases cannot change the distance; it only
    # moves energy. The unmodulated light is scattered too, and the total is conserved.
    cam = _cam(40, 30)
    p = np.full(cam.shape, 1e-12)
    p[10:20, 10:20] = 1e-10
    sig = _signal(cam, 0.9, p)
    sig.ambient_w = np.full(cam.shape, 2e-12)
    eff = parse_effects({"stray_light": {"weight": 0.1, "sigma_px": 1.0, "veil": 0.05}})
    out = apply_signal_effects(sig, eff, _ctx(cam))
    np.testing.assert_allclose(_read(cam, out), 0.9, atol=2e-5)
    assert out.dc_w.sum() == pytest.approx(sig.dc_w.sum(), rel=1e-3)  # only the 1-px lobe's tail leaves
    assert out.ambient_w.sum() == pytest.approx(sig.ambient_w.sum(), rel=2e-2)
    # The dark corner keeps 1 - 0.15 of its light, receives the veil's 0.05 * total / (H W), and
    # less than the 0.1 lobe weight back from its dark neighbours.
    keep_plus_veil = 0.85e-12 + 0.05 * sig.dc_w.sum() / sig.dc_w.size
    assert keep_plus_veil < out.dc_w[0, 0] < keep_plus_veil + 0.1e-12


def test_stray_light_mixes_a_bright_near_object_into_a_dark_far_one() -> None:
    # Two regions: the scattered phasor of the bright near card adds to the dark far wall's; the
    # result reads between the two, by the phasor sum written out independently.
    cam = _cam(40, 30)
    d = np.full(cam.shape, 1.0)
    p = np.full(cam.shape, 1e-12)
    d[:, :10], p[:, :10] = 0.2, 1e-10
    sig = _signal(cam, d, p)
    out = apply_signal_effects(sig, parse_effects({"stray_light": {"veil": 0.02}}), _ctx(cam))
    got = _read(cam, out)
    k = 4 * np.pi * F / C
    total = (p * np.exp(1j * k * d)).sum()
    mixed = 0.98 * 1e-12 * np.exp(1j * k * 1.0) + 0.02 * total / d.size
    assert got[15, 30] == pytest.approx(np.mod(np.angle(mixed), 2 * np.pi) / k, abs=2e-5)
    assert 0.2 < got[15, 30] < 0.9


def test_multipath_scales_the_indirect_light() -> None:
    cam = _cam(6, 4)
    k = 4 * np.pi * F / C
    direct = 1e-11 * np.exp(1j * k * 1.0) * np.ones(cam.shape)
    indirect = 3e-12 * np.exp(1j * k * 1.4) * np.ones(cam.shape)
    p_dir, p_ind = 1e-11, 5e-12  # indirect power exceeds |indirect phasor| (several paths)

    def stack(a, b):  # [F=2 (44 MHz, 0 Hz), NH=1, H, W]
        return np.stack([a[None], b[None]])

    rr = SimpleNamespace(freq_hz=np.array([F, 0.0]), harmonics=(1,),
                         phasor=stack(direct + indirect, np.full(cam.shape, p_dir + p_ind, complex)),
                         phasor_direct=stack(direct, np.full(cam.shape, p_dir, complex)),
                         phasor_indirect=stack(indirect, np.full(cam.shape, p_ind, complex)),
                         power_w=np.full(cam.shape, p_dir + p_ind), ambient_power_w=np.zeros(cam.shape),
                         camera=cam)
    mp = EFFECTS["multipath"]
    for scale in (0.0, 0.5, 1.0, 2.0):
        sig = mp.apply_render(rr, {"scale": scale})
        np.testing.assert_allclose(sig.phasor_w[0, 0], direct + scale * indirect)
        np.testing.assert_allclose(sig.dc_w, p_dir + scale * p_ind)
        assert sig.freq_hz.tolist() == [F]
    assert mp.render_requirements({"scale": 1.0}, SimpleNamespace(render=RenderSettings(bounces=0)))["bounces"] >= 2


# ----------------------------------------------------------------------------- scene stage
def _plane_scene(distance: float = 1.0):
    from tofhil.sim.scene import scene_from_dict

    return scene_from_dict({
        "camera": {"width": 24, "height": 18, "fx": 20.0, "fy": 20.0, "cx": 11.5, "cy": 8.5,
                   "pixel_pitch_m": 100e-6},
        "emitter": {"power_w": 1.0, "offset_m": [0, 0, 0], "profile": {"type": "cos_n", "n": 1.0}},
        "materials": {"white": {"reflectance": 0.8}, "grey": {"reflectance": 0.4}},
        "objects": [{"name": "wall", "type": "plane", "size": [20, 20], "material": "white",
                     "pose": {"position": [0, 0, distance]}},
                    {"name": "patch", "type": "plane", "size": [0.3, 0.3], "material": "grey",
                     "pose": {"position": [0, 0, distance - 0.001]}}],
        "sensor": {"freq_hz": [F]},
    })


def test_scene_effects_are_identity_when_off() -> None:
    scene = _plane_scene()
    for name in ORDER:
        if EFFECTS[name].stage != "scene":
            continue
        out = apply_scene_effects(scene, parse_effects({name: EFFECTS[name].off_values()}))
        assert out is scene  # an off effect does not even copy the scene


def test_pose_translation_moves_the_wall() -> None:
    from tofhil.sim.render import render

    scene = _plane_scene(1.0)
    moved = apply_scene_effects(scene, parse_effects({"pose": {"tz": 0.1}}))
    r0, r1 = render(scene), render(moved)
    # Fronto-parallel planes: the depth along the axis drops by exactly 0.1 m at every pixel.
    rz = scene.camera.ray_z
    np.testing.assert_allclose(r1.radial_m * rz, r0.radial_m * rz - 0.1, atol=1e-6)
    np.testing.assert_array_equal(scene.camera_pose, np.eye(4))  # the input scene is unchanged
    # A rotation about y by a small angle: the centre ray meets the plane at D / cos(a).
    turned = apply_scene_effects(scene, parse_effects({"pose": {"ry": 0.1}}))
    rc = render(turned).radial_m
    # The principal point sits between pixels; compare the mean of the 4 centre pixels.
    assert rc[8:10, 11:13].mean() == pytest.approx(render(scene).radial_m[8:10, 11:13].mean() / math.cos(0.1),
                                                   rel=2e-3)


def test_reflectance_scales_the_returned_power() -> None:
    from tofhil.sim.render import render

    scene = _plane_scene()
    base = render(scene)
    half = render(apply_scene_effects(scene, parse_effects({"reflectance": {"scale": 0.5}})))
    np.testing.assert_allclose(half.power_w, 0.5 * base.power_w, rtol=1e-9)
    only_patch = render(apply_scene_effects(scene, parse_effects({"reflectance": {"objects": {"patch": 0.25}}})))
    patch = base.object_id == 1
    assert patch.any() and (~patch).any()
    np.testing.assert_allclose(only_patch.power_w[patch], 0.25 * base.power_w[patch], rtol=1e-9)
    np.testing.assert_allclose(only_patch.power_w[~patch], base.power_w[~patch], rtol=1e-12)
    with pytest.raises(InputFileError) as err:
        apply_scene_effects(scene, parse_effects({"reflectance": {"materials": {"gold": 2.0}}}))
    assert err.value.field == "effects.reflectance.materials.gold"


def test_ambient_adds_irradiance_linearly() -> None:
    from tofhil.sim.render import render

    scene = _plane_scene()
    a1 = render(apply_scene_effects(scene, parse_effects({"ambient": {"irradiance_w_m2": 1.0}}))).ambient_power_w
    a3 = render(apply_scene_effects(scene, parse_effects({"ambient": {"irradiance_w_m2": 3.0}}))).ambient_power_w
    assert a1.min() > 0
    np.testing.assert_allclose(a3, 3 * a1, rtol=1e-9)


def test_lens_distortion_bends_the_pixel_rays() -> None:
    from tofhil.sim.render import render

    scene = _plane_scene(1.0)
    warped = apply_scene_effects(scene, parse_effects({"lens_distortion": {"k1": -0.3}}))
    assert warped.camera.dist[0] == -0.3 and scene.camera.dist[0] == 0.0
    res = render(warped)
    # Planes at z = 1 (wall) and 0.999 (patch): radial distance along each (distorted-model)
    # pixel ray is z / ray_z.
    z = np.where(res.object_id == 1, 0.999, 1.0)
    # k1 = -0.3 maps no ray beyond the distorted radius 2 / (3 sqrt(0.9)) (the fold of
    # r (1 + k1 r^2)): the image corners there see nothing
    cam = warped.camera
    v, u = np.mgrid[0:cam.height, 0:cam.width]
    has_ray = np.hypot((u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy) < 2 / (3 * np.sqrt(0.9))
    np.testing.assert_array_equal(np.isfinite(res.radial_m), has_ray)
    np.testing.assert_allclose(res.radial_m[has_ray], (z / warped.camera.ray_z)[has_ray], rtol=1e-6)
    assert not np.allclose(res.radial_m[has_ray], (z / scene.camera.ray_z)[has_ray], rtol=1e-3)


def test_forward_on_a_cached_render_does_not_render(monkeypatch) -> None:
    from tofhil.sim import pipeline, render as render_mod

    scene = _plane_scene()
    rr = render_mod.render(scene)

    def boom(*a, **k):
        raise AssertionError("re-rendered")

    monkeypatch.setattr(render_mod, "render", boom)
    eff = {"stray_light": {"weight": 0.05}, "range_offset": {"path_m": 0.1}, "wiggling": {},
           "fixed_pattern": {}, "amplitude_dependent": {}}
    frame = pipeline.forward(scene, rr, eff, noise=False)
    assert frame.taps.shape == (1, 4, 18, 24)


@pytest.mark.parametrize("block, field", [
    ({"straylight": {}}, "effects.straylight"),
    ({"range_offset": {"offset_m": 1}}, "effects.range_offset.offset_m"),
    ({"range_offset": {"path_m": 99}}, "effects.range_offset.path_m"),
    ({"wiggling": {"h3_amplitude": "big"}}, "effects.wiggling.h3_amplitude"),
    ({"fixed_pattern": {"seed": -1}}, "effects.fixed_pattern.seed"),
    ({"multipath": {"bounces": 0}}, "effects.multipath.bounces"),
    ({"stray_light": {"weight": 0.5, "veil": 0.4, "ghost_weight": 0.2}}, "effects.stray_light"),
    ({"pose": {"enabled": "no"}}, "effects.pose.enabled"),
])
def test_bad_effects_blocks_name_the_field(block: dict, field: str) -> None:
    with pytest.raises(InputFileError) as err:
        parse_effects(block, source="s.yaml")
    assert err.value.field == field and err.value.file == "s.yaml"


def test_enabled_false_switches_an_effect_off_and_defaults_fill_in() -> None:
    eff = parse_effects({"wiggling": {"enabled": False}, "stray_light": None, "range_offset": {}})
    assert "wiggling" not in eff
    assert eff["stray_light"]["weight"] == EFFECTS["stray_light"].params["weight"].default
    assert list(eff) == ["stray_light", "range_offset"]  # forward-model order


def test_docs_table_of_effects_is_the_registry() -> None:
    """docs/effects.md's table is generated from the registry (tools/effects_table.py)."""
    from pathlib import Path

    from tofhil.sim.effects import effects_table_markdown

    text = (Path(__file__).resolve().parents[2] / "docs" / "effects.md").read_text()
    begin = text.index("\n", text.index("<!-- effects-table:")) + 1
    table = text[begin:text.index("<!-- end effects-table -->")]
    assert table == effects_table_markdown(), "run: python tools/effects_table.py"
    for name in ORDER:
        assert f"| `{name}` |" in table
