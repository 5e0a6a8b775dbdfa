"""Scene files: validation errors name file, field and expectation; parameters; round trips."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from tofhil.errors import InputFileError
from tofhil.sim.scene import load_scene, scene_from_dict, scene_from_yaml, scene_to_yaml


def base() -> dict:
    return {
        "camera": {"preset": "holmlund_thesis", "pose": {"position": [0, 0, 0]}},
        "emitter": {"power_w": 1.0},
        "materials": {"white": {"reflectance": 0.8}},
        "objects": [{"name": "wall", "type": "plane", "size": [2, 2], "material": "white",
                     "pose": {"position": [0, 0, 1]}}],
    }


@pytest.mark.parametrize("mutate, field, expected", [
    (lambda d: d["materials"]["white"].update(reflectance=1.5), "materials.white.reflectance", "[0, 1]"),
    (lambda d: d["objects"][0].update(material="black"), "objects[0].material", "white"),
    (lambda d: d["objects"][0].update(type="torus"), "objects[0].type", "plane"),
    (lambda d: d["objects"][0].update(size=[2]), "objects[0].size", "2 numbers"),
    (lambda d: d["emitter"].pop("power_w"), "emitter.power_w", "optical power"),
    (lambda d: d["emitter"].update(profile={"type": "gauss"}), "emitter.profile.type", "cos_n"),
    (lambda d: d["camera"].update(f_number=-1), "camera.f_number", "> 0"),
    (lambda d: d.update(sensor=[1, 2]), "sensor", "mapping"),
    (lambda d: d.update(colour="red"), "colour", "one of"),
    (lambda d: d["objects"][0].update(file="x.obj"), "objects[0].file", "one of"),
    (lambda d: d["objects"].append({"type": "mesh", "file": "missing.obj", "material": "white"}),
     "objects[1].file", "existing file"),
])
def test_errors_name_file_field_and_expectation(mutate, field, expected) -> None:
    d = base()
    mutate(d)
    with pytest.raises(InputFileError) as exc:
        scene_from_dict(d, source="bench.yaml")
    msg = str(exc.value)
    assert "bench.yaml" in msg and f"'{field}'" in msg and expected in msg


def test_params_substitution_and_overrides(tmp_path) -> None:
    d = base()
    d["params"] = {"rho": 0.5, "scale": 0.1}
    d["materials"]["dark"] = {"reflectance": "${rho * scale}"}
    path = tmp_path / "s.yaml"
    path.write_text(yaml.safe_dump(d))
    s = load_scene(path)
    assert s.materials["dark"].reflectance == pytest.approx(0.05)
    s2 = load_scene(path, overrides={"params": {"scale": 0.02}})
    assert s2.materials["dark"].reflectance == pytest.approx(0.01)
    with pytest.raises(InputFileError, match="materials.dark.reflectance"):
        d["materials"]["dark"]["reflectance"] = "${nope}"
        scene_from_dict(d)


def test_round_trip_through_yaml(tmp_path) -> None:
    d = base()
    d["camera"]["pose"] = {"position": [0.1, 0.2, -0.3], "rotation_deg": [5, -10, 20]}
    d["camera"]["f_number"] = 1.4
    d["camera"]["focus_distance_m"] = 1.0
    d["emitter"].update(offset_m=[0.02, 0, 0], waveform={"harmonics": [[1, 1.0, 0.0], [3, 0.1, 0.5]]},
                        profile={"type": "table", "theta_deg": [0, 30, 60], "relative_intensity": [1, 0.8, 0.1]})
    d["materials"]["chk"] = {"reflectance": 0.5, "glossy": {"reflectance": 0.2, "exponent": 30},
                             "texture": {"type": "checker", "size_m": 0.05, "reflectance": [0.7, 0.1]}}
    d["objects"].append({"name": "ball", "type": "sphere", "radius": 0.1, "material": "chk",
                         "pose": {"position": [0, 0, 0.8]}})
    d["sensor"] = {"freq_hz": [44e6], "taps": 4}
    d["effects"] = {"stray_light": {"weight": 0.01}}
    s = scene_from_dict(d)
    path = tmp_path / "rt.yaml"
    path.write_text(scene_to_yaml(s))
    s2 = load_scene(path)
    assert s2.camera == s.camera
    np.testing.assert_allclose(s2.camera_pose, s.camera_pose, atol=1e-12)
    assert s2.f_number == 1.4 and s2.focus_distance_m == 1.0
    assert s2.emitter.harmonics == s.emitter.harmonics
    assert s2.emitter.profile == s.emitter.profile
    assert s2.materials["chk"] == s.materials["chk"]
    assert [o.name for o in s2.objects] == ["wall", "ball"]
    np.testing.assert_allclose(s2.objects[1].pose, s.objects[1].pose)
    assert s2.sensor == s.sensor and s2.effects == s.effects


def test_pose_conventions() -> None:
    d = base()
    d["camera"]["pose"] = {"position": [1, 0, 0], "look_at": [1, 0, 5]}
    s = scene_from_dict(d)
    np.testing.assert_allclose(s.camera_pose[:3, :3], np.eye(3), atol=1e-12)
    d["camera"]["pose"] = {"rotation_deg": [0, 90, 0]}
    s = scene_from_dict(d)
    # Rotating 90 deg about y turns the optical axis (z) onto world +x.
    np.testing.assert_allclose(s.camera_pose[:3, 2], [1, 0, 0], atol=1e-12)


@pytest.mark.parametrize("up", [[0, 0, 1], [0, 0, -2], [0, 0, 0]])
def test_look_at_along_up_is_a_field_error(up: list[float]) -> None:
    """An ``up`` along the viewing direction (or zero) leaves no "down" to orient the camera by:
    the pose's field is named, not a bare ValueError (hypothesis found it)."""
    d = base()
    d["camera"]["pose"] = {"position": [0, 0, 0], "look_at": [0, 0, 5], "up": up}
    with pytest.raises(InputFileError, match="camera.pose.look_at"):
        scene_from_dict(d)


