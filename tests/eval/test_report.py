"""tofhil correct / compare / calibrate-taps end to end on synthetic sessions built in the test."""

from __future__ import annotations

import base64
import json
import re
from pathlib import Path

import numpy as np
import pytest

from tests import straylight_synthetic as syn  # noqa: E402

from tests.cli_in_process import run_cli as run  # noqa: E402
from tofhil.frames import DepthFrame  # noqa: E402
from tofhil.session import SessionWriter, open_session  # noqa: E402


@pytest.fixture(scope="module")
def sessions(tmp_path_factory):
    d = tmp_path_factory.mktemp("sessions")
    s, _ = syn.scene_signal(0.05)
    syn.write_session(d / "a.h5", syn.with_stray_light(s), noise=0.0003, seed=1)
    syn.write_session(d / "b.h5", s)
    card, _ = syn.scene_signal(None, card=True, wall=False)
    syn.write_session(d / "cal.h5", syn.with_stray_light(card))
    return d


def square_median(metrics: dict, variant: str) -> float:
    return metrics["variants"][variant]["regions"]["square"]["depth_residual_m"]["median"]


def test_calibrate_correct_and_compare(sessions, tmp_path, capsys):
    d = sessions
    psf = tmp_path / "psf.json"
    assert run("correct", d / "cal.h5", "--method", "psf", "--calibrate", d / "cal.h5", "--save-psf", psf,
               "--out", tmp_path / "cal_corr.h5") == 0
    assert psf.is_file()
    assert run("correct", d / "a.h5", "--method", f"psf:psf={psf}", "--out", tmp_path / "a_corr.h5") == 0
    from tofhil.depth import depth_from_raw

    with open_session(tmp_path / "a_corr.h5") as s, open_session(d / "b.h5") as b:
        assert s.n_frames == 2 and s.has_raw and s.has_depth
        corrected = s.depth_frame(0).radial_m[syn.SQUARE]
        truth = depth_from_raw(b.raw_frame(0)).radial_m[syn.SQUARE]
    with open_session(d / "a.h5") as a:
        before = depth_from_raw(a.raw_frame(0)).radial_m[syn.SQUARE]
    # The card's stray light pulls the square nearer by centimetres; the correction undoes it.
    assert np.median(truth - before) > 0.05
    assert np.abs(np.median(corrected - truth)) < 0.1 * np.median(truth - before)

    out = tmp_path / "report"
    roi = f"{syn.SQUARE[1].start},{syn.SQUARE[0].start},{syn.SQUARE[1].stop},{syn.SQUARE[0].stop}"
    assert run("compare", d / "a.h5", d / "b.h5", "--out", out, "--correct", f"psf:psf={psf}",
               "--correct", "uniform:w=3e-6", "--correct", "smooth-median:size=3", "--roi", roi) == 0
    m = json.loads((out / "metrics.json").read_text())
    m["variants"] = {k: v for k, v in m["variants"].items()}
    for v in m["variants"].values():  # rename the ROI for readability
        v["regions"]["square"] = v["regions"].pop(f"roi_{roi.replace(',', '_')}")
    assert set(m["variants"]) == {"measured", f"psf:psf={psf}", "uniform:w=3e-6", "smooth-median:size=3"}
    before_m = square_median(m, "measured")
    assert before_m < -0.05
    assert abs(square_median(m, f"psf:psf={psf}")) < 0.1 * abs(before_m)
    # Cloud metrics and NDT of the other helper's modules are there for every variant.
    for v in m["variants"].values():
        allr = v["regions"]["all"]
        assert {"chamfer", "fscore"} <= set(allr["cloud"])
        assert {"score_per_point", "nvtl", "mean_likelihood_trilinear"} <= set(allr["ndt"])
    assert (m["variants"][f"psf:psf={psf}"]["regions"]["all"]["cloud"]["chamfer"]
            < m["variants"]["measured"]["regions"]["all"]["cloud"]["chamfer"])

    html = (out / "report.html").read_text()
    pngs = re.findall(r"src='data:image/png;base64,([^']+)'", html)
    assert len(pngs) == 7  # depth, amplitude, residual, amplitude ratio, cross-section, histogram, NDT maps
    for p in pngs:
        assert base64.b64decode(p)[:8] == b"\x89PNG\r\n\x1a\n"
    # Self-contained: nothing is fetched from anywhere.
    assert not re.search(r"(src|href)=['\"](https?:)?//", html)
    assert "<script" not in html
    # An existing report is not overwritten without --force.
    assert run("compare", d / "a.h5", d / "b.h5", "--out", out) == 2
    assert "already exists" in capsys.readouterr().err


