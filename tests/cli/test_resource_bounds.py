"""Resource bounds and rough edges under hostile files, by command and resource (issue 34).

Each case is a small file that would take unbounded memory or time, or a fault beyond the
ones tests/cli/test_hostile_inputs.py covers. The CLI runs in a subprocess under
``RLIMIT_AS`` and ``RLIMIT_CPU`` (and a wall-clock timeout), so a bound that regresses fails
the test in seconds instead of swapping or hanging CI. A refusal is one line naming the file
and the field, exit code 2, no traceback and nothing written (:func:`assert_refused`).

The last test checks that every command is listed here with the resources it reads (or why
it reads none): a new command cannot ship without its bounds.
"""

from __future__ import annotations

import json
import os
import resource
import signal
import struct
import subprocess
import sys
import time
import zlib
from pathlib import Path

import h5py
import numpy as np
import pytest

from tests.cli.test_hostile_inputs import CAM, SMALL_SCENE, THETA, _raw, assert_refused, write_good, write_raw_by_hand

#: Address space of a case: the CLI with numba, Embree and Open3D imported takes about 1.5 GB of
#: it; a runaway allocation (149 GB, 7 TB) fails at once instead of swapping.
MEMORY_LIMIT = 3 << 30
#: CPU seconds of a case: a refusal takes about 2 (interpreter and imports); an unbounded parse
#: or expansion is stopped by SIGXCPU well before CI's own timeout.
CPU_LIMIT_S = 30
TIMEOUT_S = 60


def _limits() -> None:
    resource.setrlimit(resource.RLIMIT_AS, (MEMORY_LIMIT, MEMORY_LIMIT))
    resource.setrlimit(resource.RLIMIT_CPU, (CPU_LIMIT_S, CPU_LIMIT_S))
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def run(*args: str | Path, cwd: Path, fsize: int | None = None) -> subprocess.CompletedProcess:
    def pre() -> None:
        _limits()
        if fsize is not None:
            resource.setrlimit(resource.RLIMIT_FSIZE, (fsize, fsize))
    env = dict(os.environ, COLUMNS="200", NO_COLOR="1")
    return subprocess.run([sys.executable, "-m", "tofhil.cli", *map(str, args)], cwd=cwd, capture_output=True,
                          text=True, timeout=TIMEOUT_S, preexec_fn=pre, env=env)


def start(*args: str | Path, cwd: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "tofhil.cli", *map(str, args)], cwd=cwd, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, preexec_fn=_limits)


def refused(tmp_path: Path, *args: str | Path, contains: tuple[str, ...] = (), fsize: int | None = None) -> str:
    """Run in an empty directory ``out`` (inputs elsewhere); refused, and ``out`` stays empty."""
    out = tmp_path / "out"
    out.mkdir(exist_ok=True)
    t0 = time.monotonic()
    res = run(*args, cwd=out, fsize=fsize)
    line = assert_refused(res, contains=contains)
    assert list(out.iterdir()) == [], f"left behind: {list(out.iterdir())}"
    assert time.monotonic() - t0 < TIMEOUT_S
    return line


# ---------------------------------------------------------------------------- hostile files
def _scene(tmp_path: Path, name: str, text: str) -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def _with_objects(objects_yaml: str) -> str:
    head, tail = SMALL_SCENE.split("objects:\n")
    return head + "objects:\n" + objects_yaml + "sensor:" + tail.split("sensor:", 1)[1]


def billion_laughs() -> str:
    """Nine levels of nine aliases (9^9 = 3.9 x 10^8 values) in the description of a scene."""
    parts = ["&l0 [1,1,1,1,1,1,1,1,1]"] + [f"&l{i} [" + ",".join([f"*l{i - 1}"] * 9) + "]" for i in range(1, 9)]
    return SMALL_SCENE.replace("name: small_wall", "name: lol\ndescription: [" + ", ".join(parts) + "]")


