"""``tofhil correct --method twin`` and ``compare --correct`` before and after, on an 80 x 60
dark square with a card that clips and stray light the base twin lacks (in-process CLI)."""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import pytest

from tests.cli_in_process import run_cli
from tofhil.eval.corrections.context import FLAG_STRAY_LIGHT

PSF = {"weight": 0.03, "sigma_px": 6.0, "veil": 0.005}
CAMERA = {"width": 80, "height": 60, "fx": 58.333, "fy": 58.333, "cx": 39.5, "cy": 29.5, "pixel_pitch_m": 48.0e-6}


def _session(path: Path, twin, frames: int, noise: bool, scene_text: str, recorded: bool) -> None:
    from tofhil.session import SessionWriter

    with SessionWriter(path, twin.scene.camera, device={"model": "tofhil-sim"}, scene_text=scene_text,
                       sensor_config=twin.config.to_dict() if recorded else None) as w:
        for f in twin.frames(frames=frames, seed=3, noise=noise):
            w.append(f)


@pytest.fixture(scope="module")
def bench(tmp_path_factory) -> Path:
    from tofhil.sim.scene import load_scene, scene_to_yaml
    from tofhil.sim.straylight import StrayLightPSF
    from tofhil.sim.twin import Twin

    d = tmp_path_factory.mktemp("twincorr")
    over = {"camera": CAMERA, "params": {"square_reflectance": 0.02}, "sensor": {"integration_time_s": 0.6e-3}}
    truth = load_scene("dark_square_card", {**over, "effects": {"stray_light": PSF}})
    base = load_scene("dark_square_card", over)
    (d / "extended.yaml").write_text(scene_to_yaml(truth), encoding="utf-8")
    StrayLightPSF.from_params(PSF).save(d / "psf.json")
    # a device capture: no recorded sensor configuration (the twin fits the signal scale)
    _session(d / "capture.h5", Twin(truth), 3, True, scene_to_yaml(base), recorded=False)
    _session(d / "twin.h5", Twin(base), 1, False, scene_to_yaml(base), recorded=True)
    return d


def test_correct_twin_writes_flags_and_notes(bench, tmp_path, capsys) -> None:
    out = tmp_path / "c.h5"
    assert run_cli("correct", bench / "capture.h5", "--method", f"twin:scene={bench / 'extended.yaml'}",
                   "--out", out) == 0
    text = capsys.readouterr().out
    assert "clipped source pixels is the twin's prediction" in text
    with h5py.File(out, "r") as f:
        doc = json.loads(f.attrs["correction"])
        flags = f["correction/flags"][()]
    assert doc["saturated_source_pixels"] > 20  # the card clips: the case this is about
    assert doc["twin"]["effects_removed"] == ["stray_light"]
    assert abs(doc["twin"]["signal_scale"] - 1.0) < 0.02  # the capture's units are the twin's
    assert (flags & FLAG_STRAY_LIGHT).mean() > 0.5


def test_compare_before_after_marks_what_got_worse(bench, tmp_path) -> None:
    out = tmp_path / "cmp"
    twin = f"twin:scene={bench / 'extended.yaml'}"
    psf = f"psf:psf={bench / 'psf.json'}"
    restored = f"{psf},twin={bench / 'extended.yaml'}"
    assert run_cli("compare", bench / "capture.h5", bench / "twin.h5", "--out", out, "--frames", 3,
                   "--correct", twin, "--correct", psf, "--correct", restored) == 0
    m = json.loads((out / "metrics.json").read_text())
    before = m["variants"]["measured"]["regions"]["square"]["depth_residual_m"]["median"]
    assert before < -0.05  # the card's stray light pulls the square near
    for spec in (twin, restored):
        ch = m["variants"][spec]["before_after"]["square"]
        # the square brought to the base twin within 3 x the noise of its median
        assert abs(ch["median_after_m"]) < 3 * ch["median_noise_m"] + 1e-3, ch
        assert not ch["worse"]
        assert not m["variants"][spec]["before_after"]["wall"]["worse"]
    assert m["variants"][restored]["correction"]["flagged_pixels"]["restored_from_twin"] > 20
    # the PSF alone cannot know the card's light: wherever it makes a region worse, it says why
    for region, ch in m["variants"][psf]["before_after"].items():
        if ch["worse"]:
            assert "saturated" in (ch["reason"] or ""), (region, ch)
    assert m["variants"][psf]["correction"]["flagged_pixels"]["untrusted"] > 0
    assert "near clipped (15 px)" in m["variants"][psf]["before_after"]
    page = (out / "report.html").read_text()
    assert "Before and after each correction" in page
    # scored like the diagnosis: the scale fitted on the even frames, the figures on the odd one
    assert m["heldout"]["fit_frames"] == [0, 2] and m["heldout"]["scored_frames"] == [1]
    assert m["frames"]["a"] == 1 and not m["heldout"]["in_sample"]
    fit = m["variants"][twin]["correction"]["twin"]["signal_scale_fit"]
    assert fit["fitted"] and fit["fitted_on"].startswith("frames 0, 2") and abs(fit["factor"] - 1) < 0.02
    assert "Scored on held-out frames" in page and "fitted on frames 0, 2" in page
    # one scored frame still has a noise floor: the fit frames' scatter joins the estimate
    assert m["variants"][twin]["before_after"]["square"]["median_noise_m"] > 0


def test_compare_of_one_frame_says_its_score_is_in_sample(bench, tmp_path) -> None:
    out = tmp_path / "cmp1"
    twin = f"twin:scene={bench / 'extended.yaml'}"
    assert run_cli("compare", bench / "capture.h5", bench / "twin.h5", "--out", out, "--frames", 1,
                   "--correct", twin) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["heldout"]["in_sample"] and m["heldout"]["scored_frames"] == [0]
    assert "in-sample" in m["variants"][twin]["correction"]["twin"]["signal_scale_fit"]["fitted_on"]
    assert "Scored in-sample" in (out / "report.html").read_text()
    # a depth-domain method fits nothing: every frame is scored, no split
    out2 = tmp_path / "cmp2"
    assert run_cli("compare", bench / "capture.h5", bench / "twin.h5", "--out", out2, "--frames", 3,
                   "--correct", "smooth-median:size=3") == 0
    m2 = json.loads((out2 / "metrics.json").read_text())
    assert m2["heldout"] is None and m2["frames"]["a"] == 3


def test_bad_twin_specs_are_one_line_and_write_nothing(bench, tmp_path, capsys) -> None:
    out = tmp_path / "c.h5"
    for spec, words in ((f"twin:scene={tmp_path / 'missing.yaml'}", ("missing.yaml", "scene")),
                        (f"twin:scene={bench / 'extended.yaml'},remove=most", ("twin:remove", "light")),
                        (f"psf:psf={bench / 'psf.json'},twin={tmp_path / 'gone.yaml'}", ("gone.yaml",))):
        assert run_cli("correct", bench / "capture.h5", "--method", spec, "--out", out) == 2
        err = capsys.readouterr().err
        assert "Traceback" not in err and all(w in err for w in words), err
        assert not out.exists()
