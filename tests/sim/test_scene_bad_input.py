"""Hostile or mistaken scene files (issue 11): one clear error naming the file and the field,
exit code 2 on the CLI, bounded time and memory, no file left behind."""

from __future__ import annotations

import os
import subprocess
import tempfile
import sys
from pathlib import Path

import pytest
import yaml

from tofhil.errors import InputFileError, TofhilError
from tofhil.sim.memory import estimate_bytes
from tofhil.sim.scene import load_scene, scene_from_dict


def _scene_dict(**camera) -> dict:
    return {
        "camera": {"preset": "holmlund_thesis", **camera},
        "emitter": {"power_w": 0.5},
        "materials": {"wall": {"reflectance": 0.6}},
        "objects": [{"name": "wall", "type": "plane", "size": [3, 3], "material": "wall",
                     "pose": {"position": [0, 0, 1.0]}}],
    }


def _write(tmp_path: Path, d: dict, name: str = "s.yaml") -> Path:
    p = tmp_path / name
    p.write_text(yaml.safe_dump(d))
    return p


# The CLI in a fresh process that writes its own peak resident memory (VmHWM: this process's
# memory since exec) to a file. The rusage of a child is no measure: Linux carries the peak of
# the forked copy of the test process (over 1 GiB late in a full run) across the exec.
_PEAK_WRAPPER = """
import atexit, os, sys
def _peak():
    with open("/proc/self/status") as f, open(os.environ["TOFHIL_TEST_PEAK_FILE"], "w") as out:
        out.write(next(line for line in f if line.startswith("VmHWM:")).split()[1])
atexit.register(_peak)
from tofhil.cli import main
main()
"""


def _cli(*args, env: dict | None = None) -> tuple[subprocess.CompletedProcess, int]:
    """Run the CLI; returns the process and its peak resident memory since exec (bytes)."""
    with tempfile.TemporaryDirectory() as d:
        peak_file = Path(d) / "peak"
        p = subprocess.run([sys.executable, "-c", _PEAK_WRAPPER, *map(str, args)], capture_output=True, text=True,
                           env={**os.environ, **(env or {}), "TOFHIL_TEST_PEAK_FILE": str(peak_file)}, timeout=300)
        peak = int(peak_file.read_text()) * 1024 if peak_file.exists() else -1  # -1: not measured
    return p, peak


def _one_line_error(proc: subprocess.CompletedProcess, *needles: str) -> str:
    assert proc.returncode == 2, proc.stdout + proc.stderr
    text = (proc.stdout + proc.stderr).strip()
    assert "Traceback" not in text and len(text.splitlines()) <= 3, text   # rich may wrap the one line
    flat = " ".join(text.split())
    for n in needles:
        assert n in flat, flat
    return flat


def test_non_utf8_scene_names_the_file(tmp_path) -> None:
    p = tmp_path / "latin1.yaml"
    p.write_bytes(yaml.safe_dump(_scene_dict()).encode() + b"# caf\xe9\n")
    with pytest.raises(InputFileError) as e:
        load_scene(p)
    assert e.value.file == str(p) and "UTF-8" in str(e.value)


@pytest.mark.parametrize("expr, words", [("${1/0}", "divides by zero"), ("${9**9**9}", "beyond"),
                                         ("${2**4000}", "beyond"), ("${(-8)**0.5}", "negative"),
                                         ("${" + "1+" * 150 + "1}", "characters"), ("${__import__('os')}", "evaluate"),
                                         ("${rho.real}", "evaluate"), ("${nope}", "unknown parameter")])
def test_bad_expressions_fail_fast_naming_the_field(expr, words) -> None:
    d = _scene_dict()
    d["params"] = {"rho": 0.5}
    d["materials"]["wall"]["reflectance"] = expr
    with pytest.raises(InputFileError) as e:
        scene_from_dict(d, source="x.yaml")
    assert e.value.file == "x.yaml" and e.value.field == "materials.wall.reflectance" and words in str(e.value)


def test_huge_power_in_a_scene_fails_on_the_cli(tmp_path) -> None:
    d = _scene_dict()
    d["materials"]["wall"]["reflectance"] = "${9**9**9}"
    out = tmp_path / "o.h5"
    proc, _ = _cli("simulate", _write(tmp_path, d), "--out", out)
    _one_line_error(proc, "materials.wall.reflectance")
    assert not out.exists()


