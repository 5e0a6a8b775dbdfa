"""Hostile and mistaken input through the CLI, as a user types it (issue 11).

Every case runs ``tofhil`` in a subprocess (bounded time and address space) and must give
exit code 2, exactly one line on stderr (``error: ...``), no traceback, no input changed and
no file left behind. Fixture sessions are written once per module with SessionWriter (small,
40 x 30 pixels); malformed sessions are written with h5py as another tool would.
"""

from __future__ import annotations

import hashlib
import json
import os
import resource
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from tofhil.camera import CameraModel
from tofhil.demod import distance_to_phase, equally_spaced_phases, taps_from_signal
from tofhil.depth import depth_from_raw
from tofhil.frames import RawFrame
from tofhil.session import SessionWriter

TIMEOUT_S = 120
MEMORY_LIMIT = 4 << 30  # address space: generous, but a runaway allocation fails instead of swapping


def _limits() -> None:
    resource.setrlimit(resource.RLIMIT_AS, (MEMORY_LIMIT, MEMORY_LIMIT))
    # a shell starts background jobs with SIGINT ignored and Python keeps it ignored: the CLI
    # gets a terminal user's Ctrl-C disposition whatever way the tests were started
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def run(*args: str | Path, cwd: Path, fsize: int | None = None, timeout: float = TIMEOUT_S
        ) -> subprocess.CompletedProcess:
    def pre() -> None:
        _limits()
        if fsize is not None:
            resource.setrlimit(resource.RLIMIT_FSIZE, (fsize, fsize))
    env = dict(os.environ, COLUMNS="80", NO_COLOR="1")
    return subprocess.run([sys.executable, "-m", "tofhil.cli", *map(str, args)], cwd=cwd, capture_output=True,
                          text=True, timeout=timeout, preexec_fn=pre, env=env)


# ---------------------------------------------------------------------------------- fixtures
CAM = CameraModel.from_fov(40, 30, 60.0)
THETA = equally_spaced_phases(4)


def _raw(freqs: list[float], seq: int, *, dtype=np.float32) -> RawFrame:
    d = np.full(CAM.shape, 1.2)
    amp = np.full((len(freqs),) + CAM.shape, 300.0)
    phase = np.stack([distance_to_phase(d, f) for f in freqs])
    taps = taps_from_signal(amp, phase, np.full(amp.shape, 800.0), THETA).astype(dtype)
    return RawFrame(taps=taps, freq_hz=freqs, theta_rad=THETA, integration_time_s=1e-3, camera=CAM,
                    sequence=seq, timestamp_s=0.05 * seq)


def write_good(path: Path, n: int = 2) -> Path:
    with SessionWriter(path, CAM, device={"model": "test"}) as w:
        for i in range(n):
            raw = _raw([20e6], i)
            w.append(raw, depth_from_raw(raw))
    return path


def write_raw_by_hand(path: Path, *, taps=None, freq=(20e6,), theta=None, camera=None, attrs=None,
                      raw_attrs=None, drop=()) -> Path:
    """A session as another tool writes it (docs/session-format.md), with one thing wrong."""
    taps = _raw([20e6], 0).taps[None] if taps is None else taps
    cam = json.loads(CAM.to_json()) if camera is None else camera
    with h5py.File(path, "w") as f:
        f.attrs.update(format="tofhil.session", format_version=1, device="{}", scene="",
                       camera=json.dumps(cam), n_frames=taps.shape[0])
        f.attrs.update(attrs or {})
        f["raw/taps"] = taps
        f["raw/freq_hz"] = np.asarray(freq)
        f["raw/theta_rad"] = THETA if theta is None else np.asarray(theta)
        f["raw"].attrs["integration_time_s"] = 1e-3
        f["raw"].attrs.update(raw_attrs or {})
        f["frames/timestamp_s"] = np.arange(taps.shape[0], dtype="f8")
        f["frames/sequence"] = np.arange(taps.shape[0], dtype="i8")
        for name in drop:
            del f[name]
    return path


