"""``tofhil ndt``: JSON keys, session-frame input, exit code 2 on bad input."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from tofhil.camera import CameraModel
from tofhil.cli import main
from tofhil.eval.metrics.clouds import load_cloud
from tofhil.eval.metrics.ndt import ndt_score
from tofhil.frames import DepthFrame
from tofhil.session import SessionWriter

DATA = Path(__file__).resolve().parents[1] / "data" / "pcl"


def run(capsys, *args: str) -> tuple[int, str, str]:
    with pytest.raises(SystemExit) as exc:
        main(list(args))
    cap = capsys.readouterr()
    return int(exc.value.code or 0), cap.out, cap.err


def test_json_output(capsys):
    ref, cloud = DATA / "ref.pcd", DATA / "cloud.pcd"
    code, out, _ = run(capsys, "ndt", str(ref), str(cloud), "--cell-size", "0.5", "--threshold", "0.2",
                       "--threshold", "0.6", "--json")
    assert code == 0
    d = json.loads(out)
    assert {"score_per_point", "nvtl", "mean_likelihood", "mean_likelihood_trilinear",
            "fraction_above", "cells"} <= set(d)
    assert set(d["fraction_above"]) == {"0.2", "0.6"}
    s = ndt_score(load_cloud(ref), load_cloud(cloud), cell_size=0.5, thresholds=(0.2, 0.6))
    assert d["score_per_point"] == pytest.approx(s.score_per_point, rel=1e-12)
    assert d["cells"] == 62           # PCL 1.13 counts 62 voxels here (tests/data/pcl)
    assert d["fraction_above"]["0.2"] >= d["fraction_above"]["0.6"]


def test_score_only_json_and_text(capsys):
    ref, cloud = DATA / "ref.pcd", DATA / "cloud.pcd"
    code, out, _ = run(capsys, "ndt", str(ref), str(cloud), "--cell-size", "0.5", "--score-only", "--json")
    assert code == 0
    d = json.loads(out)
    assert set(d) == {"score_per_point", "cells", "n_points", "cell_size", "outlier_ratio"}
    s = ndt_score(load_cloud(ref), load_cloud(cloud), cell_size=0.5)
    assert d["score_per_point"] == pytest.approx(s.score_per_point, abs=1e-12)
    assert d["cells"] == 62
    code, out, _ = run(capsys, "ndt", str(ref), str(cloud), "--cell-size", "0.5", "--score-only", "--d2d")
    assert code == 0 and "score per point (PCL)" in out and "D2D" in out and "NVTL" not in out


def test_session_frames_and_text(tmp_path, capsys):
    cam = CameraModel.from_fov(40, 30, 60.0)
    path = tmp_path / "s.h5"
    with SessionWriter(path, cam) as w:
        w.append(depth=DepthFrame(np.full((30, 40), 1.0), "z", cam))
        w.append(depth=DepthFrame(np.full((30, 40), 1.05), "z", cam))
    np.savetxt(tmp_path / "same.xyz", load_cloud(f"{path}:0"))
    code, out, _ = run(capsys, "ndt", f"{path}:0", str(tmp_path / "same.xyz"), "--cell-size", "0.1", "--json")
    same = json.loads(out)
    code2, out2, _ = run(capsys, "ndt", f"{path}:0", f"{path}:1", "--cell-size", "0.1", "--json")
    moved = json.loads(out2)
    assert code == code2 == 0
    # A flat wall scored against itself vs 5 cm behind it (normal std floored at 10 % of in-plane).
    assert same["mean_likelihood"] > 0.2 and moved["mean_likelihood"] < 0.01
    code3, out3, _ = run(capsys, "ndt", f"{path}:0", f"{path}:1", "--cell-size", "0.1")
    assert code3 == 0 and "NVTL" in out3


@pytest.mark.parametrize("args,msg", [
    (["missing.pcd", "{cloud}"], "missing.pcd: no such file"),
    (["{ref}", "{cloud}", "--cell-size", "-1"], "--cell-size"),
    (["{ref}", "{cloud}", "--outlier-ratio", "1.5"], "--outlier-ratio"),
    (["{ref}", "{cloud}", "--threshold", "2"], "--threshold"),
    (["{ref}", "{cloud}", "--cell-size", "0.01"], "no NDT cell"),
])
def test_bad_input_exits_2(capsys, args, msg):
    a = [x.format(ref=DATA / "ref.pcd", cloud=DATA / "cloud.pcd") for x in args]
    code, _, err = run(capsys, "ndt", *a)
    assert code == 2
    assert msg in err.replace("\n", "")
    assert "Traceback" not in err


def test_several_resolutions_and_d2d(capsys):
    ref, cloud = DATA / "ref.pcd", DATA / "cloud.pcd"
    code, out, _ = run(capsys, "ndt", str(ref), str(cloud), "--cell-size", "0.5", "--cell-size", "0.25",
                       "--d2d", "--json")
    assert code == 0
    d = json.loads(out)
    assert set(d["resolutions"]) == {"0.5", "0.25"}
    assert d["cells"] == d["resolutions"]["0.5"]["cells"] == 62
    assert d["resolutions"]["0.25"]["cells"] == 223          # PCL's count at 0.25 m
    assert 0 < d["d2d"]["mean_similarity"] < 1 and d["d2d"]["pairs"] > 0
    code, out, _ = run(capsys, "ndt", str(ref), str(cloud), "--cell-size", "0.5", "--cell-size", "0.25", "--d2d")
    assert code == 0 and out.count("NVTL") == 2 and "D2D" in out
