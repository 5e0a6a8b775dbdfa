"""The view (Rerun): a capture with ``--save`` and ``tofhil view`` write ``.rrd`` files that the
Rerun SDK reads back with the entities and frames expected; the residual against the twin is
measured - twin; a slow viewer drops view frames, never camera frames; a missing extra or a
bad ``--save`` is one line and leaves nothing behind. Small frames, few of them."""

from __future__ import annotations

import math
import sys
import threading
from pathlib import Path

import h5py
import numpy as np
import pytest

from tests.cli_in_process import run_cli
from tofhil.app import view as V
from tofhil.app.view_sink import DroppingSink
from tofhil.depth import depth_from_raw
from tofhil.session import open_session

rr = pytest.importorskip("rerun")  # the test extra installs it (pyproject: test includes rerun-sdk)


# --------------------------------------------------------------------------- reading an .rrd back
def read_rrd(path: Path) -> dict[str, dict]:
    """``{entity: {"static": {component: value}, "frames": {frame index: {component: value}}}}``
    from the chunks of an .rrd file (Rerun's own reader); images decoded to numpy arrays."""
    from rerun.chunk import RrdReader

    out: dict[str, dict] = {}
    for chunk in RrdReader(path).store().stream():
        batch = chunk.to_record_batch()
        entity = chunk.entity_path.lstrip("/")
        e = out.setdefault(entity, {"static": {}, "frames": {}})
        names = [n for n in batch.schema.names if ":" in n]
        rows = batch.to_pylist()
        for row in rows:
            values = {n: row[n] for n in names if row[n] is not None}
            if chunk.is_static:
                e["static"].update(values)
            else:
                e["frames"].setdefault(row["frame"], {}).update(values)
    return out


def image(values: dict, kind: str = "Image") -> np.ndarray:
    """A logged image (``Image`` or ``DepthImage``) as an array of its own type and shape."""
    fmt = values[f"{kind}:format"][0]
    dtype = {"U8": np.uint8, "F32": np.float32, "F64": np.float64, "U16": np.uint16}[
        rr.ChannelDatatype(fmt["channel_datatype"]).name]
    channels = {None: 1, 1: 1, 2: 3, 3: 4}[fmt.get("color_model")]
    buf = np.frombuffer(bytes(values[f"{kind}:buffer"][0]), dtype=dtype)
    shape = (fmt["height"], fmt["width"]) + ((channels,) if channels > 1 else ())
    return buf.reshape(shape)