def test_complex_methods_refuse_depth_only_sessions(tmp_path, capsys):
    depth_only = tmp_path / "depth.h5"
    with SessionWriter(depth_only, syn.CAMERA) as w:
        w.append(None, DepthFrame(distance_m=syn.wall_distance(), kind="radial", camera=syn.CAMERA,
                                  amplitude=np.ones(syn.CAMERA.shape)))
    assert run("correct", depth_only, "--method", "uniform:w=1e-5", "--out", tmp_path / "x.h5") == 2
    err = capsys.readouterr().err
    assert "needs raw taps" in err and "depth only" in err
    assert not (tmp_path / "x.h5").exists()
    # Depth methods work on it.
    assert run("correct", depth_only, "--method", "jump-distance:max_step_m=0.02",
               "--out", tmp_path / "y.h5") == 0
    assert run("compare", depth_only, depth_only, "--out", tmp_path / "r", "--correct", "psf:psf=x.npz") == 2
    assert "needs raw taps" in capsys.readouterr().err


def test_bad_options_are_one_line_errors(sessions, tmp_path, capsys):
    d = sessions
    assert run("correct", d / "a.h5", "--method", "nope", "--out", tmp_path / "x.h5") == 2
    assert "unknown correction method" in capsys.readouterr().err
    assert run("correct", d / "a.h5", "--method", "uniform", "--out", tmp_path / "x.h5") == 2
    assert "needs parameter 'w'" in capsys.readouterr().err
    assert run("correct", d / "a.h5", "--method", "uniform:w=1e-5,sigma_px=2", "--out", tmp_path / "x.h5") == 2
    assert "has no parameter(s) sigma_px" in capsys.readouterr().err
    assert run("correct", d / "a.h5", "--method", f"psf:psf={tmp_path / 'missing.json'}",
               "--out", tmp_path / "x.h5") == 2
    assert "missing.json: no such file" in capsys.readouterr().err
    assert run("compare", d / "a.h5", d / "b.h5", "--out", tmp_path / "r", "--roi", "1,2") == 2
    assert "X0,Y0,X1,Y1" in capsys.readouterr().err


def test_tap_calibration_removes_tap_gains(tmp_path):
    # Taps with per-tap gains g_k(p): a flat (unmodulated) capture reveals them.
    rng = np.random.default_rng(7)
    gains = 1.0 + 0.02 * rng.standard_normal((1, 4) + syn.CAMERA.shape)
    offsets = 3.0 + 0.5 * rng.standard_normal((1, 4) + syn.CAMERA.shape)
    from tofhil.frames import RawFrame

    def write(path: Path, s: np.ndarray, b: np.ndarray) -> None:
        from tofhil.demod import taps_from_signal

        taps = gains * taps_from_signal(np.abs(s)[None], np.angle(s)[None], b[None], syn.THETA) + offsets
        with SessionWriter(path, syn.CAMERA) as w:
            w.append(RawFrame(taps=taps.astype(np.float32), freq_hz=syn.FREQ, theta_rad=syn.THETA,
                              integration_time_s=1e-3, camera=syn.CAMERA))

    zero = np.zeros(syn.CAMERA.shape, complex)
    v, u = np.mgrid[0:syn.H, 0:syn.W]
    illum = 200.0 * (1 - 0.3 * ((u - 40) ** 2 + (v - 30) ** 2) / 2500)  # smooth, like a lit wall
    write(tmp_path / "dark.h5", zero, np.zeros(syn.CAMERA.shape))
    write(tmp_path / "flat.h5", zero, illum)
    s, _ = syn.scene_signal(0.05)
    write(tmp_path / "scene.h5", 40 * s, np.full(syn.CAMERA.shape, 50.0))  # wall: |S|/B = 0.2
    cal = tmp_path / "taps.npz"
    assert run("calibrate-taps", "--flat", tmp_path / "flat.h5", "--dark", tmp_path / "dark.h5", "--out", cal) == 0
    assert run("correct", tmp_path / "scene.h5", "--method", f"taps:flat={cal}", "--out", tmp_path / "c.h5") == 0
    from tofhil.demod import phasor

    with open_session(tmp_path / "c.h5") as c, open_session(tmp_path / "scene.h5") as raw:
        sc = phasor(c.raw_frame(0).taps.astype(float), syn.THETA)[0]
        sr = phasor(raw.raw_frame(0).taps.astype(float), syn.THETA)[0]
    # Offsets and tap gains removed: the phase is the scene's (gains of 2 % and 0.5 DN tap
    # offsets put the 5 % square's phase off by tenths of a radian).
    sq = syn.SQUARE
    err_raw = np.abs(np.angle(sr[sq] / s[sq])).mean()
    err_cal = np.abs(np.angle(sc[sq] / s[sq])).mean()
    assert err_raw > 0.05 and err_cal < 0.02 * err_raw
    # A modulated "flat" capture is refused.
    assert run("calibrate-taps", "--flat", tmp_path / "scene.h5", "--out", tmp_path / "bad.npz") == 2