SMALL_SCENE = """\
name: small_wall
camera: {width: 40, height: 30, fx: 40.0, fy: 40.0, cx: 19.5, cy: 14.5}
emitter: {offset_m: [0.01, 0.0, 0.0], power_w: 0.3, profile: {type: cos_n, n: 2.0}}
materials: {wall: {reflectance: 0.8}}
objects:
  - {name: wall, type: plane, size: [4.0, 3.0], material: wall, pose: {position: [0.0, 0.0, 1.0]}}
sensor: {taps: 4, theta_deg: [0, 90, 180, 270], freq_hz: [20.0e6], integration_time_s: 0.3e-3,
         frame_period_s: 0.05, conversion_gain_dn_per_e: 0.02, full_well_e: 200000, read_noise_e: 20}
"""


@pytest.fixture(scope="module")
def inputs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("hostile_inputs")
    p: dict[str, Path] = {"dir": d, "subdir": d / "a_directory"}
    p["subdir"].mkdir()
    p["good"] = write_good(d / "good.h5")
    p["existing"] = write_good(d / "existing.h5", n=1)
    (d / "existing.npz").write_bytes(b"recorded calibration")
    p["existing_npz"] = d / "existing.npz"
    p["scene"] = d / "small.yaml"
    p["scene"].write_text(SMALL_SCENE)
    p["text"] = d / "not_hdf5.h5"
    p["text"].write_text("this is not HDF5\n")
    p["empty"] = d / "empty.h5"
    p["empty"].write_bytes(b"")
    good_taps = _raw([20e6], 0).taps[None]
    bad = {
        "freq_zero": dict(freq=(0.0,)),
        "freq_negative": dict(freq=(-20e6,)),
        "freq_nan": dict(freq=(np.nan,)),
        "freq_inf": dict(freq=(np.inf,)),
        "taps_complex": dict(taps=good_taps.astype(np.complex64)),
        "taps_text": dict(taps=np.full((1, 1, 4, 30, 40), b"x", dtype="S1")),
        "two_taps": dict(taps=good_taps[:, :, :2], theta=[0.0, np.pi]),
        "freq_count": dict(freq=(20e6, 40e6)),
        "theta_count": dict(theta=[0.0, 1.0, 2.0]),
        "theta_nan": dict(theta=[0.0, np.nan, np.pi, 4.7]),
        "theta_uneven": dict(theta=[0.0, 0.3, np.pi, 4.7]),
        "taps_shape": dict(taps=good_taps[..., :20]),
        "fx_nan": dict(camera=json.loads(CAM.to_json()) | {"fx": float("nan")}),
        "cx_nan": dict(camera=json.loads(CAM.to_json()) | {"cx": float("nan")}),
        "dist_inf": dict(camera=json.loads(CAM.to_json()) | {"dist": [float("inf"), 0, 0, 0, 0]}),
        "integration_negative": dict(raw_attrs={"integration_time_s": -1.0}),
        "n_frames_negative": dict(attrs={"n_frames": -1}),
        "device_not_object": dict(attrs={"device": "[1, 2]"}),
        "format_missing": dict(attrs={"format": "something.else"}),
        "saturation_nan": dict(raw_attrs={"saturation_dn": np.nan}),
        "no_timestamps": dict(drop=("frames/timestamp_s",)),
    }
    for name, kw in bad.items():
        p[f"bad_{name}"] = write_raw_by_hand(d / f"bad_{name}.h5", **kw)
    return p


MALFORMED = ["text", "empty", "bad_freq_zero", "bad_freq_negative", "bad_freq_nan", "bad_freq_inf",
             "bad_taps_complex", "bad_taps_text", "bad_two_taps", "bad_freq_count", "bad_theta_count",
             "bad_theta_nan", "bad_theta_uneven", "bad_taps_shape", "bad_fx_nan", "bad_cx_nan", "bad_dist_inf",
             "bad_integration_negative", "bad_n_frames_negative", "bad_device_not_object", "bad_format_missing",
             "bad_saturation_nan", "bad_no_timestamps"]
