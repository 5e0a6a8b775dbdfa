"""The pyusb TOFcam635 driver, run unchanged against the in-process emulator backend.

Physics is checked against closed forms of the analytic wall (radial distance z / ray_z,
amplitude A1 cos^6(alpha) / d^2 (the twin's plane radiometry) scaled with exposure, phase wrap at c / 2f), and the tap
convention against the vendor's own phase formula on the raw device DCS."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tofhil import C_M_PER_S
from tofhil.demod import phasor
from tofhil.depth import depth_from_raw
from tofhil.drivers.tofcam635 import protocol as P
from tofhil.drivers.base import CaptureSettings, list_devices, open_device
from tofhil.drivers.tofcam635.emulator import EmulatedTofCam635, Epc635Emulator
from tofhil.sim.sources import AnalyticWall, NoiseModel, WallSpec
from tofhil.drivers.tofcam635.usb_backend import EmulatorBackend
from tofhil.drivers.tofcam635.driver import TofCam635
from tofhil.errors import DeviceError

NO_NOISE = NoiseModel(read_noise_dn=0.0, electrons_per_dn=math.inf)


def wall_device(distance_m: float = 1.2, noise: NoiseModel | None = NO_NOISE, **wall: float) -> EmulatedTofCam635:
    src = AnalyticWall(WallSpec(distance_m=distance_m, **wall))
    return EmulatedTofCam635("emulator", emulator=Epc635Emulator(src, noise=noise))


def test_dcs_frames_are_canonical_taps_of_the_wall() -> None:
    with wall_device(1.2) as dev:
        dev.configure(CaptureSettings(mode="dcs", integration_time_s=500e-6, mod_freq_hz=20e6))
        raw = next(dev.stream(1)).raw
        assert raw is not None
        assert raw.taps.shape == (1, 4, 60, 160)
        np.testing.assert_allclose(np.degrees(raw.theta_rad), [0, 90, 180, 270])
        assert raw.freq_hz[0] == 20e6 and raw.integration_time_s == pytest.approx(500e-6)
        d_true = 1.2 / raw.camera.ray_z
        depth = depth_from_raw(raw)
        # DCS are integers: phase error <= 0.5 DN / A ~ 3e-4 rad ~ 0.2 mm at 20 MHz
        np.testing.assert_allclose(depth.radial_m, d_true, atol=2e-3)
        rz = raw.camera.ray_z  # cos^1 beam, cos incidence, cos^4 lens, 1/d^2; 500 us = 4 x the reference
        a_true = 600.0 * 4 * rz * rz * rz ** 4 / d_true**2
        np.testing.assert_allclose(np.abs(phasor(raw.taps[0], raw.theta_rad)), a_true, rtol=0.01, atol=1.0)
        # differential DCS: the offset (ambient + signal) cancels
        assert abs(float(raw.taps.mean())) < 1.0


def test_tap_convention_matches_the_vendor_phase_formula() -> None:
    """Vendor toolkit: phase = atan2(DCS3 - DCS1, DCS2 - DCS0) + pi, distance = c phase / 4 pi f."""
    with wall_device(2.3) as dev:
        dev.configure(CaptureSettings(mode="dcs", integration_time_s=1000e-6, mod_freq_hz=10e6))
        img = dev.acquire(P.Cmd.GET_DCS)
        dcs = P.decode_dcs(img).astype(np.float64) - 2048
        vendor_m = (np.arctan2(dcs[3] - dcs[1], dcs[2] - dcs[0]) + np.pi) * C_M_PER_S / (4 * np.pi * 10e6)
        raw = next(dev.stream(1)).raw
        assert raw is not None
        ours = depth_from_raw(raw).radial_m
        np.testing.assert_allclose(ours, vendor_m, atol=2e-3)
        # dim corners at 2.3 m (cos^8 falloff): integer DCS give up to ~0.5 DN / A rad there
        np.testing.assert_allclose(ours, 2.3 / raw.camera.ray_z, atol=4e-3)


@pytest.mark.parametrize("freq_hz", [20e6, 10e6])
def test_distance_wraps_at_the_ambiguity_range(freq_hz: float) -> None:
    with wall_device(9.0, amplitude_at_1m_dn=2000.0) as dev:
        dev.configure(CaptureSettings(mode="dcs", integration_time_s=2000e-6, mod_freq_hz=freq_hz))
        raw = next(dev.stream(1)).raw
        assert raw is not None
        d = 9.0 / raw.camera.ray_z
        unambiguous = C_M_PER_S / (2 * freq_hz)  # 7.49 m at 20 MHz, 14.99 m at 10 MHz
        expect = np.mod(d, unambiguous)
        got = depth_from_raw(raw).radial_m
        np.testing.assert_allclose(got, expect, atol=0.01)
        assert (freq_hz == 20e6) == bool(np.all(got < 7.5))


def test_distance_mode_reports_metres_and_low_amplitude_codes() -> None:
    with wall_device(1.5) as dev:
        dev.configure(CaptureSettings(mode="distance", integration_time_s=250e-6, mod_freq_hz=20e6))
        cam = dev.camera
        d_true = 1.5 / cam.ray_z
        # The twin's radiometry of a wall (cos^1 beam, cos incidence, 1/d^2, cos^4 lens), x2 exposure.
        a_true = 600.0 * 2 * cam.ray_z * cam.ray_z * cam.ray_z ** 4 / d_true**2
        limit = float(np.percentile(a_true, 30))  # the dimmer (outer) 30 % of the wall falls below
        dev.configure(min_amplitude=limit)
        depth = next(dev.stream(1)).depth
        assert depth is not None and depth.kind == "radial"
        clear = np.abs(a_true - limit) > 3.0  # away from the threshold, the mask is exact
        np.testing.assert_array_equal(depth.valid[clear], (a_true >= limit)[clear])
        # mm codes, plus the integer DCS's ~0.5 DN / A rad on the dimmer valid pixels
        np.testing.assert_allclose(depth.radial_m[depth.valid], d_true[depth.valid], atol=3e-3)
        assert np.all(np.isnan(depth.radial_m[~depth.valid]))
        np.testing.assert_allclose(depth.amplitude[depth.valid], a_true[depth.valid], rtol=0.01, atol=1.5)
        assert depth.meta["invalid_codes"]["low_amplitude"] == int(np.count_nonzero(~depth.valid))


def test_saturated_pixels_are_flagged_not_measured() -> None:
    with wall_device(0.25, amplitude_at_1m_dn=600.0) as dev:  # 16x brighter than at 1 m
        dev.configure(CaptureSettings(mode="distance", integration_time_s=1000e-6, min_amplitude=0))
        depth = next(dev.stream(1)).depth
        assert depth is not None
        centre = (slice(25, 35), slice(70, 90))
        assert not depth.valid[centre].any()  # 600*8*16 DN >> 2047: the 12-bit DCS clip
        assert depth.meta["invalid_codes"]["adc_overflow"] > 0


def test_roi_crops_image_and_camera_model() -> None:
    with wall_device(1.0) as dev:
        dev.configure(CaptureSettings(mode="dcs", integration_time_s=300e-6))
        full = next(dev.stream(1)).raw
        dev.configure(roi=(8, 4, 88, 44))
        roi = next(dev.stream(1)).raw
        assert full is not None and roi is not None
        assert roi.taps.shape == (1, 4, 40, 80)
        assert (roi.camera.cx, roi.camera.cy) == (full.camera.cx - 8, full.camera.cy - 4)
        np.testing.assert_array_equal(roi.taps, full.taps[..., 4:44, 8:88])  # noise off: same pixels
        np.testing.assert_allclose(roi.camera.ray_z, full.camera.ray_z[4:44, 8:88])
        with pytest.raises(DeviceError, match="roi"):
            dev.configure(roi=(0, 0, 160, 61))


# Every ROI the camera accepts (multiples of 4, half-open, at least 4 x 4): the vendor test's
# (4, 4, 156, 12) = 152 x 8, the smallest in each corner, full width and full height strips.
ACCEPTED_ROIS = [(0, 0, 160, 60), (4, 4, 156, 12), (0, 0, 4, 4), (156, 56, 160, 60), (0, 28, 160, 32),
                 (76, 0, 80, 60), (8, 4, 88, 44)]


@pytest.mark.parametrize("mode", ["dcs", "distance", "grayscale"])
def test_every_accepted_roi_gives_images_of_its_size(mode: str) -> None:
    """Through pyusb (the in-process backend): the image is (y1 - y0) x (x1 - x0), its pixels
    are the full frame's at [y0:y1, x0:x1] (noise off) and the camera model is cropped to it."""
    with wall_device(1.0) as dev:
        dev.configure(CaptureSettings(mode=mode, integration_time_s=300e-6, min_amplitude=0))
        full = next(dev.stream(1))
        for x0, y0, x1, y1 in ACCEPTED_ROIS:
            dev.configure(roi=(x0, y0, x1, y1))
            frame = next(dev.stream(1))
            crop = (Ellipsis, slice(y0, y1), slice(x0, x1))
            if mode == "dcs":
                assert frame.raw is not None and full.raw is not None
                assert frame.raw.taps.shape == (1, 4, y1 - y0, x1 - x0)
                np.testing.assert_array_equal(frame.raw.taps, full.raw.taps[crop])
                camera = frame.raw.camera
            elif mode == "distance":
                assert frame.depth is not None and full.depth is not None
                assert frame.depth.radial_m.shape == frame.depth.amplitude.shape == (y1 - y0, x1 - x0)
                np.testing.assert_array_equal(frame.depth.radial_m, full.depth.radial_m[crop])
                camera = frame.depth.camera
            else:
                gray = frame.images["grayscale"]
                assert gray.shape == (y1 - y0, x1 - x0)
                np.testing.assert_array_equal(gray, full.images["grayscale"][crop])
                camera = dev.camera
            assert camera.shape == (y1 - y0, x1 - x0)
            assert (camera.cx, camera.cy) == (dev._sensor_camera.cx - x0, dev._sensor_camera.cy - y0)