def test_beam_profile_normalisation_conserves_power() -> None:
    d = base()
    for prof in ({"type": "cos_n", "n": 3.0},
                 {"type": "table", "theta_deg": [0, 20, 50, 90], "relative_intensity": [1.0, 0.9, 0.3, 0.0]}):
        d["emitter"] = {"power_w": 2.0, "profile": prof}
        em = scene_from_dict(d).emitter
        # Integrate I over the sphere independently (midpoint rule in theta).
        th = (np.arange(20000) + 0.5) * (np.pi / 20000)
        total = np.sum(em.intensity_w_sr(np.cos(th)) * 2 * np.pi * np.sin(th)) * (np.pi / 20000)
        assert total == pytest.approx(2.0, rel=1e-6)


def test_yaml_errors_name_the_source() -> None:
    with pytest.raises(InputFileError, match="x.yaml"):
        scene_from_yaml("camera: [", source="x.yaml")
    with pytest.raises(InputFileError, match="no such bundled scene"):
        load_scene("no_such_scene_name")


# --------------------------------------------------------------------------- bundled scenes
from tofhil.sim.render import render  # noqa: E402
from tofhil.sim.scene import bundled_scenes  # noqa: E402

THESIS_SCENES = ["wall", "dark_square", "two_squares", "wall_card", "dark_square_card",
                 "two_squares_card", "corner", "bench_demo"]


def test_all_thesis_scenes_are_bundled() -> None:
    assert set(THESIS_SCENES) <= set(bundled_scenes())


@pytest.mark.parametrize("name", THESIS_SCENES)
def test_bundled_scene_round_trips_and_renders(name: str, tmp_path) -> None:
    scene = load_scene(name)
    assert scene.camera.name == "holmlund_thesis" and scene.camera.shape == (120, 160)
    assert scene.sensor.freq_hz == (44.0e6,) and scene.sensor.taps == 4
    path = tmp_path / f"{name}.yaml"
    path.write_text(scene_to_yaml(scene))
    again = load_scene(path)
    cam = scene.camera.scaled(0.25)
    a = render(scene, camera=cam, samples_per_pixel=1, bounces=0)
    b = render(again, camera=cam, samples_per_pixel=1, bounces=0)
    np.testing.assert_array_equal(a.phasor, b.phasor)
    assert np.all(np.isfinite(a.radial_m)) and np.all(a.object_id >= 0)   # the view is filled