MALFORMED_FAST = {"text", "bad_freq_zero", "bad_freq_nan", "bad_taps_complex", "bad_two_taps", "bad_fx_nan"}
#: The field each malformed session's message must name.
MALFORMED_FIELD = {"bad_freq_zero": "raw/freq_hz", "bad_freq_negative": "raw/freq_hz", "bad_freq_nan": "raw/freq_hz",
                   "bad_freq_inf": "raw/freq_hz", "bad_taps_complex": "raw/taps", "bad_taps_text": "raw/taps",
                   "bad_two_taps": "raw/taps", "bad_freq_count": "raw/freq_hz", "bad_theta_count": "raw/theta_rad",
                   "bad_theta_nan": "raw/theta_rad", "bad_theta_uneven": "raw/theta_rad",
                   "bad_taps_shape": "raw/taps", "bad_fx_nan": "fx", "bad_cx_nan": "cx", "bad_dist_inf": "dist",
                   "bad_integration_negative": "integration_time_s", "bad_n_frames_negative": "n_frames",
                   "bad_device_not_object": "device", "bad_format_missing": "format",
                   "bad_saturation_nan": "saturation_dn", "bad_no_timestamps": "frames/timestamp_s"}


def _snapshot(root: Path) -> dict[str, str]:
    out = {}
    for path in sorted(root.rglob("*")):
        out[str(path.relative_to(root))] = (hashlib.sha256(path.read_bytes()).hexdigest() if path.is_file()
                                            else "dir")
    return out


def assert_refused(res: subprocess.CompletedProcess, *, contains: tuple[str, ...] = ()) -> str:
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert "Traceback" not in res.stderr and "Traceback" not in res.stdout, res.stderr
    assert res.returncode == 2, (res.returncode, res.stderr, res.stdout)
    assert len(lines) == 1, res.stderr
    assert lines[0].startswith("error: "), lines[0]
    for text in contains:
        assert text in lines[0], (text, lines[0])
    return lines[0]