@pytest.mark.parametrize("mutate, field", [
    (lambda d: d["objects"][0].update(size=[float("nan"), 1.0]), "objects[0].size[0]"),
    (lambda d: d["objects"][0]["pose"].update(position=[0, 0, float("inf")]), "objects[0].pose.position[2]"),
    (lambda d: d["objects"][0]["pose"].update(position=[0, float("-inf"), 1]), "objects[0].pose.position[1]"),
    (lambda d: d["emitter"].update(power_w=float("nan")), "emitter.power_w"),
    (lambda d: d["camera"].update(fx=float("nan")), "camera.fx"),
    (lambda d: d["camera"].update(cx=float("inf")), "camera.cx"),
    (lambda d: d["camera"].update(dist=[0, 0, 0, 0, float("nan")]), "camera.dist[4]"),
    (lambda d: d.update(sensor={"wavelength_m": float("nan")}), "sensor.wavelength_m"),
    (lambda d: d.update(sensor={"freq_hz": [float("inf")]}), "sensor.freq_hz[0]"),
    (lambda d: d.update(ambient_irradiance_w_m2=float("nan")), "ambient_irradiance_w_m2"),
    (lambda d: d["materials"]["wall"].update(reflectance=float("nan")), "materials.wall.reflectance"),
    (lambda d: d.update(sensor={"read_nois_e": 3}), "sensor.read_nois_e"),
    (lambda d: d.update(render={"samples": 3}), "render.samples"),
    (lambda d: d.update(render={"bounces": 1.5}), "render.bounces"),
    (lambda d: d["camera"].update(width=8.5), "camera.width"),
    (lambda d: d["camera"].update(colour="red"), "camera.colour"),
    (lambda d: d.update(params={"k": float("nan")}), "params.k"),
])
def test_non_finite_and_unknown_values_name_the_field(mutate, field) -> None:
    d = _scene_dict()
    mutate(d)
    with pytest.raises(InputFileError) as e:
        scene_from_dict(d, source="bench.yaml")
    assert e.value.file == "bench.yaml" and e.value.field == field and e.value.expected


def test_nan_size_on_the_cli_is_refused_not_an_empty_frame(tmp_path) -> None:
    d = _scene_dict()
    d["objects"][0]["size"] = [float("nan"), 1.0]
    out = tmp_path / "o.h5"
    proc, _ = _cli("simulate", _write(tmp_path, d), "--out", out)
    _one_line_error(proc, "objects[0].size[0]")
    assert not out.exists()


def test_memory_estimate_of_huge_cameras() -> None:
    # 8000 x 8000 needs several GiB whatever the machine: the estimate says so before any allocation.
    e = estimate_bytes(width=8000, height=8000, render_freqs=1, harmonics=1, sensor_freqs=1, taps=4)
    assert e.total_bytes > 6 * 2 ** 30
    e2 = estimate_bytes(width=20000, height=20000, render_freqs=1, harmonics=1, sensor_freqs=1, taps=4)
    assert e2.total_bytes == pytest.approx(e.total_bytes * 20000 ** 2 / 8000 ** 2, rel=0.05)


@pytest.mark.parametrize("size", [(8000, 8000), (20000, 20000)])
def test_huge_camera_is_refused_before_allocating(tmp_path, size) -> None:
    w, h = size
    d = _scene_dict(width=w, height=h, cx=(w - 1) / 2, cy=(h - 1) / 2)
    out = tmp_path / "o.h5"
    # The machine's memory is whatever it is; tell the check it has 4 GiB.
    proc, peak = _cli("simulate", _write(tmp_path, d), "--out", out, env={"TOFHIL_MEMORY_LIMIT_BYTES": str(4 << 30)})
    msg = _one_line_error(proc, "needs about", "GiB", "available", "camera")
    assert "4.00 GiB is available" in msg
    assert not out.exists()
    assert 0 < peak < 1 << 30, f"the refusal itself used {peak / 2 ** 20:.0f} MiB"


def test_4000x3000_refused_past_the_available_memory(tmp_path) -> None:
    from tofhil.sim.pipeline import simulate

    w, h = 4000, 3000
    scene = scene_from_dict(_scene_dict(width=w, height=h, cx=(w - 1) / 2, cy=(h - 1) / 2), source="big.yaml")
    with pytest.raises(TofhilError) as e:
        os.environ["TOFHIL_MEMORY_LIMIT_BYTES"] = str(2 << 30)
        try:
            simulate(scene)
        finally:
            del os.environ["TOFHIL_MEMORY_LIMIT_BYTES"]
    assert e.value.file == "big.yaml" and e.value.field == "camera" and "2.00 GiB is available" in str(e.value)


def test_camera_sides_are_bounded_at_load() -> None:
    with pytest.raises(InputFileError) as e:
        scene_from_dict(_scene_dict(width=10 ** 9), source="x.yaml")
    assert e.value.field == "camera.width"


def test_directory_and_missing_scene(tmp_path) -> None:
    with pytest.raises(InputFileError, match="directory"):
        load_scene(tmp_path / ".")
    with pytest.raises(InputFileError, match="no such file"):
        load_scene(tmp_path / "missing.yaml")
