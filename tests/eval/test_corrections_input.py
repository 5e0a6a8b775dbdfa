"""Bad correction parameters are refused in the library (so every command refuses them the
same way): one line naming ``METHOD:key`` and what was expected, exit 2, nothing written."""

from __future__ import annotations

import numpy as np
import pytest

from tests import straylight_synthetic as syn
from tofhil.errors import TofhilError
from tofhil.eval.corrections import correct_depth, parse_method_spec, resolve_params
from tofhil.frames import DepthFrame


@pytest.mark.parametrize("spec, field", [
    ("gaussian-inverse:sigma_h=-1,sigma_v=2,w=0.1", "gaussian-inverse:sigma_h"),
    ("gaussian-inverse:sigma_h=0,sigma_v=2,w=0.1", "gaussian-inverse:sigma_h"),
    ("gaussian-inverse:sigma_h=2,sigma_v=-3,w=0.1", "gaussian-inverse:sigma_v"),
    ("gaussian-inverse:sigma_h=2,sigma_v=2,w=0.1,mu=-1", "gaussian-inverse:mu"),
    ("uniform:w=nan", "uniform:w"),
    ("uniform:w=-1", "uniform:w"),
    ("uniform:w=5", "uniform:w"),
    ("uniform:w=1", "uniform:w"),
    ("gaussian-inverse:sigma_h=2,sigma_v=2,w=inf", "gaussian-inverse:w"),
    ("amplitude:min_amplitude=nan", "amplitude:min_amplitude"),
    ("amplitude:min_amplitude=-1", "amplitude:min_amplitude"),
    ("jump-angle:angle_deg=500", "jump-angle:angle_deg"),
    ("jump-angle:angle_deg=-1", "jump-angle:angle_deg"),
    ("jump-distance:max_step_m=-0.1", "jump-distance:max_step_m"),
    ("smooth-bilateral:sigma_px=-1", "smooth-bilateral:sigma_px"),
    ("smooth-bilateral:sigma_m=-0.03", "smooth-bilateral:sigma_m"),
    ("smooth-gaussian:sigma_px=0", "smooth-gaussian:sigma_px"),
    ("smooth-median:size=4", "smooth-median:size"),
    ("smooth-median:size=0", "smooth-median:size"),
    ("smooth-median:size=-3", "smooth-median:size"),
    ("smooth-median:size=3.5", "smooth-median:size"),
    ("psf:psf=x.json,iterations=0", "psf:iterations"),
    ("uniform:w=1e-5,sigma_px=2", "uniform:sigma_px"),
    ("uniform", "uniform:w"),
])
def test_bad_parameters_name_method_and_key(spec: str, field: str) -> None:
    with pytest.raises(TofhilError) as err:
        parse_method_spec(spec)
    assert err.value.field == field
    assert err.value.expected


def test_good_specs_parse_to_typed_values() -> None:
    name, p = parse_method_spec("gaussian-inverse:sigma-h=32,sigma_v=30,w=0.04")
    assert name == "gaussian-inverse"
    assert resolve_params(name, p) == {"sigma_h": 32.0, "sigma_v": 30.0, "w": 0.04, "mu": 0.0, "twin": "", "flat": ""}
    assert resolve_params(*parse_method_spec("smooth-median:size=5")) == {"size": 5}


@pytest.mark.parametrize("spec", ["smooth-median:size=100001", "smooth-median:size=61",
                                  "smooth-gaussian:sigma_px=1e9", "smooth-bilateral:sigma_px=1e6"])
def test_windows_are_bounded_by_the_image(spec: str) -> None:
    frame = DepthFrame(distance_m=syn.wall_distance(), kind="radial", camera=syn.CAMERA,
                       amplitude=np.ones(syn.CAMERA.shape))  # 80 x 60
    name, p = parse_method_spec(spec)
    with pytest.raises(TofhilError) as err:
        correct_depth(frame, name, p)
    assert err.value.field == spec.split("=")[0] and "80x60" in str(err.value)


def test_median_of_a_large_window_matches_a_direct_median() -> None:
    from tofhil.eval.corrections.depth_filters import median_smooth

    rng = np.random.default_rng(0)
    d = rng.random((30, 40))
    valid = rng.random((30, 40)) > 0.2
    got = median_smooth(d, valid, 7, max_bytes=8 * 49 * 40 * 3)  # three rows at a time
    y, x = 12, 33
    win = np.where(valid, d, np.nan)[y - 3:y + 4, x - 3:min(x + 4, 40)]
    assert got[y, x] == pytest.approx(np.nanmedian(win) if valid[y, x] else d[y, x])


def test_all_nan_flat_is_not_a_calibration() -> None:
    from tofhil.demod import equally_spaced_phases
    from tofhil.eval.calibration.taps import calibrate_taps

    flat = np.full((1, 4, 6, 8), np.nan)
    with pytest.raises(TofhilError) as err:
        calibrate_taps(flat, equally_spaced_phases(4))
    assert err.value.field == "flat" and "not finite" in str(err.value)


def _one_line_error(proc, *needles: str) -> None:
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:"), proc.stderr
    for n in needles:
        assert n in lines[0], lines[0]


def test_cli_refuses_bad_values_and_writes_nothing(tofhil_cli, tmp_path) -> None:
    s, _ = syn.scene_signal(0.05, card=True)
    a = syn.write_session(tmp_path / "a.h5", syn.with_stray_light(s), n_frames=1)
    out = tmp_path / "x.h5"
    _one_line_error(tofhil_cli("correct", a, "--method", "uniform:w=nan", "--out", out), "uniform:w", "[0, 1)")
    _one_line_error(tofhil_cli("correct", a, "--method", "smooth-median:size=4", "--out", out),
                    "smooth-median:size", "odd")
    _one_line_error(tofhil_cli("correct", a, "--method", "uniform:w=1e-5", "--min-amplitude", "nan",
                               "--out", out), "--min-amplitude")
    _one_line_error(tofhil_cli("compare", a, a, "--out", tmp_path / "r", "--correct",
                               "gaussian-inverse:sigma_h=-2,sigma_v=2,w=0.1"), "gaussian-inverse:sigma_h")
    assert not out.exists() and not (tmp_path / "r" / "metrics.json").exists()


def test_cli_calibration_files_are_never_replaced_without_force(tofhil_cli, tmp_path) -> None:
    s, _ = syn.scene_signal(None, card=True)
    cal = syn.write_session(tmp_path / "cal.h5", syn.with_stray_light(s), n_frames=1)
    twin = syn.write_session(tmp_path / "twin.h5", s, n_frames=1)
    psf = tmp_path / "psf.json"
    psf.write_text("keep me")
    p = tofhil_cli("correct", cal, "--method", "psf", "--calibrate", cal, "--reference", twin,
                   "--save-psf", psf, "--out", tmp_path / "c.h5")
    _one_line_error(p, str(psf), "--force")
    assert psf.read_text() == "keep me" and not (tmp_path / "c.h5").exists()
    # calibrate-taps --out calib writes calib.npz: an existing calib.npz is refused, by its real name.
    flat = tmp_path / "flat.h5"
    syn.write_session(flat, np.zeros_like(s), n_frames=1, offset=50.0)
    (tmp_path / "calib.npz").write_bytes(b"recorded")
    _one_line_error(tofhil_cli("calibrate-taps", "--flat", flat, "--out", tmp_path / "calib"),
                    str(tmp_path / "calib.npz"), "--force")
    assert (tmp_path / "calib.npz").read_bytes() == b"recorded" and not (tmp_path / "calib").exists()