def png_header(width: int, height: int) -> bytes:
    """A PNG whose header declares ``width`` x ``height`` (its pixel data is a stub)."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(b"\0" * 1000)) + chunk(b"IEND", b""))


def session_declaring(path: Path, width: int, height: int, freqs: int = 1) -> Path:
    """A few kB of HDF5 whose camera and datasets declare ``width`` x ``height`` (chunked, so
    nothing is stored), as a hostile or broken writer makes it."""
    cam = json.loads(CAM.to_json()) | {"width": width, "height": height, "cx": width / 2, "cy": height / 2}
    with h5py.File(path, "w") as f:
        f.attrs.update(format="tofhil.session", format_version=1, device="{}", scene="", camera=json.dumps(cam),
                       n_frames=1)
        f.create_dataset("raw/taps", shape=(1, freqs, 4, height, width), dtype="f4", chunks=(1, 1, 1, 64, 64))
        f["raw/freq_hz"] = np.linspace(20e6, 80e6, freqs)
        f["raw/theta_rad"] = THETA
        f["raw"].attrs["integration_time_s"] = 1e-3
        f["frames/timestamp_s"] = np.zeros(1)
        f["frames/sequence"] = np.zeros(1, "i8")
    return path


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("bounds")
    p = {"good": write_good(d / "good.h5")}
    p["zero"] = write_raw_by_hand(d / "zero.h5", taps=_raw([20e6], 0).taps[None][:0])
    p["huge_camera"] = session_declaring(d / "huge_camera.h5", 100_000, 100_000)
    p["huge_frame"] = session_declaring(d / "huge_frame.h5", 4096, 4096, freqs=3)  # 2 x 10^8 values a frame
    cam = json.loads(CAM.to_json()) | {"width": 40.5}
    p["fractional_width"] = write_raw_by_hand(d / "fractional_width.h5", camera=cam)
    # another camera size than good.h5's 40 x 30
    other = json.loads(CAM.to_json()) | {"width": 20, "cx": 9.5}
    p["other_size"] = write_raw_by_hand(d / "other_size.h5", taps=_raw([20e6], 0).taps[None][..., :20], camera=other)
    return p


# ---------------------------------------------------------------------------- simulate: scene files
def test_simulate_yaml_billion_laughs(tmp_path: Path) -> None:
    scene = _scene(tmp_path, "laughs.yaml", billion_laughs())
    assert scene.stat().st_size - len(SMALL_SCENE) < 500  # the aliases: under 500 bytes
    refused(tmp_path, "simulate", scene, "--out", "s.h5", contains=("laughs.yaml", "1,000,000 values"))


def test_simulate_yaml_alias_of_itself(tmp_path: Path) -> None:
    scene = _scene(tmp_path, "self.yaml", SMALL_SCENE.replace("name: small_wall", "name: x\ndescription: &a [*a]"))
    refused(tmp_path, "simulate", scene, "--out", "s.h5", contains=("self.yaml", "aliases"))


def test_simulate_million_objects_by_alias(tmp_path: Path) -> None:
    objects = ("  - &o {name: wall, type: plane, size: [4.0, 3.0], material: wall, "
               "pose: {position: [0.0, 0.0, 1.0]}}\n" + "  - *o\n" * 999_999)
    scene = _scene(tmp_path, "million.yaml", _with_objects(objects))
    refused(tmp_path, "simulate", scene, "--out", "s.h5", contains=("million.yaml", "values"))


def test_simulate_object_count(tmp_path: Path) -> None:
    # the count is checked before any object is validated: empty entries are enough
    objects = "  - {}\n" * 10_001
    scene = _scene(tmp_path, "many.yaml", _with_objects(objects))
    refused(tmp_path, "simulate", scene, "--out", "s.h5", contains=("many.yaml", "'objects'", "10,001", "10,000"))


@pytest.mark.parametrize("kind", ["png", "npy"])
def test_simulate_texture_pixels_from_header(kind: str, tmp_path: Path) -> None:
    image = tmp_path / f"huge.{kind}"
    if kind == "png":
        image.write_bytes(png_header(30_000, 30_000))
    else:
        with image.open("wb") as fh:  # the header alone: 7.2 GB of float64 declared
            np.lib.format.write_array_header_1_0(fh, {"descr": "<f8", "fortran_order": False,
                                                      "shape": (30_000, 30_000)})
    text = SMALL_SCENE.replace("wall: {reflectance: 0.8}",
                               f"wall: {{reflectance: 0.8, texture: {{type: image, file: {image.name}}}}}")
    scene = _scene(tmp_path, "textured.yaml", text)
    refused(tmp_path, "simulate", scene, "--out", "s.h5",
            contains=("textured.yaml", "materials.wall.texture.file", "30000 x 30000", "4096 x 4096"))


@pytest.mark.parametrize("kind", ["ply", "stl", "obj"])
def test_simulate_mesh_triangles_before_loading(kind: str, tmp_path: Path) -> None:
    mesh = tmp_path / f"big.{kind}"
    if kind == "ply":  # the header declares 10^7 faces
        mesh.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                        "property float z\nelement face 10000000\nproperty list uchar int vertex_indices\n"
                        "end_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
    elif kind == "stl":  # binary: 3 x 10^6 triangles (a sparse file of 150 MB)
        with mesh.open("wb") as fh:
            fh.write(b"\0" * 80 + struct.pack("<I", 3_000_000))
            fh.truncate(84 + 50 * 3_000_000)
    else:  # 2 x 10^6 + 1 face lines (16 MB)
        mesh.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n" + "f 1 2 3\n" * 2_000_001)
    scene = _scene(tmp_path, "meshed.yaml", _with_objects(
        f"  - {{name: m, type: mesh, file: {mesh.name}, material: wall}}\n"))
    refused(tmp_path, "simulate", scene, "--out", "s.h5", contains=("meshed.yaml", "objects[0].file", "2,000,000"))


# ---------------------------------------------------------------------------- sessions
SESSION_COMMANDS = {
    "info": ["info", "{s}"],
    "depth": ["depth", "{s}", "--out", "d.h5"],
    "correct": ["correct", "{s}", "--method", "smooth-median", "--out", "c.h5"],
    "compare": ["compare", "{s}", "{s}", "--out", "cmp"],
    "diagnose": ["diagnose", "{s}", "--scene", "wall", "--out", "dg"],
    "import": ["import", "{s}", "--out", "i.h5"],
    "export": ["export", "{s}", "--out", "e.mcap"],
    "calibrate-taps": ["calibrate-taps", "--flat", "{s}", "--out", "t.npz"],
    "calibrate-camera": ["calibrate-camera", "{s}", "--target", "checkerboard:9x6:0.03", "--out", "c.yaml"],
    "calibrate-stereo": ["calibrate-stereo", "{s}", "--target", "checkerboard:9x6:0.03", "--out", "x.yaml"],
    "scene-from-capture": ["scene-from-capture", "{s}", "--out", "sc.yaml"],
    "model": ["model", "{s}", "{s}", "--out", "m.ply"],
    "view": ["view", "{s}", "--save", "v.rrd"],
    "capture": ["capture", "--device", "replay:{s}", "--frames", "1", "--out", "cap.h5"],
}


@pytest.mark.parametrize("command", sorted(SESSION_COMMANDS))
def test_session_declaring_a_huge_camera(command: str, files: dict[str, Path], tmp_path: Path) -> None:
    """11 kB declaring 100000 x 100000 (149 GB for depth): refused when opened, by every reader."""
    assert files["huge_camera"].stat().st_size < 50_000
    argv = [a.replace("{s}", str(files["huge_camera"])) for a in SESSION_COMMANDS[command]]
    refused(tmp_path, *argv, contains=("huge_camera.h5", "'camera'", "100000 x 100000"))


def test_session_frame_values(files: dict[str, Path], tmp_path: Path) -> None:
    refused(tmp_path, "depth", files["huge_frame"], "--out", "d.h5", contains=("huge_frame.h5", "raw/taps"))


def test_session_fractional_width(files: dict[str, Path], tmp_path: Path) -> None:
    refused(tmp_path, "info", files["fractional_width"], contains=("fractional_width.h5", "'width'", "40.5",
                                                                   "an integer"))


@pytest.mark.parametrize("command", ["depth", "correct", "compare", "import", "export", "diagnose"])
def test_session_of_no_frames(command: str, files: dict[str, Path], tmp_path: Path) -> None:
    argv = [a.replace("{s}", str(files["zero"])) for a in SESSION_COMMANDS[command]]
    refused(tmp_path, *argv, contains=("zero.h5", "n_frames", "no complete frame"))


def test_compare_of_two_camera_sizes(files: dict[str, Path], tmp_path: Path) -> None:
    refused(tmp_path, "compare", files["good"], files["other_size"], "--out", "cmp",
            contains=("good.h5", "40 x 30", "20 x 30"))


# ---------------------------------------------------------------------------- import / export
def test_import_mcap_image_without_header(tmp_path: Path) -> None:
    from mcap_ros2.writer import Writer

    from tofhil.drivers.importers import ros2

    bag = tmp_path / "noheader.mcap"
    definition = "uint32 height\nuint32 width\nstring encoding\nuint8 is_bigendian\nuint32 step\nuint8[] data\n"
    with bag.open("wb") as fh:
        w = Writer(fh)
        schema = w.register_msgdef(ros2.IMAGE, definition)
        data = np.full((30, 40), 1.2, "<f4").tobytes()
        for i in range(2):
            w.write_message("/tof/depth", schema, {"height": 30, "width": 40, "encoding": "32FC1", "is_bigendian": 0,
                                                   "step": 160, "data": data}, log_time=i, publish_time=i)
        w.finish()
    refused(tmp_path, "import", bag, "--out", "i.h5", contains=("noheader.mcap", "/tof/depth", "Image.header"))


def test_export_onto_a_full_disk_names_the_bag(files: dict[str, Path], tmp_path: Path) -> None:
    refused(tmp_path, "export", files["good"], "--out", "e.mcap", fsize=4096, contains=("e.mcap", "cannot be written"))


# ---------------------------------------------------------------------------- sweep specs
@pytest.mark.parametrize("case, axes, expect", [
    ("linspace", "  params.wall_distance_m: {linspace: [0.5, 2.0, 1e12]}\n", ("linspace", "100,000")),
    ("grid", "  params.wall_distance_m: {linspace: [0.5, 2.0, 1000]}\n"
             "  params.wall_reflectance: {linspace: [0.1, 0.9, 1001]}\n", ("1,001,000 cases", "1,000,000")),
    ("list", "  params.wall_distance_m: [" + ", ".join(["1.0"] * 100_001) + "]\n", ("100,001 values",)),
])
def test_sweep_axis_and_case_counts(case: str, axes: str, expect: tuple[str, ...], tmp_path: Path) -> None:
    spec = tmp_path / f"{case}.yaml"
    spec.write_text("scene: wall\naxes:\n" + axes)
    refused(tmp_path, "sweep", spec, "--out", "sw", contains=(f"{case}.yaml", "axes", *expect))


def test_sweep_spec_size_before_reading(tmp_path: Path) -> None:
    spec = tmp_path / "huge.yaml"
    with spec.open("wb") as fh:  # 20 MB (sparse): refused from its size, never read
        fh.truncate(20 << 20)
    refused(tmp_path, "sweep", spec, "--out", "sw", contains=("huge.yaml", "16 MiB"))


# ---------------------------------------------------------------------------- capture: options
@pytest.mark.parametrize("faults, expect", [("crc=1.5", "probability in [0, 1]"), ("timeout=nan", "probability"),
                                            ("crc@-2", "integer >= 0"), ("disconnect_s=inf", "duration")])
def test_capture_fault_probabilities(faults: str, expect: str, tmp_path: Path) -> None:
    refused(tmp_path, "capture", "--device", "emulator", "--frames", "1", "--out", "c.h5", "--faults", faults,
            contains=("--faults", expect))


# ---------------------------------------------------------------------------- signals
def _wait_for(path_glob: str, where: Path, min_bytes: int, deadline_s: float = 40) -> None:
    deadline = time.monotonic() + deadline_s
    while time.monotonic() < deadline:
        if any(p.stat().st_size >= min_bytes for p in where.glob(path_glob)):
            return
        time.sleep(0.05)
    raise AssertionError(f"no {path_glob} of {min_bytes} bytes in {deadline_s} s")


def long_session(path: Path, n: int = 3000) -> Path:
    """``n`` raw frames written at once with h5py (a second), which take seconds to import."""
    return write_raw_by_hand(path, taps=np.repeat(_raw([20e6], 0).taps[None], n, axis=0))


def test_sigterm_during_import_leaves_nothing(tmp_path: Path) -> None:
    """SIGTERM as Ctrl-C: exit 130, one line, no .OUT.PID.partial (it was killed silently)."""
    src = long_session(tmp_path / "src.h5")
    proc = start("import", src, "--out", "i.h5", cwd=tmp_path)
    try:
        _wait_for(".i.h5.*.partial", tmp_path, 1)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=TIMEOUT_S)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, err
    assert [ln for ln in err.splitlines() if ln.strip()] == ["interrupted (nothing was written)"], err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["src.h5"]


def test_sigterm_during_simulate_keeps_frames(tmp_path: Path) -> None:
    from tofhil.session import open_session

    scene = _scene(tmp_path, "small.yaml", SMALL_SCENE)
    proc = start("simulate", scene, "--out", "s.h5", "--frames", "1000000", cwd=tmp_path)
    try:
        _wait_for(".s.h5.*.partial", tmp_path, 100_000)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=TIMEOUT_S)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, err
    n = int(err.split()[1])
    with open_session(tmp_path / "s.h5") as s:
        assert s.n_frames == n > 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.h5", "small.yaml"]


def test_partial_of_a_killed_run_removed_by_the_next(tmp_path: Path) -> None:
    """SIGKILL cannot be handled: the next run of the same output removes what it left."""
    src = long_session(tmp_path / "src.h5")
    proc = start("import", src, "--out", "i.h5", cwd=tmp_path)
    try:
        _wait_for(".i.h5.*.partial", tmp_path, 1)
        proc.kill()
        proc.communicate(timeout=TIMEOUT_S)
    finally:
        if proc.poll() is None:
            proc.kill()
    left = list(tmp_path.glob(".i.h5.*.partial"))
    assert left, "the killed import left no partial file: the test did not test anything"
    res = run("import", write_good(tmp_path / "small.h5"), "--out", "i.h5", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["i.h5", "small.h5", "src.h5"]


def test_partial_of_a_running_writer_is_kept(tmp_path: Path) -> None:
    """Only a dead process's partial file goes: a live one (a concurrent writer) is kept."""
    from tofhil.outputs import partial_path

    live = tmp_path / f".o.h5.{os.getppid()}.partial"
    dead = tmp_path / ".o.h5.999999999.partial"
    for p in (live, dead):
        p.write_bytes(b"x")
    mine = partial_path(tmp_path / "o.h5")
    assert mine.name == f".o.h5.{os.getpid()}.partial"
    assert live.exists() and not dead.exists()