# ------------------------------------------------------------------ the cases, by class
# Each is (id, argv with {placeholders} for fixture paths and {out} for the case's own
# directory, text the message must contain). Outputs go to {out}, which must stay empty.
G = "{good}"
NUMERIC = [
    # simulate
    ("simulate-frames-0", ["simulate", "{scene}", "--out", "{out}/s.h5", "--frames", "0"], "--frames"),
    ("simulate-frames--1", ["simulate", "{scene}", "--out", "{out}/s.h5", "--frames", "-1"], "--frames"),
    ("simulate-frames-1.5", ["simulate", "{scene}", "--out", "{out}/s.h5", "--frames", "1.5"], "--frames"),
    ("simulate-seed--1", ["simulate", "{scene}", "--out", "{out}/s.h5", "--seed", "-1"], "--seed"),
    # a parameter the scene does not declare: named, with the scene's own (it changed nothing before)
    ("simulate-param-unknown", ["simulate", "dark_square", "--out", "{out}/s.h5", "--param", "wal_distance_m=2"],
     "declares no parameter 'wal_distance_m' (expected one of square_reflectance, square_size_m, wall_distance_m"),
    # an analytic wall behind the camera: the error names the scene given
    ("emulate-wall-negative", ["emulate", "--scene", "wall:-1", "--pty"], "in scene 'wall:-1'"),
    ("emulate-wall-text", ["emulate", "--scene", "wall:far", "--pty"], "bad wall distance 'far' in scene 'wall:far'"),
    ("simulate-seed-nan", ["simulate", "{scene}", "--out", "{out}/s.h5", "--seed", "nan"], "--seed"),
    # depth
    *[(f"depth-margin-{v}", ["depth", G, "--out", "{out}/d.h5", "--margin", v], "--margin")
      for v in ("5", "-1", "0", "nan", "inf")],
    *[(f"depth-min-amplitude-{v}", ["depth", G, "--out", "{out}/d.h5", "--min-amplitude", v], "--min-amplitude")
      for v in ("nan", "-1", "inf", "-inf")],
    # correct: every numeric parameter (METHOD:key=value, checked in the library) and option
    *[(f"correct-{method}-{key}-{v}",
       ["correct", G, "--method", f"{method}:" + ",".join([f"{key}={v}"] + [p for p in rest if not p.startswith(key + "=")]),
        "--out", "{out}/c.h5"], f"{method}:{key}")
      for method, key, values, rest in (
          ("uniform", "w", ("nan", "-1", "5"), ()),
          ("gaussian-inverse", "sigma_h", ("-1", "nan"), ("sigma_v=5", "w=0.01")),
          ("gaussian-inverse", "sigma_v", ("0", "inf"), ("sigma_h=5", "w=0.01")),
          ("gaussian-inverse", "mu", ("-1",), ("sigma_h=5", "sigma_v=5", "w=0.01")),
          ("amplitude", "min_amplitude", ("nan", "-1"), ()),
          ("jump-angle", "angle_deg", ("500", "-10", "nan"), ()),
          ("jump-distance", "max_step_m", ("-1", "nan"), ()), ("jump-distance", "relative", ("nan", "-0.5"), ()),
          ("smooth-gaussian", "sigma_px", ("-1", "nan"), ()), ("smooth-bilateral", "sigma_m", ("0", "-0.03"), ()),
          ("smooth-median", "size", ("4", "0", "-3", "100001"), ()))
      for v in values],
    *[(f"correct-target-threshold-{v}", ["correct", G, "--method", "psf", "--calibrate", G, "--out", "{out}/c.h5",
                                         "--target-threshold", v], "--target-threshold") for v in ("2", "nan")],
    *[(f"correct-min-amplitude-{v}", ["correct", G, "--method", "smooth-median", "--out", "{out}/c.h5",
                                      "--min-amplitude", v], "--min-amplitude") for v in ("nan", "-1")],
    # compare
    *[(f"compare-{opt}-{v}", ["compare", G, G, "--out", "{out}/cmp", f"--{opt}", v], f"--{opt}")
      for opt, values in (("threshold", ("-1", "nan", "0")), ("frames", ("0", "-2")), ("cell-size", ("0", "inf")),
                          ("min-amplitude", ("nan",)), ("min-relative-amplitude", ("2", "-1")))
      for v in values],
    # ndt
    *[(f"ndt-{opt}-{v}", ["ndt", G, G, f"--{opt}", v], f"--{opt}")
      for opt, values in (("cell-size", ("nan", "-1", "0")), ("outlier-ratio", ("1", "nan", "0")),
                          ("min-points", ("2", "-1")), ("eig-floor", ("0", "nan")), ("threshold", ("2", "nan")))
      for v in values],
    # capture (refused before any device is opened)
    *[(f"capture-{opt}-{v}", ["capture", "--device", "emulator", "--out", "{out}/cap.h5", f"--{opt}", v], f"--{opt}")
      for opt, values in (("frames", ("0", "-5")), ("integration-time-us", ("-5", "nan", "0")),
                          ("mod-freq-hz", ("0", "nan", "-1e6")), ("channel", ("16", "-1")),
                          ("min-amplitude", ("nan", "-1")))
      for v in values],
    # bench (refused before the device is opened: {out} stays empty)
    *[(f"bench-{proc}-{opt}-{v}", ["bench", proc, "--device", "emulator", "--out", "{out}/b", f"--{opt}", v], f"--{opt}")
      for proc, opt, values in (("accuracy-vs-distance", "frames", ("0", "-2")),
                                ("accuracy-vs-distance", "distances", ("nan", "-1", "0,1", "inf")),
                                ("ambient", "levels", ("nan", "-1", "inf")), ("dark-squares", "levels", ("0",)),
                                ("interference", "levels", ("0", "nan", "-0.1", "0.1,0.2", "inf")),
                                ("warm-up", "captures", ("1",)), ("warm-up", "interval-s", ("-1", "nan")),
                                ("flatness", "roi", ("1,1,1,1", "a,b,c,d")))
      for v in values],
    # emulate, diagnose, demo, import (--max-effects 0 is allowed: it says that nothing was searched)
    *[(f"emulate-{opt}-{v}", ["emulate", "--pty", f"--{opt}", v], f"--{opt}")
      for opt, values in (("frame-rate", ("-1", "nan", "inf")), ("seed", ("-1",))) for v in values],
    *[(f"diagnose-max-effects-{v}", ["diagnose", G, "--scene", "{scene}", "--out", "{out}/dg", "--max-effects", v],
       "--max-effects") for v in ("nan", "-1")],
    *[(f"demo-frames-{v}", ["demo", "--out", "{out}/demo", "--frames", v], "--frames") for v in ("1", "nan", "0")],
    *[(f"import-adi-max-confidence-{v}", ["import", G, "--out", "{out}/i.h5", "--adi-max-confidence", v],
       "--adi-max-confidence") for v in ("-1", "256")],
]

