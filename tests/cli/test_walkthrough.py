"""The README's and the docs' workflows as a new user walks them (issue 34's walkthrough table)."""

from __future__ import annotations

from pathlib import Path

from tests.cli.test_hostile_inputs import CAM, _raw, run
from tofhil.depth import depth_from_raw
from tofhil.session import SessionWriter, open_session


def test_replay_past_the_end_ends_cleanly(tmp_path: Path) -> None:
    """docs/importers.md: reading past the end ends a capture cleanly: the 4 frames with the
    embedded scene, a one-line note, exit 0 (it was exit 2 and the scene was dropped)."""
    src = tmp_path / "four.h5"
    with SessionWriter(src, CAM, device={"model": "test"}, scene_text="name: recorded_twin\n") as w:
        for i in range(4):
            raw = _raw([20e6], i)
            w.append(raw, depth_from_raw(raw))
    res = run("capture", "--device", f"replay:{src}", "--frames", "10", "--out", "r.h5", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert [ln for ln in res.stderr.splitlines() if ln.strip()] == [
        "note: the recording ended after 4 of 10 frames"], res.stderr
    with open_session(tmp_path / "r.h5") as s:
        assert s.n_frames == 4 and s.scene_text == "name: recorded_twin\n"


def _taps(path: Path):
    with open_session(path) as s:
        return s.raw_frame(0).taps, s.device.get("emulator_seed")


def test_emulated_captures_draw_fresh_noise_and_record_the_seed(tmp_path: Path) -> None:
    """Two captures of the emulated bench differ as a real camera's do (they were bit-identical,
    and compare reported 1 mm under a 14 mm noise floor); --seed repeats one exactly."""
    import numpy as np

    for name, extra in (("a", ()), ("b", ()), ("c", ("--seed", "7")), ("d", ("--seed", "7"))):
        res = run("capture", "--device", "emulator:wall:1", "--frames", "1", "--out", f"{name}.h5", *extra,
                  cwd=tmp_path)
        assert res.returncode == 0, res.stderr
    (a, seed_a), (b, seed_b), (c, seed_c), (d, _) = (_taps(tmp_path / f"{n}.h5") for n in "abcd")
    assert seed_a != seed_b and seed_c == 7
    assert not np.array_equal(a, b)
    np.testing.assert_array_equal(c, d)


def test_compare_defines_the_depth_rmse_once(tmp_path: Path) -> None:
    """The 100-character definition is printed once, under the lines that use it (it was
    repeated on every line of compare's and diagnose's console)."""
    from tests.cli.test_hostile_inputs import SMALL_SCENE
    from tofhil.eval.metrics.core import DEPTH_RMSE
    from tofhil.sim.pipeline import simulate_session
    from tofhil.sim.scene import scene_from_yaml

    a, b = tmp_path / "a.h5", tmp_path / "b.h5"
    for seed, path in enumerate((a, b)):
        simulate_session(scene_from_yaml(SMALL_SCENE), path, frames=2, seed=seed, noise=True)
    res = run("compare", a, b, "--out", "cmp", "--roi", "0,0,20,15", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    text = " ".join(res.stdout.split())  # unfolded
    assert text.count(DEPTH_RMSE) == 1
    assert text.count("depth RMSE*") == 3  # the whole image, the wall, the ROI


def test_simulate_report_of_a_glass_scene(tmp_path: Path) -> None:
    """A row of the README's tour: `simulate glass_pane --report DIR` writes the session and a
    report that says what it cannot show (it was exit 2: no multipath shares through glass)."""
    import json

    res = run("simulate", "glass_pane", "--out", "g.h5", "--report", "rep", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    notes = json.loads((tmp_path / "rep" / "report.json").read_text())["notes"]
    assert len(notes) == 1 and "glass" in notes[0]
    assert "glass or scattering media" in (tmp_path / "rep" / "report.html").read_text()
