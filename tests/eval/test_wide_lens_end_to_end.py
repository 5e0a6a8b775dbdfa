"""A fisheye and a rational camera through simulate, compare and diagnose (the CLI, end to end):
the twin renders through the lens model, the session carries it, and diagnosis finds a hidden
wiggling through it as it does through a pinhole."""

from __future__ import annotations

import json

import pytest
import yaml

from tofhil.session import open_session

#: wall_fisheye at half the resolution (80 x 60, the same 132 x 100 degree field)
FISHEYE = {"width": 80, "height": 60, "fx": 34.5, "fy": 34.5, "cx": 39.5, "cy": 29.5}
#: the Azure Kinect's factory rational lens on 80 x 72 pixels (its NFOV field, 73 x 66 degrees)
RATIONAL = {"width": 80, "height": 72, "fx": 63.08, "fy": 63.09, "cx": 41.6, "cy": 43.6, "pixel_pitch_m": 28e-6,
            "model": "rational", "dist": [0.5479397773742676, -0.020971370860934258, 2.0557534298859537e-05,
                                          -7.210415787994862e-05, -0.002652231603860855, 0.8896790742874146,
                                          0.08613020926713943, -0.013910384848713875]}


def scene_file(tmp_path, camera: dict) -> str:
    """wall_fisheye with another camera block (lens model kept unless the block gives one)."""
    from tofhil.sim.scene import scenes_dir

    d = yaml.safe_load((scenes_dir() / "wall_fisheye.yaml").read_text())
    d["camera"].update(camera)
    path = tmp_path / "scene.yaml"
    path.write_text(yaml.safe_dump(d))
    return str(path)


@pytest.mark.slow
@pytest.mark.parametrize("camera,model", [(FISHEYE, "fisheye"), (RATIONAL, "rational")], ids=["fisheye", "rational"])
def test_wide_lens_simulate_compare_diagnose(tmp_path, tofhil_cli, camera, model):
    scene = scene_file(tmp_path, camera)
    meas, twin = tmp_path / "meas.h5", tmp_path / "twin.h5"
    r = tofhil_cli("simulate", scene, "--out", meas, "--frames", "3", "--effect", "wiggling.h3_amplitude=0.03")
    assert r.returncode == 0, r.stderr
    r = tofhil_cli("simulate", scene, "--out", twin, "--frames", "1", "--seed", "7")
    assert r.returncode == 0, r.stderr
    with open_session(meas) as s:
        assert s.camera.distortion_model == model and s.camera.shape == (camera["height"], camera["width"])
    r = tofhil_cli("compare", meas, twin, "--out", tmp_path / "cmp")
    assert r.returncode == 0, r.stderr
    text = (tmp_path / "cmp" / "metrics.json").read_text()
    assert '"same_intrinsics": true' in text          # the same lens model on both sides
    assert json.loads(text)["acquisition"]
    r = tofhil_cli("diagnose", meas, "--scene", scene, "--out", tmp_path / "diag")
    assert r.returncode == 0, r.stderr
    d = json.loads((tmp_path / "diag" / "diagnosis.json").read_text())
    assert "wiggling" in d["causes"] and d["verdict"]["kind"] == "explained"