# ---------------------------------------------------------------------------- every command listed
#: Each command, the hostile resources the cases above (or tests/cli/test_hostile_inputs.py)
#: give it, or why it reads none. A new command fails the test below until it is listed here.
COVERAGE: dict[str, str] = {
    **{c: "session bounds (test_session_declaring_a_huge_camera)" for c in SESSION_COMMANDS},
    "simulate": "scene bounds: YAML, aliases, objects, textures, meshes",
    "emulate": "scene bounds through the same loader (tests/cli/test_hostile_inputs.py: emulate-*)",
    "sweep": "sweep bounds: axis values, cases; the spec through the YAML bounds",
    "batch": "sessions of a batch are cases: a refused session is a failed case, recorded in the table",
    "colorize": "reads Azure Kinect MKV recordings (tests/drivers/test_import_mkv.py: truncated and malformed)",
    "ndt": "reads point clouds or sessions (tests/cli/test_hostile_inputs.py: ndt-*)",
    "demo": "its inputs are bundled",
    "bench": "plans and spec sheets through the YAML bounds, scenes through the scene bounds, its captures' "
             "sessions through the session bounds (tests/app/test_bench_campaign.py: impossible plans, unknown "
             "spec fields); its numeric options of every procedure, interference's --levels included "
             "(tests/cli/test_hostile_inputs.py: bench-*)",
    "devices": "reads no file",
    "effects": "reads no file",
}