PATHS = [
    # missing inputs: named, with 'no such file'
    *[(f"missing-{cmd[0]}", cmd, "no such file") for cmd in (
        ["info", "{dir}/missing.h5"], ["depth", "{dir}/missing.h5", "--out", "{out}/d.h5"],
        ["correct", "{dir}/missing.h5", "--method", "smooth-median", "--out", "{out}/c.h5"],
        ["compare", "{dir}/missing.h5", G, "--out", "{out}/cmp"],
        ["diagnose", "{dir}/missing.h5", "--scene", "{scene}", "--out", "{out}/dg"],
        ["calibrate-taps", "--flat", "{dir}/missing.h5", "--out", "{out}/cal.npz"],
        ["import", "{dir}/missing.bin", "--out", "{out}/i.h5"])],
    # a directory where a file is expected: 'is a directory', never 'no such file'
    *[(f"dir-as-input-{cmd[0]}", cmd, "is a directory") for cmd in (
        ["info", "{subdir}"], ["depth", "{subdir}", "--out", "{out}/d.h5"],
        ["compare", G, "{subdir}", "--out", "{out}/cmp"], ["calibrate-taps", "--flat", "{subdir}", "--out", "{out}/c"],
        ["import", "{subdir}", "--out", "{out}/i.h5"],
        ["correct", G, "--method", "psf:psf={subdir}", "--out", "{out}/c.h5"])],
    # --out a directory where a file is expected
    *[(f"dir-as-output-{cmd[0]}", cmd, "is a directory") for cmd in (
        ["depth", G, "--out", "{subdir}"], ["simulate", "{scene}", "--out", "{subdir}"],
        ["correct", G, "--method", "smooth-median", "--out", "{subdir}"], ["import", G, "--out", "{subdir}"],
        ["calibrate-taps", "--flat", G, "--out", "{subdir}"],
        ["capture", "--device", "emulator", "--out", "{subdir}"])],
    # --out an existing file where a directory is expected
    *[(f"file-as-outdir-{cmd[0]}", cmd, "is a file") for cmd in (
        ["compare", G, G, "--out", "{existing}"], ["diagnose", G, "--scene", "{scene}", "--out", "{existing}"],
        ["demo", "--out", "{existing}"])],
    # an existing output without --force
    *[(f"exists-{cmd[0]}", cmd, "already exists") for cmd in (
        ["depth", G, "--out", "{existing}"], ["simulate", "{scene}", "--out", "{existing}"],
        ["correct", G, "--method", "smooth-median", "--out", "{existing}"], ["import", G, "--out", "{existing}"],
        ["calibrate-taps", "--flat", G, "--out", "{existing_npz}"],
        ["capture", "--device", "emulator", "--out", "{existing}", "--frames", "1"])],
    ("exists-calibrate-taps-no-suffix", ["calibrate-taps", "--flat", G, "--out", "{dir}/existing"], "existing.npz"),
    # unwritable output locations: sysfs, a device, a missing directory
    *[(f"unwritable-{cmd[0]}", cmd, "/sys") for cmd in (
        ["depth", G, "--out", "/sys/x.h5"], ["simulate", "{scene}", "--out", "/sys/x.h5"],
        ["correct", G, "--method", "smooth-median", "--out", "/sys/x.h5"], ["import", G, "--out", "/sys/x.h5"],
        ["calibrate-taps", "--flat", G, "--out", "/sys/x.npz"], ["compare", G, G, "--out", "/sys/x"],
        ["diagnose", G, "--scene", "{scene}", "--out", "/sys/x"], ["demo", "--out", "/sys/x"],
        ["capture", "--device", "emulator", "--out", "/sys/x.h5"])],
    *[(f"device-{cmd[0]}", cmd, "/dev/full") for cmd in (
        ["depth", G, "--out", "/dev/full", "--force"], ["simulate", "{scene}", "--out", "/dev/full", "--force"],
        ["correct", G, "--method", "smooth-median", "--out", "/dev/full", "--force"])],
    ("no-such-dir-depth", ["depth", G, "--out", "{out}/no/such/dir/d.h5"], "does not exist"),
    # rich markup and emoji codes in names print literally
    ("markup-slash", ["info", "{dir}/x[/].h5"], "x[/].h5"),
    ("markup-bold-red", ["info", "{dir}/[bold red]alarm.h5"], "[bold red]alarm.h5"),
    ("markup-emoji", ["info", "{dir}/\U0001F600:smile:.h5"], "\U0001F600:smile:.h5"),
    ("markup-out", ["depth", G, "--out", "{out}/no[/]dir/[red]x.h5"], "no[/]dir"),
    # usage slips
    ("unknown-option", ["depth", G, "--out", "{out}/d.h5", "--bogus"], "--bogus"),
    ("missing-out", ["depth", G], "--out"),
    ("unknown-command", ["frobnicate"], "frobnicate"),
]

