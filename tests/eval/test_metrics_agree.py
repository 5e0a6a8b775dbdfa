"""compare and diagnose print one depth RMSE: the same figure on the same pair of sessions.

The capture carries a hidden range offset; the twin is the same scene without it, rendered
noise-free like diagnosis's own base twin. Diagnosis writes the held-out pixels its figures
use; ``compare`` of the capture against the twin over that mask must give diagnosis's
"before" depth RMSE, over the same number of pixels. The capture is noise-free with 2 frames
so that diagnosis's held-out frame and compare's frame average are the same data; what is
left is float32 (compare demodulates each stored frame) against float64 rounding.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from tofhil.eval.compare import compare_sessions
from tofhil.eval.diagnose.run import HELD_OUT, HELD_OUT_MASK, run_diagnosis
from tofhil.eval.metrics.core import DEPTH_RMSE
from tofhil.sim.pipeline import simulate_session
from tofhil.sim.scene import load_scene, scene_to_yaml


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    d = tmp_path_factory.mktemp("pair")
    scene = load_scene("bench_demo")
    scene = dataclasses.replace(scene, camera=scene.camera.scaled(0.25))  # 40 x 30
    (d / "twin.yaml").write_text(scene_to_yaml(scene))
    simulate_session(scene, d / "capture.h5", frames=2, seed=1, noise=False,
                     effects={"range_offset": {"path_m": 0.05}})
    simulate_session(scene, d / "twin.h5", frames=1, seed=1, noise=False)
    return d


def test_compare_and_diagnose_give_the_same_depth_rmse(pair):
    d = pair
    res = run_diagnosis(d / "capture.h5", d / "twin.yaml", d / "diag", candidates=["range_offset"], max_effects=1)
    before = res.evaluations["before"].regions[HELD_OUT]
    assert res.gain["depth_rmse_m"]["before"] == before.depth_rmse_m
    assert before.depth_rmse_m > 0.01  # the hidden offset is visible: the figure means something
    mask = np.load(d / "diag" / HELD_OUT_MASK)
    assert mask.sum() == before.depth_residual_m.n > 100

    m = compare_sessions(d / "capture.h5", d / "twin.h5", d / "cmp", masks=[d / "diag" / HELD_OUT_MASK],
                         objects=False)
    region = m["variants"]["measured"]["regions"][f"mask_{HELD_OUT_MASK[:-4]}"]
    assert region["depth_residual_m"]["n"] == before.depth_residual_m.n  # the same pixels
    assert region["depth_rmse_m"] == pytest.approx(before.depth_rmse_m, rel=1e-6)
    # the median is one pixel's value: float32 demodulation resolves its phase to ~1e-7 rad, ~1e-7 m
    assert region["depth_residual_m"]["median"] == pytest.approx(before.depth_residual_m.median, abs=1e-6)
    # one name for the figure in both outputs
    assert m["depth_rmse_definition"] == DEPTH_RMSE
    assert json.loads((d / "diag" / "diagnosis.json").read_text())["depth_rmse_definition"].startswith(DEPTH_RMSE)
    assert DEPTH_RMSE in (d / "diag" / "report.html").read_text()
    assert DEPTH_RMSE in (d / "cmp" / "report.html").read_text()