def test_every_command_has_its_bounds_listed() -> None:
    import typer

    from tofhil.cli import _register_command_modules, app

    _register_command_modules()
    commands = set(typer.main.get_command(app).commands)
    assert commands - set(COVERAGE) == set(), "list the new command's hostile inputs in COVERAGE"
    assert set(COVERAGE) - commands == set()


# ---------------------------------------------------------------------------- --max-memory
@pytest.mark.parametrize("command", ["simulate", "diagnose"])
def test_max_memory_refuses_before_the_render(command: str, files: dict[str, Path], tmp_path: Path) -> None:
    from tofhil.sim.pipeline import simulate_session
    from tofhil.sim.scene import scene_from_yaml

    scene = _scene(tmp_path, "small.yaml", SMALL_SCENE)
    session = tmp_path / "small.h5"
    if command == "diagnose":
        simulate_session(scene_from_yaml(SMALL_SCENE), session, frames=2)
    argv = (["simulate", scene, "--out", "s.h5"] if command == "simulate"
            else ["diagnose", session, "--scene", scene, "--out", "dg"])
    refused(tmp_path, *argv, "--max-memory", "64K", contains=("small.yaml", "--max-memory 0.1 MiB"))


def test_max_memory_is_a_size(tmp_path: Path) -> None:
    refused(tmp_path, "simulate", "wall", "--out", "s.h5", "--max-memory", "lots", contains=("--max-memory",))
