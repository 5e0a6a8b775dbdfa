"""End to end: scene -> render -> effects -> sensor -> frames / session / CLI, and the stray-light
thesis's bench observations reproduced on the bundled scenes."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
import yaml

from tofhil.depth import depth_from_raw
from tofhil.errors import InputFileError
from tofhil.session import open_session
from tofhil.sim.pipeline import forward, prepare_render, simulate, simulate_session
from tofhil.sim.scene import load_scene, scene_from_dict, scene_from_yaml

F = 44.0e6
#: A plausible lens PSF for the thesis camera: a broad lobe plus a uniform veil.
STRAY = {"stray_light": {"weight": 0.02, "sigma_px": 40.0, "veil": 0.01}}
#: The bundled scenes' sensor without its fixed-pattern offsets, so that noise-free readings
#: without stray light are exact and every change is the stray light's.
NO_FPN = {"sensor": {"fixed_pattern": {"dsnu_e": 0.0, "prnu": 0.0, "seed": 0}}}


def plane(distance: float = 1.2, **sensor) -> dict:
    return {
        "camera": {"width": 32, "height": 24, "fx": 26.0, "fy": 26.0, "cx": 15.5, "cy": 11.5,
                   "pixel_pitch_m": 80e-6},
        "emitter": {"power_w": 0.5, "offset_m": [0, 0, 0], "profile": {"type": "cos_n", "n": 1.0}},
        "materials": {"white": {"reflectance": 0.8}},
        "objects": [{"name": "wall", "type": "plane", "size": [20, 20], "material": "white",
                     "pose": {"position": [0, 0, distance]}}],
        "sensor": {"freq_hz": [F], "integration_time_s": 3e-4, "read_noise_e": 10.0,
                   "full_well_e": 2e5, "adc_bits": 16, **sensor},
    }


def test_noise_free_simulation_of_a_plane_is_exact() -> None:
    scene = scene_from_dict(plane(1.2))
    frame = simulate(scene, frames=1, noise=False)[0]
    _, rr = prepare_render(scene)
    d = depth_from_raw(frame).distance_m
    v, u = np.mgrid[0:24, 0:32]
    truth = 1.2 * np.sqrt(1 + ((u - 15.5) / 26.0) ** 2 + ((v - 11.5) / 26.0) ** 2)  # radial to a plane
    np.testing.assert_allclose(d, truth, atol=1e-4)
    np.testing.assert_allclose(rr.radial_m, truth, atol=1e-9)
    assert frame.taps.max() < 2e5 * frame.meta["conversion_gain_dn_per_e"]  # not saturated


def test_same_seed_identical_frames_and_independent_noise_per_frame() -> None:
    scene = scene_from_dict(plane())
    a = simulate(scene, frames=3, seed=11)
    b = simulate(scene, frames=3, seed=11)
    for fa, fb in zip(a, b):
        np.testing.assert_array_equal(fa.taps, fb.taps)
    assert not np.array_equal(a[0].taps, a[1].taps)
    assert not np.array_equal(a[0].taps, simulate(scene, frames=1, seed=12)[0].taps)
    # Frames are independent draws around one expectation: the frame-to-frame difference has
    # twice the single-frame noise variance, and no mean.
    exact = simulate(scene, frames=1, noise=False)[0].taps.astype(float)
    many = np.stack([f.taps for f in simulate(scene, frames=6, seed=1)]).astype(float)
    diff = many[1:] - many[:-1]
    assert abs(diff.mean()) < 0.05 * diff.std()
    assert diff.var() == pytest.approx(2 * (many - exact).var(), rel=0.1)
    assert [f.sequence for f in a] == [0, 1, 2]
    period = scene.sensor.frame_period_s
    assert [f.timestamp_s for f in a] == pytest.approx([0.0, period, 2 * period])


def test_session_has_the_capture_layout_with_scene_text(tmp_path) -> None:
    scene = load_scene("wall", NO_FPN)
    out = tmp_path / "sim.h5"
    simulate_session(scene, out, frames=2, seed=5)
    frames = simulate(scene, frames=2, seed=5)
    with open_session(out) as s:
        assert s.n_frames == 2 and s.has_raw and s.has_depth
        assert s.device["model"] == "tofhil-sim" and s.device["seed"] == 5
        assert s.scene_text == scene.text
        assert s.camera == scene.camera
        np.testing.assert_allclose(s.freq_hz, [F])
        for i in range(2):
            np.testing.assert_array_equal(s.raw_frame(i).taps, frames[i].taps)
            np.testing.assert_allclose(s.depth_frame(i).distance_m, depth_from_raw(frames[i]).distance_m,
                                       atol=1e-6)
        # The embedded text reproduces the scene.
        again = scene_from_yaml(s.scene_text, source="embedded")
        assert again.camera == scene.camera and len(again.objects) == len(scene.objects)
    with pytest.raises(InputFileError):
        simulate_session(scene, out, frames=1)  # never overwrite without force
    simulate_session(scene, out, frames=1, force=True)
    with open_session(out) as s:
        assert s.n_frames == 1


def test_session_with_given_effects_embeds_those_effects(tmp_path) -> None:
    scene = load_scene("wall")
    out = simulate_session(scene, tmp_path / "e.h5", frames=1, noise=False, effects=STRAY)
    with open_session(out) as s:
        block = yaml.safe_load(s.scene_text)["effects"]
        assert block["stray_light"]["weight"] == 0.02 and block["stray_light"]["veil"] == 0.01
        assert s.device["effects"]["stray_light"]["sigma_px"] == 40.0


def _run_cli(*args: str, cwd) -> subprocess.CompletedProcess:
    env = dict(os.environ, COLUMNS="200")
    return subprocess.run([sys.executable, "-c", "from tofhil.cli import main; main()", *args], cwd=cwd,
                          capture_output=True,
                          text=True, env=env, timeout=120)


def test_cli_simulate_writes_a_session(tmp_path) -> None:
    r = _run_cli("simulate", "dark_square", "--out", "s.h5", "--frames", "2", "--seed", "3", "--no-noise",
                 "--param", "square_reflectance=0.1", "--effect", "stray_light.weight=0.03", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    with open_session(tmp_path / "s.h5") as s:
        assert s.n_frames == 2 and s.device["noise"] is False
        assert s.device["effects"]["stray_light"]["weight"] == 0.03
        # Parameters are resolved in the embedded text: the square is 0.1 of the wall's 0.8.
        assert yaml.safe_load(s.scene_text)["materials"]["square"]["reflectance"] == pytest.approx(0.08)
        np.testing.assert_array_equal(s.raw_frame(0).taps, s.raw_frame(1).taps)  # noise-free


@pytest.mark.parametrize("args, message", [
    (["--effect", "stray_light.wieght=0.1"], "effects.stray_light.wieght"),
    (["--param", "square_reflectance"], "NAME=VALUE"),
])
def test_cli_simulate_user_errors_exit_2_without_traceback(tmp_path, capsys, args, message) -> None:
    from tofhil.cli import main

    with pytest.raises(SystemExit) as ex:
        main(["simulate", "dark_square", "--out", str(tmp_path / "t.h5"), *args])
    assert ex.value.code == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err
    assert not (tmp_path / "t.h5").exists()
    (tmp_path / "t.h5").write_bytes(b"recorded data")
    with pytest.raises(SystemExit) as ex:
        main(["simulate", "wall", "--out", str(tmp_path / "t.h5")])
    assert ex.value.code == 2 and "already exists" in capsys.readouterr().err
    assert (tmp_path / "t.h5").read_bytes() == b"recorded data"  # never overwritten
    with pytest.raises(SystemExit) as ex:
        main(["simulate", str(tmp_path / "no_such_scene.yaml"), "--out", str(tmp_path / "u.h5")])
    assert ex.value.code == 2 and "no_such_scene.yaml" in capsys.readouterr().err


def test_multipath_effect_on_the_corner_reads_farther_and_off_is_direct_only() -> None:
    scene = load_scene("corner", NO_FPN)
    cam = scene.camera.scaled(0.25)  # 40 x 30 keeps the path tracing quick
    _, rr = prepare_render(scene, {"multipath": {"scale": 1.0, "bounces": 2}},
                           render_kwargs={"camera": cam, "samples_per_pixel": 4})
    truth = rr.radial_m
    direct = depth_from_raw(forward(scene, rr, {"multipath": {"scale": 0.0}}, noise=False)).distance_m
    full = depth_from_raw(forward(scene, rr, {"multipath": {"scale": 1.0}}, noise=False)).distance_m
    double = depth_from_raw(forward(scene, rr, {"multipath": {"scale": 2.0}}, noise=False)).distance_m
    ok = np.isfinite(truth)
    # Direct only: the mixed-pixel edges aside, the reading is the first-hit distance.
    assert np.median(np.abs(direct - truth)[ok]) < 2e-3
    # Indirect light has travelled farther: it biases every reading away from the camera.
    assert np.median((full - direct)[ok]) > 0.01
    assert np.median((double - full)[ok]) > 0


# ------------------------------------------------------------------ the thesis's observations
def _region_readings(name: str, reflectance: float, effects: dict) -> tuple[dict, np.ndarray, object]:
    """Noise-free readings of a bundled scene: per-object median error against the truth."""
    scene = load_scene(name, {"params": {"square_reflectance": reflectance}, **NO_FPN})
    _, rr = prepare_render(scene, {})
    d = depth_from_raw(forward(scene, rr, effects, noise=False)).distance_m
    err = {o.name: float(np.median((d - rr.radial_m)[rr.object_id == i])) for i, o in enumerate(scene.objects)}
    return err, d, rr


def test_dark_square_reads_nearer_with_the_card_the_darker_it_is() -> None:
    """Holmlund: with stray light the dark square reads nearer than the wall's 1 m, more so the
    darker the square (squares from 50 % down to 1 % of the wall's reflectivity)."""
    errors = []
    for q in (0.5, 0.2, 0.05, 0.01):
        off, *_ = _region_readings("dark_square_card", q, {})
        assert abs(off["square"]) < 1e-3  # control: without stray light the reading is exact
        on, *_ = _region_readings("dark_square_card", q, STRAY)
        errors.append(on["square"])
    assert all(e < -0.02 for e in errors)  # nearer than the truth (~1.0 m) at every reflectivity
    assert all(b < a for a, b in zip(errors, errors[1:]))  # strictly more so as it darkens


def test_card_near_the_lens_pulls_the_whole_wall_nearer_the_dark_square_most() -> None:
    q = 0.05
    base, d0, r0 = _region_readings("dark_square", q, STRAY)
    card, d1, r1 = _region_readings("dark_square_card", q, STRAY)
    # Control: without stray light the card changes nothing where the wall stays visible and
    # lit (the card, beside the emitter, also shadows part of the wall).
    _, e0, _ = _region_readings("dark_square", q, {})
    _, e1, _ = _region_readings("dark_square_card", q, {})
    oid0, oid1 = r0.object_id, r1.object_id
    lit = np.isclose(r1.power_w, r0.power_w, rtol=1e-9, atol=0) & (r0.power_w > 0)
    both = (oid0 == 0) & (oid1 == 0) & lit
    assert both.mean() > 0.5
    np.testing.assert_allclose(e1[both], e0[both], atol=1e-5)
    # With stray light, every visible part of the wall (8 x 8 blocks of the image) reads nearer.
    pull = d1 - d0
    h, w = pull.shape
    blocks = []
    for by in range(8):
        for bx in range(8):
            sl = (slice(by * h // 8, (by + 1) * h // 8), slice(bx * w // 8, (bx + 1) * w // 8))
            m = both[sl]
            if m.sum() > 20:
                blocks.append(float(np.median(pull[sl][m])))
    assert len(blocks) > 30 and max(blocks) < 0
    square = (oid0 == 1) & (oid1 == 1) & lit
    square_pull = float(np.median(pull[square]))
    assert square_pull < min(blocks)  # the dark square most
    assert card["square"] < card["wall"] < base["wall"]


def test_cli_effects_lists_the_vocabulary_with_off_values_and_bounds() -> None:
    import json

    from typer.testing import CliRunner

    import tofhil.cli.simulate  # noqa: F401  (registers the commands)
    from tofhil.cli import app
    from tofhil.sim.effects import EFFECTS

    r = CliRunner().invoke(app, ["effects", "--json"])
    assert r.exit_code == 0, r.output
    listed = {e["name"]: e for e in json.loads(r.output)}
    assert set(listed) == set(EFFECTS)
    sl = listed["stray_light"]["params"]["weight"]
    assert sl["off"] == 0.0 and sl["lo"] == 0.0 and sl["hi"] > 0 and listed["stray_light"]["stage"] == "signal"


def test_scene_file_effects_block_with_a_measured_psf_next_to_the_scene(tmp_path) -> None:
    # A measured PSF named relative to the scene file gives the same frames as the parametric
    # PSF it was measured from.
    from tofhil.sim.straylight import StrayLightPSF, apply_stray_light

    lobe = {"weight": 0.05, "sigma_px": 3.0}
    point = np.zeros((31, 31))
    point[15, 15] = 1.0
    np.save(tmp_path / "lens_psf.npy", apply_stray_light(point, StrayLightPSF.from_params(lobe)))
    d = plane(1.0)
    d["objects"].append({"name": "card", "type": "plane", "size": [0.1, 0.1], "material": "white",
                         "pose": {"position": [0.05, 0, 0.3]}})
    d["effects"] = {"stray_light": {"psf_file": "lens_psf.npy"}}
    (tmp_path / "scene.yaml").write_text(yaml.safe_dump(d))
    scene = load_scene(tmp_path / "scene.yaml")
    measured = simulate(scene, noise=False)[0].taps
    parametric = simulate(scene, noise=False, effects={"stray_light": lobe})[0].taps
    none = simulate(scene, noise=False, effects={})[0].taps
    np.testing.assert_allclose(measured, parametric, rtol=1e-5, atol=1e-3)
    assert np.abs(measured - none).max() > 1.0  # the stray light did something


def test_two_frequency_simulation_unwraps_beyond_both_ambiguity_ranges() -> None:
    # 80 and 100 MHz wrap at 1.87 m and 1.50 m; together they are unambiguous to 7.5 m.
    scene = scene_from_dict(plane(2.6, freq_hz=[80e6, 100e6]))
    frame = simulate(scene, frames=1, noise=False)[0]
    assert frame.taps.shape[:2] == (2, 4)
    v, u = np.mgrid[0:24, 0:32]
    truth = 2.6 * np.sqrt(1 + ((u - 15.5) / 26.0) ** 2 + ((v - 11.5) / 26.0) ** 2)
    np.testing.assert_allclose(depth_from_raw(frame).distance_m, truth, atol=2e-4)