def test_dark_square_reflectivity_parameter_scales_the_square_only() -> None:
    cam = load_scene("dark_square").camera.scaled(0.5)
    bare = render(load_scene("wall"), camera=cam)
    for rel in (0.5, 0.05, 0.01):
        scene = load_scene("dark_square", overrides={"params": {"square_reflectance": rel}})
        res = render(scene, camera=cam)
        square = res.object_id == scene.object_index("square")
        assert scene.materials["square"].reflectance == pytest.approx(0.8 * rel)
        # 0.2 m at 1 m with fx = 58 px: about 11.7 px across.
        assert 100 <= square.sum() <= 144 and square[30, 40]
        # Against the bare wall, pixel by pixel: the square's power is the relative reflectivity,
        # up to being 1 mm nearer (< 0.5 % here); the wall around it is unchanged.
        np.testing.assert_allclose(res.power_w[square] / bare.power_w[square], rel, rtol=0.005)
        np.testing.assert_allclose(res.power_w[~square], bare.power_w[~square], rtol=1e-12)


def test_card_scenes_put_a_near_card_over_part_of_the_view() -> None:
    for name in ("wall_card", "dark_square_card", "two_squares_card", "bench_demo"):
        scene = load_scene(name)
        cam = scene.camera.scaled(0.5)
        res = render(scene, camera=cam)
        card = res.object_id == scene.object_index("card")
        assert 0.15 < card.mean() < 0.5                     # part of the view, not all of it
        assert not card[30, 40] and card[:, 60:].any()      # off-centre, on the right
        np.testing.assert_allclose(cam.radial_to_z(res.radial_m)[card], 0.17, rtol=1e-9)


def test_corner_scene_shows_three_walls_meeting_at_the_centre() -> None:
    scene = load_scene("corner")
    res = render(scene, camera=scene.camera.scaled(0.25))
    assert set(np.unique(res.object_id)) == {0, 1, 2}
    assert res.radial_m[15, 20] == pytest.approx(1.2, abs=0.05)   # the vertex along the axis


def test_rendered_scenes_can_be_copied_and_pickled() -> None:
    import copy
    import pickle

    scene = load_scene("wall")
    cam = scene.camera.scaled(0.1)
    first = render(scene, camera=cam)                     # caches the Embree scene
    for other in (copy.deepcopy(scene), pickle.loads(pickle.dumps(scene))):
        np.testing.assert_array_equal(render(other, camera=cam).phasor, first.phasor)


def test_scene_parts_are_typed_and_replace_validates_mappings() -> None:
    import dataclasses

    from tofhil.sim.scene import EffectSet, RenderSettings
    from tofhil.sim.sensor import SensorConfig

    s = scene_from_dict(base() | {"effects": {"stray_light": {"weight": 0.01}}, "render": {"bounces": 1}},
                        source="bench.yaml")
    assert isinstance(s.sensor, SensorConfig) and isinstance(s.effects, EffectSet)
    assert isinstance(s.render, RenderSettings) and s.render.bounces == 1
    assert s.effects["stray_light"]["weight"] == 0.01 and "sigma_px" in s.effects["stray_light"]  # defaults filled
    s2 = dataclasses.replace(s, sensor={"freq_hz": [20e6]}, effects={}, render={"samples_per_pixel": 2})
    assert s2.sensor.freq_hz == (20e6,) and s2.sensor.wavelength_m == 850e-9   # preset facts fill the rest
    assert s2.effects == {} and s2.render.samples_per_pixel == 2
    same = dataclasses.replace(s, camera=s.camera.scaled(0.5))
    assert same.sensor is s.sensor and same.effects is s.effects          # typed parts are not parsed again
    with pytest.raises(InputFileError) as e:
        dataclasses.replace(s, sensor={"freq_hz": [20e6], "bogus": 1})
    assert e.value.file == "bench.yaml" and e.value.field == "sensor.bogus"