# --------------------------------------------------------------------------- capture --save
def test_capture_with_save_writes_the_viewed_frames_as_rrd(tmp_path: Path, capsys) -> None:
    """``tofhil capture --device emulator --save V.rrd --scene wall``: every camera frame in the
    session, the frames the view took in the .rrd under their session index, with the twin
    (rendered on the viewer thread for the capture's camera) and the live residual."""
    session, rrd = tmp_path / "s.h5", tmp_path / "v.rrd"
    n = 6
    code = run_cli("capture", "--device", "emulator:wall:1.2", "--frames", n, "--out", session, "--save", rrd,
                   "--view-rate", "0", "--mode", "dcs", "--scene", "wall")
    out = capsys.readouterr().out
    assert code == 0, out
    line = next(ln for ln in out.splitlines() if ln.startswith("view dropped"))
    dropped = int(line.split()[2])
    assert line.startswith(f"view dropped {dropped} of {n} frames -> ") and line.endswith("v.rrd")
    data = read_rrd(rrd)
    assert {V.DEPTH, V.AMPLITUDE, V.POINTS, V.CAMERA, V.INFO, "world", V.TWIN_DEPTH, V.TWIN_POINTS, V.RESIDUAL} <= set(data)
    shown = sorted(data[V.DEPTH]["frames"])
    assert len(shown) == n - dropped >= 1 and set(shown) <= set(range(n))
    assert sorted(data[V.POINTS]["frames"]) == shown == sorted(data[V.AMPLITUDE]["frames"])
    # the twin is rendered before the first view frame is logged (frames arriving meanwhile are dropped)
    assert sorted(data[V.RESIDUAL]["frames"]) == shown
    pinhole = data[V.CAMERA]["static"]
    twin = image(data[V.TWIN_DEPTH]["static"], "DepthImage")
    with open_session(session) as s:
        assert s.n_frames == n  # every camera frame is in the session
        cam = s.camera
        assert pinhole["Pinhole:resolution"][0] == [cam.width, cam.height] and twin.shape == cam.shape
        for i in shown:  # view frame i is session frame i, demodulated by the core
            d = depth_from_raw(s.raw_frame(i))
            logged = image(data[V.DEPTH]["frames"][i], "DepthImage")
            ok = cam.valid_mask(d.radial_m, d.valid)
            # (to a float32 ulp: the fused kernel's vector loop may round the live frame's taps
            # differently from the same values read back from the file)
            np.testing.assert_allclose(logged[ok], d.radial_m[ok], rtol=3e-7)
            assert (logged[~ok] == 0).all()
            pts = np.asarray(data[V.POINTS]["frames"][i]["Points3D:positions"], dtype=np.float32)
            np.testing.assert_allclose(pts, d.points(), atol=1e-5)  # unprojected with the camera's rays
            np.testing.assert_allclose(image(data[V.AMPLITUDE]["frames"][i]), d.amplitude, rtol=3e-7)
            res = image(data[V.RESIDUAL]["frames"][i])
            both = ok & (twin > 0)
            assert both.sum() > 0.9 * both.size
            np.testing.assert_allclose(res[both], logged[both].astype(np.float64) - twin[both], atol=1e-6)
    assert list(tmp_path.glob(".*partial")) == []


# --------------------------------------------------------------------------- tofhil view --scene
@pytest.fixture(scope="module")
def small_session(tmp_path_factory) -> Path:
    """Three depth frames of a 32 x 24 camera, written directly (no renderer)."""
    from tofhil.camera import CameraModel
    from tofhil.frames import DepthFrame
    from tofhil.session import SessionWriter

    cam = CameraModel.from_fov(32, 24, 60.0)
    path = tmp_path_factory.mktemp("small") / "small.h5"
    with SessionWriter(path, cam, device={"model": "synthetic"}) as w:
        for i in range(3):
            w.append(depth=DepthFrame(distance_m=np.full(cam.shape, 1.0 + 0.1 * i, np.float32), kind="radial",
                                      camera=cam, amplitude=np.full(cam.shape, 300.0, np.float32), sequence=i,
                                      timestamp_s=0.05 * i))
    return path


@pytest.fixture(scope="module")
def wall_session(tmp_path_factory) -> Path:
    from tofhil.sim.pipeline import simulate_session
    from tofhil.sim.scene import load_scene

    return simulate_session(load_scene("wall"), tmp_path_factory.mktemp("view") / "wall.h5", frames=2, seed=7)


