"""The CLI imports only the module of a command listed in ``_COMMAND_HOME``: that module must
be the one that registers the command, and the command must work started alone. A short
command (``tofhil ndt``, timed against PCL as a whole process) imports neither pydantic (typer's
coercion), importlib.metadata (the version) nor rich (JSON into a pipe)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

import tofhil.cli as cli

DATA = Path(__file__).resolve().parents[1] / "data" / "pcl"


def test_command_home_is_the_registering_module():
    cli._register_command_modules()
    homes = {}
    for info in cli.app.registered_commands:
        name = info.name or info.callback.__name__.replace("_", "-")
        homes[name] = info.callback.__module__
    for command, module in cli._COMMAND_HOME.items():
        assert homes[command] == module
        assert module in cli.COMMAND_MODULES


def test_ndt_alone_imports_no_other_command_module():
    code = ("import sys, tofhil.cli as c\n"
            "try:\n    c.main(['ndt', '--help'])\nexcept SystemExit as e:\n    assert not e.code, e.code\n"
            "others = [m for m in c.COMMAND_MODULES if m in sys.modules and m != 'tofhil.cli.ndt']\n"
            "print('OTHERS', others, 'numba' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert "OTHERS [] False" in out


def _modules_after(args: list[str]) -> str:
    code = ("import sys, tofhil.cli as c\n"
            "try:\n    c.main(sys.argv[1:])\nexcept SystemExit as e:\n    print('EXIT', e.code)\n"
            "print('PYDANTIC', 'pydantic' in sys.modules, 'METADATA', 'importlib.metadata' in sys.modules)\n")
    return subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True).stdout


def _binary_pcd(src: Path, dst: Path) -> Path:
    """``src`` as a binary PCD (what the direct reader reads; ASCII ones go through Open3D,
    which imports pydantic itself)."""
    import numpy as np

    from tofhil.eval.metrics.clouds import load_cloud

    pts = load_cloud(src).astype("<f4")
    header = (f"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {len(pts)}\nHEIGHT 1\n"
              f"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(pts)}\nDATA binary\n")
    dst.write_bytes(header.encode() + np.ascontiguousarray(pts).tobytes())
    return dst


@pytest.mark.parametrize("what", ["score", "help", "root help"])
def test_ndt_and_help_import_neither_pydantic_nor_metadata(tmp_path, what):
    # typer 0.29 imports pydantic (~0.15 CPU-s with importlib.metadata) to coerce options;
    # the direct coercion must reach every parameter of the command, --help included.
    ref, cloud = (_binary_pcd(DATA / f"{n}.pcd", tmp_path / f"{n}.pcd") for n in ("ref", "cloud"))
    args = {"score": ["ndt", str(ref), str(cloud), "--cell-size", "0.5", "--score-only", "--json"],
            "help": ["ndt", "--help"], "root help": ["--help"]}[what]
    out = _modules_after(args)
    assert "EXIT 0" in out and "PYDANTIC False METADATA False" in out, out


def test_bad_ndt_option_is_one_line_without_pydantic():
    out = subprocess.run([sys.executable, "-c",
                          "import sys, tofhil.cli as c\n"
                          "try:\n    c.main(sys.argv[1:])\nexcept SystemExit as e:\n    print('EXIT', e.code)\n"
                          "print('PYDANTIC', 'pydantic' in sys.modules)\n",
                          "ndt", str(DATA / "ref.pcd"), str(DATA / "cloud.pcd"), "--cell-size", "-1"],
                         capture_output=True, text=True)
    assert "EXIT 2" in out.stdout and "PYDANTIC False" in out.stdout
    assert out.stderr.strip().splitlines() == [
        "error: tofhil ndt: Invalid value for '--cell-size': -1 is out of range "
        "(expected a finite number in (0, 1000] m)"]


def test_ndt_json_imports_no_rich(tmp_path):
    ref, cloud = (_binary_pcd(DATA / f"{n}.pcd", tmp_path / f"{n}.pcd") for n in ("ref", "cloud"))
    code = ("import sys, json, tofhil.cli as c\n"
            "try:\n    c.main(sys.argv[1:])\nexcept SystemExit as e:\n    assert not e.code\n"
            "print('RICH', any(m.startswith('rich') for m in sys.modules))\n")
    out = subprocess.run([sys.executable, "-c", code, "ndt", str(ref), str(cloud), "--cell-size", "0.5",
                          "--score-only", "--json"], capture_output=True, text=True, check=True).stdout
    assert out.rstrip().endswith("RICH False")
    assert json.loads(out[:out.rindex("RICH")])["cells"] == 62