SCENE_HELPER = [  # the scene helper's cases: expected to pass once that branch is merged
    ("scene-nan-size", "objects:\n  - {name: wall, type: plane, size: [.nan, 3.0], material: wall, "
                       "pose: {position: [0.0, 0.0, 1.0]}}\n"),
    ("scene-div-zero", "params: {d: 1.0}\nobjects:\n  - {name: wall, type: plane, size: [4.0, 3.0], material: wall, "
                       "pose: {position: [0.0, 0.0, '${1/0}']}}\n"),
    ("scene-huge-power", "params: {d: 1.0}\nobjects:\n  - {name: wall, type: plane, size: [4.0, 3.0], "
                         "material: wall, pose: {position: [0.0, 0.0, '${9**9**9}']}}\n"),
    ("scene-huge-camera", "camera: {width: 20000, height: 20000, fx: 40.0, fy: 40.0, cx: 19.5, cy: 14.5}\n"),
]


def _fill(argv: list[str], inputs: dict[str, Path], out: Path) -> list[str]:
    """Replace ``{name}`` placeholders (plain replacement: markup brackets stay as typed)."""
    names = {k: str(v) for k, v in inputs.items()} | {"out": str(out)}
    filled = []
    for arg in argv:
        for key, value in names.items():
            arg = arg.replace("{" + key + "}", value)
        filled.append(arg)
    return filled


def _params(cases: list[tuple], group) -> list:
    """The first case of each group runs always; the rest of the matrix is marked slow, so
    that the default run of this module stays short on a shared machine."""
    seen: set[str] = set()
    out = []
    for case in cases:
        key = group(case)
        out.append(pytest.param(case[1], case[2], id=case[0], marks=(pytest.mark.slow,) if key in seen else ()))
        seen.add(key)
    return out