def test_view_of_a_session_with_a_scene_logs_the_twin_and_the_residual(wall_session: Path, tmp_path: Path,
                                                                        capsys) -> None:
    rrd = tmp_path / "w.rrd"
    code = run_cli("view", wall_session, "--scene", "wall", "--save", rrd)
    out = capsys.readouterr().out
    assert code == 0, out
    assert "logged 2 frame(s)" in out and "twin: wall" in out
    data = read_rrd(rrd)
    assert {V.TWIN_DEPTH, V.TWIN_AMPLITUDE, V.TWIN_POINTS, V.RESIDUAL, V.RESIDUAL_COLOR, V.RESIDUAL_RMSE} <= set(data)
    assert data[V.TWIN_DEPTH]["frames"] == {} and sorted(data[V.RESIDUAL]["frames"]) == [0, 1]  # twin static
    twin = image(data[V.TWIN_DEPTH]["static"], "DepthImage").astype(np.float64)
    with h5py.File(wall_session, "r") as f:  # the session's own depth, read without tofhil
        measured = f["depth/radial_m"][:2].astype(np.float64)
        valid = f["depth/valid"][:2].astype(bool)
    h, w = twin.shape
    pixels = [(h // 2, w // 2), (3, 5), (h - 4, w - 7), (h // 3, 2 * w // 3)]
    for i in (0, 1):
        res = image(data[V.RESIDUAL]["frames"][i]).astype(np.float64)
        for y, x in pixels:
            assert valid[i, y, x] and twin[y, x] > 0
            assert res[y, x] == pytest.approx(measured[i, y, x] - twin[y, x], abs=1e-6)
        assert np.isnan(res[~valid[i]]).all()
        assert abs(np.nanmedian(res)) < 0.01  # a wall against its own twin: noise only
        rmse = data[V.RESIDUAL_RMSE]["frames"][i]["Scalars:scalars"][0]
        assert rmse == pytest.approx(1e3 * math.sqrt(np.nanmean(res ** 2)), rel=1e-4)
    assert "twin" in data[V.INFO]["static"]["TextDocument:text"][0]


def test_a_view_that_fails_midway_leaves_no_file(small_session: Path, tmp_path: Path, monkeypatch) -> None:
    rrd = tmp_path / "w.rrd"
    real = V.RerunView.log_frame

    def fail_on_second(self, index, raw=None, depth=None):
        if index == 1:
            raise RuntimeError("viewer gone")
        return real(self, index, raw=raw, depth=depth)

    monkeypatch.setattr(V.RerunView, "log_frame", fail_on_second)
    with pytest.raises(RuntimeError):
        V.view_session(small_session, save=rrd)
    assert list(tmp_path.iterdir()) == []  # neither the file nor its temporary name


# --------------------------------------------------------------------------- the capture never waits
def test_a_slow_viewer_drops_view_frames_never_camera_frames(tmp_path: Path, monkeypatch) -> None:
    from tests.drivers.test_capture import device
    from tofhil.drivers.base import CaptureSettings
    from tofhil.drivers.capture import capture

    release = threading.Event()
    real = V.LiveView._show

    def slow_show(self, item):  # a viewer that is stuck until the capture has ended
        release.wait(30)
        real(self, item)

    monkeypatch.setattr(V.LiveView, "_show", slow_show)
    live = V.LiveView(save=tmp_path / "v.rrd", max_rate_hz=None)
    n = 12
    with device(1.0) as dev:
        summary = capture(dev, tmp_path / "s.h5", n, CaptureSettings(mode="dcs"), on_frame=live.offer)
    release.set()  # the capture finished with the viewer stuck on its first frame
    view = live.close()
    assert summary.frames_written == n and summary.ended_early is None
    with open_session(tmp_path / "s.h5") as s:
        assert s.n_frames == n
    # one frame in the viewer's hands, two queued: the rest dropped, none waited for
    assert view.offered == n and view.shown in (2, 3) and view.dropped == n - view.shown
    assert view.line() == f"view dropped {n - view.shown} of {n} frames -> {tmp_path / 'v.rrd'}"
    data = read_rrd(tmp_path / "v.rrd")
    assert len(data[V.DEPTH]["frames"]) == view.shown
    assert not {V.TWIN_DEPTH, V.RESIDUAL} & set(data)  # no scene: no twin


def test_the_sink_never_blocks_and_stops_on_a_failing_consumer() -> None:
    gate = threading.Event()
    seen: list[int] = []
    sink: DroppingSink[int] = DroppingSink(lambda i: (gate.wait(30), seen.append(i)), maxsize=2)
    accepted = [sink.offer(i) for i in range(50)]  # a stuck consumer: every offer returns at once
    gate.set()
    stats = sink.close()
    assert stats.offered == 50 and stats.consumed == len(seen) in (2, 3) and stats.dropped == 50 - len(seen)
    assert sum(accepted) == len(seen) and seen == sorted(seen) and not stats.timed_out

    def boom(i: int) -> None:
        raise ValueError(f"viewer closed at {i}")

    failing: DroppingSink[int] = DroppingSink(boom)
    failing.offer(0)
    stats = failing.close()
    assert stats.consumed == 0 and stats.error == "ValueError: viewer closed at 0"
    assert failing.offer(1) is False  # closed: dropped, never raises


# --------------------------------------------------------------------------- bad input
def test_missing_rerun_names_the_extra_and_writes_nothing(small_session: Path, tmp_path: Path, monkeypatch,
                                                          capsys) -> None:
    monkeypatch.setitem(sys.modules, "rerun", None)  # as if rerun-sdk were not installed
    for argv in (["view", small_session, "--save", tmp_path / "v.rrd"],
                 ["capture", "--device", "emulator:wall:1.0", "--frames", 1, "--out", tmp_path / "s.h5",
                  "--save", tmp_path / "v.rrd"],
                 ["capture", "--device", "emulator:wall:1.0", "--frames", 1, "--out", tmp_path / "s.h5", "--view"]):
        assert run_cli(*argv) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "pip install 'tofhil[view]'" in err and "Traceback" not in err
    assert list(tmp_path.iterdir()) == []  # refused before the device was touched


@pytest.mark.parametrize("case", ["exists", "suffix", "scene-without-view", "same-as-session", "no-display"])
def test_bad_view_options_are_one_line(case: str, small_session: Path, tmp_path: Path, capsys, monkeypatch) -> None:
    for var in ("DISPLAY", "WAYLAND_DISPLAY"):  # a headless machine: the viewer cannot be spawned
        monkeypatch.delenv(var, raising=False)
    existing = tmp_path / "old.rrd"
    existing.write_bytes(b"keep me")
    cap = ["capture", "--device", "emulator:wall:1.0", "--frames", 1, "--out", tmp_path / "s.h5"]
    argv, expect = {
        "exists": (["view", small_session, "--save", existing], "--force"),
        "suffix": (cap + ["--save", tmp_path / "v.txt"], ".rrd"),
        "scene-without-view": (cap + ["--scene", "wall"], "--scene"),
        "same-as-session": (["capture", "--device", "emulator:wall:1.0", "--out", tmp_path / "x.rrd",
                             "--save", tmp_path / "x.rrd"], "--save"),
        "no-display": (cap + ["--view"], "--save VIEW.rrd"),
    }[case]
    assert run_cli(*argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and expect in err and "Traceback" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["old.rrd"] and existing.read_bytes() == b"keep me"


# --------------------------------------------------------------------------- a diagnosis's maps
def test_diagnosis_maps_are_written_as_images_that_read_back(tmp_path: Path) -> None:
    """Each map as its float values (NaN kept) and a depth map also in colour; a 3-d array is
    not a map and is left out."""
    rng = np.random.default_rng(3)
    depth = rng.normal(0, 0.01, (12, 16))
    depth[0, 0] = np.nan
    maps = {"depth_residual_after": depth, "amplitude_residual_before": rng.normal(0, 1, (12, 16)),
            "stack": np.zeros((2, 12, 16))}
    rrd = tmp_path / "d.rrd"
    logged = V.log_diagnosis_maps(maps, rrd, verdict="explained by x")
    assert logged == ["diagnosis/amplitude_residual_before/values", "diagnosis/depth_residual_after/values",
                      "diagnosis/depth_residual_after/colour"]
    got = read_rrd(rrd)
    values = image(got["diagnosis/depth_residual_after/values"]["static"])
    np.testing.assert_array_equal(values, depth.astype(np.float32))   # NaN where the map has none
    colour = image(got["diagnosis/depth_residual_after/colour"]["static"])
    assert colour.shape == (12, 16, 3) and (colour[0, 0] == 0).all()   # black without a value
    assert "diagnosis/stack/values" not in got
    assert not list(tmp_path.glob(".*"))                                 # no partial file left