REFUSED_ROIS = [(1, 0, 160, 60), (0, 0, 158, 60), (4, 4, 4, 12), (8, 4, 4, 12), (0, 0, 164, 60), (0, 0, 160, 64)]


@pytest.mark.parametrize("roi", REFUSED_ROIS)
def test_the_camera_refuses_what_the_vendor_client_cannot_send(roi: tuple[int, int, int, int]) -> None:
    """Unaligned, empty or reversed, or past the sensor: the emulated firmware answers NACK and
    keeps its ROI; the driver refuses it first with a DeviceError naming the field."""
    emu = Epc635Emulator(AnalyticWall(), noise=NO_NOISE)
    parser = P.PacketParser()
    for sent, answer in (((4, 4, 156, 12), P.DataType.ACK), (roi, P.DataType.NACK)):
        emu.receive(P.encode_command(P.Cmd.SET_ROI, b"".join(P.u16(v) for v in sent)))
        parser.feed(emu.transmit())
        reply = parser.next_packet()
        assert reply is not None and reply.dtype == answer
    assert emu.roi == (4, 4, 156, 12)
    with wall_device(1.0) as dev:
        with pytest.raises(DeviceError, match="roi.*multiples of 4"):
            dev.configure(roi=roi)


def test_grayscale_mode_and_device_information() -> None:
    with wall_device(1.0) as dev:
        info = dev.info()
        assert info.model == "TOFcam635" and info.firmware == "3.49"
        assert (info.extra["chip_id"], info.extra["wafer_id"], info.extra["chip_type"]) == (20, 1038, 4)
        assert 20.0 < dev.chip_temperature_c() < 60.0
        dev.configure(CaptureSettings(mode="grayscale", integration_time_s=125e-6))
        frame = next(dev.stream(1))
        gray = frame.images["grayscale"]
        assert gray.shape == (60, 160) and gray.dtype == np.uint8
        # offset = ambient + A at 125 us, 16 DN per grey level: brighter in the centre
        assert gray[30, 80] > gray[0, 0]
        assert dev.usb_backend.kernel_detaches == 2  # cdc_acm detached from both CDC interfaces


