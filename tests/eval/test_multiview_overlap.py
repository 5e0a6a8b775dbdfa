"""`tofhil model` of views that do not overlap is refused, not fused (issue 34's walkthrough: an
O3R and a Kinect capture of unrelated scenes were fused at ICP fitness 0.135 without a word)."""

from __future__ import annotations

from pathlib import Path

from tests.cli.test_hostile_inputs import assert_refused, run
from tofhil.sim.pipeline import simulate_session
from tofhil.sim.scene import load_scene


def test_unrelated_views_are_refused(tmp_path: Path) -> None:
    room = simulate_session(load_scene("room", overrides={"params": {"width_px": 80, "height_px": 60}}),
                            tmp_path / "room.h5", frames=2, seed=0)
    board = simulate_session(load_scene("board"), tmp_path / "board.h5", frames=2, seed=1)
    out = tmp_path / "out"
    out.mkdir()
    res = run("model", room, board, "--out", "m.ply", cwd=out)
    assert_refused(res, contains=("room and board do not overlap", "fitness"))
    assert list(out.iterdir()) == []
