"""benchmarks/before_after.py: a benchmark run alternately by an older tofhil and this one."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
from before_after import run_alternating, strip_before  # noqa: E402


def test_the_children_get_the_arguments_without_before_and_rounds() -> None:
    assert strip_before(["--skip-c", "--before", "/x", "--rounds", "3", "--threads", "2"]) == ["--skip-c", "--threads", "2"]
    assert strip_before(["--before=/x", "--rounds=2", "-q"]) == ["-q"]


def test_each_round_runs_the_older_tofhil_then_this_one(tmp_path, capsys) -> None:
    old = tmp_path / "old"
    (old / "tofhil").mkdir(parents=True)
    (old / "tofhil" / "__init__.py").write_text("WHICH = 'the older one'\n")
    script = tmp_path / "bench.py"
    script.write_text("import sys, tofhil\nprint(getattr(tofhil, 'WHICH', 'this one'), sys.argv[1:])\n")
    run_alternating(str(script), ["--x", "--before", str(old), "--rounds", "2"], old, 2)
    lines = capsys.readouterr().out.splitlines()
    assert lines == ["[before 1] the older one ['--x']", "[after 1] this one ['--x']",
                     "[before 2] the older one ['--x']", "[after 2] this one ['--x']"]


def test_a_folder_without_tofhil_is_refused_with_its_name(tmp_path) -> None:
    with pytest.raises(SystemExit, match="expected a folder holding tofhil/__init__.py"):
        run_alternating(__file__, [], tmp_path, 1)