def test_frames_carry_device_timestamps_and_sequence_numbers() -> None:
    with wall_device(1.0, noise=None) as dev:
        dev.configure(CaptureSettings(mode="dcs"))
        frames = list(dev.stream(5))
        seq = [f.sequence for f in frames]
        assert seq == list(range(seq[0], seq[0] + 5))
        ts = [f.timestamp_s for f in frames]
        assert all(b >= a for a, b in zip(ts, ts[1:]))
        assert all(f.raw is not None and f.raw.temperature_c > 20 for f in frames)


def test_bad_settings_are_refused_with_the_field_named() -> None:
    with wall_device(1.0) as dev:
        with pytest.raises(DeviceError, match="mod_freq_hz"):
            dev.configure(CaptureSettings(mod_freq_hz=30e6))
        with pytest.raises(DeviceError, match="integration_time_s"):
            dev.configure(CaptureSettings(integration_time_s=0.2))
        with pytest.raises(DeviceError, match="mode"):
            CaptureSettings(mode="colour")


def test_permission_error_points_to_the_udev_rule() -> None:
    emu = Epc635Emulator(AnalyticWall())
    dev = TofCam635("usb", backend=EmulatorBackend([emu], deny_access=True))
    with pytest.raises(DeviceError) as exc:
        dev.open()
    text = str(exc.value)
    assert "permission denied" in text and "99-tofcam635.rules" in text and "udevadm" in text


def test_no_device_and_unknown_specs_are_clear_errors() -> None:
    with pytest.raises(DeviceError, match="no TOFcam635"):
        TofCam635("usb", backend=EmulatorBackend([])).open()
    with pytest.raises(DeviceError, match="unknown device"):
        open_device("nosuchcamera:1")
    assert any(e.spec == "emulator" and e.kind == "emulated" for e in list_devices())


def test_device_counters_unwrap_across_wraps_and_restarts() -> None:
    from tofhil.drivers.tofcam635.driver import _Unwrapper

    u = _Unwrapper(1 << 16)
    assert [u(v) for v in (65534, 65535, 0, 1, 5000)] == [65534, 65535, 65536, 65537, 70536]
    assert [u(v) for v in (0, 1)] == [70537, 70538]  # a restarted device continues, no 65536 jump


def test_emulator_noise_is_the_sensor_models_shot_plus_read_noise() -> None:
    """Variance in DN = read^2 + mean / (electrons per DN): Poisson electrons, Gaussian read noise."""
    rng = np.random.default_rng(5)
    taps = np.full((4, 200, 200), 300.0, dtype=np.float32)
    noisy = NoiseModel(read_noise_dn=2.0, electrons_per_dn=4.0).apply(taps, rng)
    assert noisy.dtype == np.float32
    assert float(noisy.mean()) == pytest.approx(300.0, abs=0.1)
    assert float(noisy.var()) == pytest.approx(2.0**2 + 300.0 / 4.0, rel=0.02)
    np.testing.assert_array_equal(NO_NOISE.apply(taps, rng), taps)
