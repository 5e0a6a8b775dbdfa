"""DepthAI driver through a host-only pipeline: real depthai queues and ImgFrames, no device.

The host node renders a plane (closed form) and sends ToF-shaped ImgFrames; the driver's
decoding, pairing, unit and depth-kind handling are checked against the plane's geometry.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip("depthai")

from tofhil import C_M_PER_S  # noqa: E402
from tofhil.camera import load_camera_preset  # noqa: E402
from tofhil.drivers.base import CaptureSettings, DeviceError, create_driver, open_device  # noqa: E402
from tofhil.drivers.depthai.driver import DepthAIToF, SequencePairer, ToFSettings  # noqa: E402
from tofhil.sim.sources import PlaneScene  # noqa: E402
from tofhil.errors import TofhilError  # noqa: E402
from tofhil.session import SessionWriter, open_session  # noqa: E402

#: A quarter-resolution OAK ToF camera keeps the tests fast.
CAM = load_camera_preset("oak_tof_33d").scaled(0.25)


def capture(scene: PlaneScene, n: int, **extra) -> tuple[list, DepthAIToF]:
    dev = DepthAIToF("depthai-sim", host_scene=scene, camera=CAM)
    with dev:
        dev.configure(CaptureSettings(mode="distance", extra=extra))
        frames = list(dev.stream(n, timeout_s=5.0))
    return frames, dev


def test_plane_distance_survives_the_queues_in_millimetres():
    d0 = 1.37
    frames, dev = capture(PlaneScene(distance_m=d0), 4)
    expected = d0 / CAM.ray_z  # radial distance to a fronto-parallel plane
    for f in frames:
        assert f.depth.kind == "radial" and f.depth.distance_m.shape == CAM.shape
        # RAW16 carries whole millimetres: rounding error at most 0.5 mm.
        assert np.max(np.abs(f.depth.distance_m - expected)) <= 0.5e-3 + 1e-6
        assert f.depth.valid.all()
    assert dev.stats.dropped == 0 and dev.unmatched == 0


def test_optical_correction_z_map_is_converted_back_to_radial():
    d0, tilt = 0.9, 20.0
    radial_frames, _ = capture(PlaneScene(distance_m=d0, tilt_deg=tilt), 2)
    z_frames, _ = capture(PlaneScene(distance_m=d0, tilt_deg=tilt), 2, enable_optical_correction=True)
    # Independent closed form for a plane tilted about x: n = (0, sin t, cos t), d = d0 / (n . ray).
    t = math.radians(tilt)
    expected = d0 / (CAM.rays[..., 1] * math.sin(t) + CAM.rays[..., 2] * math.cos(t))
    for f in radial_frames + z_frames:
        assert np.max(np.abs(f.depth.radial_m - expected)) < 1.0e-3
    assert z_frames[0].depth.meta["depth_kind_on_wire"] == "z"
    # The points lie on the plane either way.
    n = np.array([0.0, math.sin(t), math.cos(t)])
    assert np.max(np.abs(z_frames[0].depth.points() @ n - d0)) < 1.0e-3


def test_outputs_are_paired_by_sequence_and_timestamps_are_device_seconds():
    scene = PlaneScene(distance_m=1.0, fps=25.0)
    frames, dev = capture(scene, 5, outputs="depth,amplitude,intensity,phase")
    seqs = [f.sequence for f in frames]
    assert seqs == list(range(5))
    dt = np.diff([f.timestamp_s for f in frames])
    np.testing.assert_allclose(dt, 1.0 / scene.fps, atol=2e-6)  # device clock at the frame rate
    f = frames[0]
    # Beam, inverse-square law and cos^4: the corner pixel is dimmer than the centre by the closed form.
    amp = f.depth.amplitude
    c = (CAM.height // 2, CAM.width // 2)
    ratio = amp[0, 0] / amp[c]
    rz0, rzc = CAM.ray_z[0, 0], CAM.ray_z[c]
    # cos^n beam (n = 1) * cos_inc * cos^4 / d^2, d = d0/rz
    closed = (rz0 * rz0 * rz0 ** 4 * rz0 ** 2) / (rzc * rzc * rzc ** 4 * rzc ** 2)
    assert abs(ratio - closed) < 0.01
    np.testing.assert_allclose(f.depth.intensity - amp, scene.ambient, atol=1.0)
    # The phase output: wrapped 80 MHz phase of the round trip 2d.
    phase = f.images["phase"]
    expected = np.mod(4 * np.pi * 80e6 * f.depth.radial_m / C_M_PER_S, 2 * np.pi)
    err = np.angle(np.exp(1j * (phase - expected)))
    assert np.max(np.abs(err)) < 4 * np.pi * 80e6 * 0.6e-3 / C_M_PER_S  # within the mm rounding


def test_a_missing_output_drops_that_frame_and_counts_it():
    frames, dev = capture(PlaneScene(distance_m=1.0, drop_amplitude_of=(2, 3)), 5)
    assert [f.sequence for f in frames] == [0, 1, 4, 5, 6]
    assert dev.stats.dropped == 2 and dev.unmatched == 2
    assert any("sequence 2 lacks amplitude" in e for e in dev.stats.events)


def test_pairer_never_mixes_sequences():
    drops: list[tuple[int, list[str]]] = []
    p = SequencePairer(("depth", "amplitude"), lambda s, m: drops.append((s, m)))
    p.add("depth", 1, "d1")
    p.add("depth", 2, "d2")
    p.add("amplitude", 2, "a2")
    assert p.pop() == (2, {"depth": "d2", "amplitude": "a2"}) and drops == [(1, ["amplitude"])]
    assert p.pop() is None


def test_capture_to_a_session_through_the_registry(tmp_path):
    out = tmp_path / "s.h5"
    with open_device("depthai-sim:1.5") as dev:
        dev.configure(mode="distance")
        with SessionWriter(out, dev.camera, device=dev.info().to_dict()) as w:
            for f in dev.stream(3, timeout_s=5.0):
                w.append(depth=f.depth)
    with open_session(out) as s:
        assert s.n_frames == 3 and s.device["driver"] == "depthai"
        assert s.device["tof_config"]["phase_unwrapping_level"] == 4
        d = s.depth_frame(2)
        assert d.sequence == 2 and d.timestamp_s > 0
        np.testing.assert_allclose(d.z_m[d.valid], 1.5, atol=0.6e-3)


def test_bad_settings_are_refused_with_the_field():
    dev = create_driver("depthai-sim")
    with dev:
        with pytest.raises(DeviceError, match="mode 'dcs'"):
            dev.configure(CaptureSettings(mode="dcs"))
        with pytest.raises(DeviceError, match="phase_unwrapping_level"):
            dev.configure(CaptureSettings(mode="distance", extra={"phase_unwrapping_level": 9}))
        with pytest.raises(DeviceError, match="unknown DepthAI option"):
            dev.configure(CaptureSettings(mode="distance", extra={"bogus": 1}))
        with pytest.raises(DeviceError, match="integration_time_s"):
            dev.configure(CaptureSettings(mode="distance", integration_time_s=1e-3))
    with pytest.raises(DeviceError, match="DISTANCE_M"):
        create_driver("depthai-sim:-1")
    with pytest.raises(TofhilError, match="no_such_scene"):
        open_device("depthai-sim:no_such_scene")


def test_tof_config_carries_the_settings():
    import depthai as dai

    cfg = ToFSettings.from_extra({"phase_unwrapping_level": 2, "median": "5x5",
                                  "enable_optical_correction": True}).to_tof_config()
    assert cfg.phaseUnwrappingLevel == 2 and cfg.enableOpticalCorrection
    assert cfg.median == dai.MedianFilter.KERNEL_5x5


def test_tofhil_capture_writes_a_session_from_the_host_pipeline(tmp_path):
    import subprocess
    import sys

    out = tmp_path / "cap.h5"
    run = lambda *a: subprocess.run([sys.executable, "-m", "tofhil.cli", "capture", *a],  # noqa: E731
                                    capture_output=True, text=True, timeout=120)
    r = run("--device", "depthai-sim:2.0", "--frames", "3", "--out", str(out), "--mode", "distance")
    assert r.returncode == 0, r.stderr
    with open_session(out) as s:
        assert s.n_frames == 3 and s.has_depth and s.device["driver"] == "depthai"
        d = s.depth_frame(0)
        np.testing.assert_allclose(d.z_m[d.valid], 2.0, atol=0.6e-3)
    r = run("--device", "depthai-sim", "--frames", "1", "--out", str(tmp_path / "x.h5"), "--mode", "dcs")
    assert r.returncode == 2 and "distance" in r.stderr and "Traceback" not in r.stderr


def test_reconfiguring_mid_stream_keeps_the_session_radial():
    d0 = 1.1
    dev = DepthAIToF("depthai-sim", host_scene=PlaneScene(distance_m=d0), camera=CAM)
    with dev:
        dev.configure(CaptureSettings(mode="distance"))
        a = next(iter(dev.stream(1, timeout_s=5.0)))
        dev.configure(CaptureSettings(mode="distance", extra={"enable_optical_correction": True}))
        b = next(iter(dev.stream(1, timeout_s=5.0)))
    assert a.depth.meta["depth_kind_on_wire"] == "radial" and b.depth.meta["depth_kind_on_wire"] == "z"
    for f in (a, b):
        np.testing.assert_allclose(f.depth.radial_m, d0 / CAM.ray_z, atol=0.6e-3)


def test_twin_frames_flow_through_the_queues(tmp_path):
    """depthai-sim:SCENE sends the simulator twin's frames; what arrives is the twin's depth
    (demodulated by the core) to the millimetre, and the bundled wall is where the scene says."""
    from tofhil.depth import depth_from_raw
    from tofhil.sim.sources import TwinScene
    from tofhil.sim.pipeline import simulate
    from tofhil.sim.scene import load_scene

    scene = TwinScene(scene="wall", realisations=2, seed=3)
    dev = DepthAIToF("depthai-sim", host_scene=scene)
    with dev:
        dev.configure(CaptureSettings(mode="distance", extra={"enable_optical_correction": True}))
        frames = list(dev.stream(3, timeout_s=30.0))
        cam = dev.camera
    twin = [depth_from_raw(r) for r in simulate(load_scene("wall"), frames=2, seed=3)]
    for i, f in enumerate(frames):
        ref = twin[i % 2]
        ok = ref.valid & f.depth.valid
        assert ok.mean() > 0.9
        # z on the wire (mm), back to radial: within the mm rounding of z.
        assert np.max(np.abs(f.depth.radial_m[ok] - ref.radial_m[ok])) < 0.6e-3 / cam.ray_z.min()
    # The wall is 1.0 m away along the optical axis (scene file): the centre's z says so.
    c = frames[0].depth.z_m[cam.height // 2 - 5:cam.height // 2 + 5, cam.width // 2 - 5:cam.width // 2 + 5]
    assert abs(float(np.median(c)) - 1.0) < 0.05


def test_colour_stream_is_recorded_beside_tof_in_the_rgb_group(tmp_path):
    """``color: true`` on depthai-sim:SCENE with a second camera: the host source sends the twin's
    colour image on its own (unsynchronised) stream; every ToF frame gets the colour frame nearest
    in device time, and a capture writes them into the session's rgb/ group with the scene's camera
    and true extrinsics."""
    from tofhil.drivers.capture import capture
    from tofhil.sim.sources import TwinScene
    from tofhil.session_rgb import read_rgb
    from tofhil.sim.rgb import render_grey
    from tofhil.sim.scene import load_scene, scene_to_yaml

    sc = load_scene("wall", {"camera": {"width": 40, "height": 30, "fx": 29.0, "fy": 29.0, "cx": 19.5, "cy": 14.5},
                             "rgb_camera": {"width": 64, "height": 48, "hfov_deg": 70.0, "samples": 1,
                                            "pose": {"position": [0.03, 0.0, 0.0]}}})
    path = tmp_path / "wall_rgb.yaml"
    path.write_text(scene_to_yaml(sc), encoding="utf-8")
    dev = DepthAIToF("depthai-sim", host_scene=TwinScene(scene=str(path), realisations=1))
    settings = CaptureSettings(mode="distance", extra={"color": True})
    with dev:
        summary = capture(dev, tmp_path / "s.h5", 3, settings, timeout_s=30.0)
    assert summary.frames_written == 3
    rgb = read_rgb(tmp_path / "s.h5")
    assert rgb.images.shape == (3, 48, 64, 3) and list(rgb.frame_index) == [0, 1, 2]
    assert rgb.camera == sc.rgb_camera.camera
    np.testing.assert_allclose(rgb.tof_to_camera, sc.rgb_camera.tof_to_camera)
    # the image is the twin's second-camera render (scaled to 8 bit), brightest where the emitter points
    grey = render_grey(sc, sc.rgb_camera.camera, sc.rgb_camera.tof_to_camera, samples=1)
    corr = np.corrcoef(rgb.images[0, ..., 0].ravel().astype(float), np.asarray(grey).ravel())[0, 1]
    assert corr > 0.99


def test_colour_on_the_plane_source_is_refused():
    dev = DepthAIToF("depthai-sim:1.0")
    with dev:
        with pytest.raises(DeviceError) as e:
            dev.configure(CaptureSettings(mode="distance", extra={"color": True}))
            dev.read_frame(5.0)
    assert e.value.field == "color"