def test_compare_twin_sessions_has_per_object_regions(tmp_path):
    pytest.importorskip("tofhil.sim.pipeline")
    from tofhil.sim.pipeline import simulate_session
    from tofhil.sim.scene import load_scene

    scene = load_scene("dark_square_card", overrides={"params": {"square_reflectance": 0.2}})
    stray = {"stray_light": {"weight": 0.03, "sigma_px": 15.0, "veil": 0.01}}
    simulate_session(scene, tmp_path / "a.h5", frames=1, noise=False, effects=stray)
    simulate_session(scene, tmp_path / "b.h5", frames=1, noise=False, effects={})
    assert run("compare", tmp_path / "a.h5", tmp_path / "b.h5", "--out", tmp_path / "r", "--frames", "1") == 0
    m = json.loads((tmp_path / "r" / "metrics.json").read_text())
    assert m["settings"]["object_regions_from"] == "B"
    regions = m["variants"]["measured"]["regions"]
    assert {"all", "wall", "square", "card"} <= set(regions)
    # The near card's stray light pulls the far, dark square nearer; the card itself,
    # bright and near, hardly moves.
    sq = regions["square"]["depth_residual_m"]["median"]
    assert sq < -0.05
    assert abs(regions["card"]["depth_residual_m"]["median"]) < 0.1 * abs(sq)
    assert regions["square"]["pixels"] > 100


def test_calibration_against_a_twin_reference_recovers_the_psf(tmp_path):
    # Calibration scene: wall + card (no square), measured with stray light, and its twin.
    s, _ = syn.scene_signal(None, card=True)
    syn.write_session(tmp_path / "cal.h5", syn.with_stray_light(s))
    syn.write_session(tmp_path / "twin.h5", s)
    psf_path = tmp_path / "psf.json"
    assert run("correct", tmp_path / "cal.h5", "--method", "psf", "--calibrate", tmp_path / "cal.h5",
               "--reference", tmp_path / "twin.h5", "--save-psf", psf_path, "--out", tmp_path / "c.h5") == 0
    from tofhil.sim.straylight import StrayLightPSF

    psf = StrayLightPSF.load(psf_path)
    w = {k: v for k, v in zip(psf.info["basis"], psf.info["weights"]) if v > 1e-4}
    # syn.psf_kernel(): a 9 px Gaussian of weight 0.08 plus a veil of 0.03, additive.
    lobes = {k: v for k, v in w.items() if k.startswith("gauss")}
    assert len(lobes) == 1 and sum(lobes.values()) == pytest.approx(0.08, rel=0.02)
    sx, sy = (float(x) for x in next(iter(lobes)).removeprefix("gauss_").split("x"))
    assert sx == pytest.approx(9.0, rel=0.03) and sy == pytest.approx(9.0, rel=0.03)
    assert w["veil"] == pytest.approx(0.03, rel=0.05)
    assert psf.keep == pytest.approx(1.0, abs=0.005)