def _check_case(argv: list[str], expect: str, inputs: dict[str, Path], tmp_path: Path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    before = _snapshot(inputs["dir"])
    res = run(*_fill(argv, inputs, out), cwd=out)
    line = assert_refused(res, contains=(expect,) if expect else ())
    assert _snapshot(inputs["dir"]) == before, f"an input changed: {line}"
    assert list(out.iterdir()) == [], f"left behind: {list(out.iterdir())}"


@pytest.mark.parametrize("argv, expect", _params(NUMERIC, lambda c: c[1][0]))
def test_out_of_range_numbers_are_one_line(argv: list[str], expect: str, inputs: dict[str, Path],
                                           tmp_path: Path) -> None:
    _check_case(argv, expect, inputs, tmp_path)


@pytest.mark.parametrize("argv, expect", _params(PATHS, lambda c: c[0].rsplit("-", 1)[0]))
def test_bad_paths_are_one_line(argv: list[str], expect: str, inputs: dict[str, Path], tmp_path: Path) -> None:
    _check_case(argv, expect, inputs, tmp_path)


@pytest.mark.parametrize("name", [n if n in MALFORMED_FAST else pytest.param(n, marks=pytest.mark.slow)
                                  for n in MALFORMED])
@pytest.mark.parametrize("command", ["depth", pytest.param("info", marks=pytest.mark.slow)])
def test_malformed_sessions_name_file_and_field(name: str, command: str, inputs: dict[str, Path],
                                                tmp_path: Path) -> None:
    argv = ["info", f"{{{name}}}"] if command == "info" else ["depth", f"{{{name}}}", "--out", "{out}/d.h5"]
    out = tmp_path / "out"
    out.mkdir()
    before = _snapshot(inputs["dir"])
    res = run(*_fill(argv, inputs, out), cwd=out)
    line = assert_refused(res, contains=(inputs[name].name,))
    if name in MALFORMED_FIELD:
        assert MALFORMED_FIELD[name] in line, line
    assert _snapshot(inputs["dir"]) == before
    assert list(out.iterdir()) == []  # the failed depth left no empty output behind


def test_disk_full_mid_write_leaves_nothing(inputs: dict[str, Path], tmp_path: Path) -> None:
    """A file-size limit below one session (EFBIG, as ENOSPC on a full disk): the derived
    output fails with one line naming it, and neither it nor its temporary file remains."""
    for argv in (["depth", inputs["good"], "--out", "d.h5"], ["simulate", inputs["scene"], "--out", "s.h5"],
                 ["correct", inputs["good"], "--method", "smooth-median", "--out", "c.h5"]):
        out = tmp_path / argv[0]
        out.mkdir()
        # the same command once without the limit first: numba writes its compiled kernels to its
        # cache on the first run, and this test is about the output, not the cache
        warm = tmp_path / f"warm-{argv[0]}"
        warm.mkdir()
        assert run(*argv, cwd=warm).returncode == 0
        res = run(*argv, cwd=out, fsize=20_000)
        assert_refused(res, contains=(str(argv[-1]), "cannot be written"))
        assert list(out.iterdir()) == []


def test_existing_output_survives_failed_forced_rewrite(inputs: dict[str, Path], tmp_path: Path) -> None:
    """--force over an existing file that then fails (disk full) keeps the old file intact."""
    target = tmp_path / "keep.h5"
    write_good(target, n=1)
    digest = hashlib.sha256(target.read_bytes()).hexdigest()
    res = run("depth", inputs["good"], "--out", target, "--force", cwd=tmp_path, fsize=20_000)
    assert_refused(res, contains=("keep.h5",))
    assert hashlib.sha256(target.read_bytes()).hexdigest() == digest
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.h5"]


def test_markup_in_names_prints_literally_in_normal_output(inputs: dict[str, Path], tmp_path: Path) -> None:
    name = "[bold red]x \U0001F600 :smile:.h5"
    res = run("depth", inputs["good"], "--out", name, cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert name in res.stdout.replace("\n", "")
    res = run("info", name, cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert name in res.stdout.replace("\n", "")


def test_interrupted_simulate_keeps_completed_frames(inputs: dict[str, Path], tmp_path: Path) -> None:
    """Ctrl-C during a long simulate: 'interrupted: N frames kept in FILE', and FILE opens
    with N frames."""
    from tofhil.session import open_session

    proc = subprocess.Popen([sys.executable, "-m", "tofhil.cli", "simulate", str(inputs["scene"]), "--out", "s.h5",
                             "--frames", "1000000"], cwd=tmp_path, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, preexec_fn=_limits)
    try:
        deadline = time.monotonic() + 90
        while time.monotonic() < deadline:  # until a few frames (about 40 kB each) are in the file
            partial = [p for p in tmp_path.iterdir() if p.name.endswith(".partial")]
            if partial and partial[0].stat().st_size > 200_000:
                break
            time.sleep(0.1)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("interrupted: ") and "s.h5" in lines[0], err
    n = int(lines[0].split()[1])
    assert n > 0
    with open_session(tmp_path / "s.h5") as s:
        assert s.n_frames == n
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.h5"]


@pytest.mark.parametrize("case, body", [pytest.param(*c, id=c[0], marks=(pytest.mark.slow,) if "huge" in c[0] else ())
                                        for c in SCENE_HELPER])
def test_scene_file_hostile_values(case: str, body: str, inputs: dict[str, Path], tmp_path: Path) -> None:
    base = {k: v for k, v in __import__("yaml").safe_load(SMALL_SCENE).items()}
    extra = __import__("yaml").safe_load(body)
    scene = tmp_path / f"{case}.yaml"
    scene.write_text(__import__("yaml").safe_dump(base | extra))
    out = tmp_path / "out"
    out.mkdir()
    res = run("simulate", scene, "--out", "s.h5", cwd=out, timeout=120)
    assert_refused(res)
    assert list(out.iterdir()) == []


def test_non_utf8_scene(tmp_path: Path) -> None:
    scene = tmp_path / "latin1.yaml"
    scene.write_bytes(SMALL_SCENE.replace("small_wall", "sm\xe4ll").encode("latin-1"))
    out = tmp_path / "out"
    out.mkdir()
    res = run("simulate", scene, "--out", "s.h5", cwd=out, timeout=120)
    assert_refused(res, contains=("latin1.yaml",))
