"""bench interference: a second ToF camera's light on the target, on the emulated TOFcam635
(pyusb backend) and the DepthAI emulation, against closed forms of the physics."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tofhil.app.bench import BenchOptions, run_bench
from tofhil.app.bench.interference import coherent_factor, predicted_range_error_m
from tofhil.camera import load_camera_preset
from tofhil.eval.metrics.bench import centre_roi


def test_coherent_factor_is_the_demodulation_integral():
    """``coherent_factor`` against the integral it stands for, summed numerically."""
    t_int = 125e-6
    t = (np.arange(200_000) + 0.5) / 200_000 * t_int
    for df in (0.0, 1e3, 3.3e3, 1e6, 1.05e6):
        numeric = np.mean(np.exp(2j * np.pi * df * t))
        assert coherent_factor(20e6, 20e6 + df, t_int) == pytest.approx(numeric, abs=1e-6)
    assert coherent_factor(20e6, 0.0, t_int) == 0          # unmodulated light: no phasor


def test_interference_on_the_emulated_tofcam635_against_closed_forms(tmp_path):
    e2, d, f = 0.1, 1.0, 20e6
    res = run_bench("interference", "emulator", tmp_path / "o", report=False,
                    options=BenchOptions(frames=5, seed=3, extra={"interferer_w_m2": e2,
                                                                 "work_dir": str(tmp_path / "w")}))
    rows = {r["label"]: r for r in res.curves["interference"]}
    # closed form, independent of the renderer: the device's own irradiance on a wall at D from a
    # cos^n beam of power P (TOFCAM635_OVERRIDES: 2 W; wall: n = 2) at a pixel with ray z-component
    # rz is P (n + 1) / (2 pi D^2) rz^(n+3) (beam, incidence, inverse square); the second camera's
    # E2 reflects from the same surface into the same pixel, so r = E2 / that
    cam = load_camera_preset("epc635")
    x0, y0, x1, y1 = centre_roi(cam.shape)
    rz = cam.ray_z[y0:y1, x0:x1]
    r = e2 * 2 * math.pi * d ** 2 / (2.0 * 3.0) / rz ** 5
    for label, psi in (("same0", 0), ("same90", 90), ("same180", 180), ("same270", 270)):
        expect = float(np.mean(predicted_range_error_m(r, math.radians(psi), f)))
        row = rows[label]
        # the 15 mm emitter offset the closed form leaves out: well below 1 % of the error
        tol = 4 * row["measured_interference_error_se_m"] + 0.01 * abs(expect)
        assert abs(row["measured_interference_error_m"] - expect) < tol, (label, row, expect)
        assert abs(row["twin_interference_error_m"] - expect) < 4 * row["twin_interference_error_se_m"] + 0.01 * abs(expect)
    assert rows["same90"]["measured_interference_error_m"] > 0.1       # ~125 mm: a tenth of the light at 90 deg
    for label in ("other", "cw"):                                       # offset only: no range change
        row = rows[label]
        assert abs(row["measured_interference_error_m"]) < 4 * row["measured_interference_error_se_m"]
    # in phase and in anti-phase the light (hence the shot noise) is the same, the amplitude
    # (1 + r) against (1 - r): the random errors' ratio sqrt(mean(w / (1 - r)^2) / mean(w / (1 + r)^2))
    # with w ~ 1 / A^2 ~ r^2 over the ROI's pixels
    w = r ** 2
    expect = math.sqrt(np.mean(w / (1 - r) ** 2) / np.mean(w / (1 + r) ** 2))
    a, b = rows["same0"], rows["same180"]
    ratio = b["measured_random_m"] / a["measured_random_m"]
    se = ratio * math.hypot(*(x["measured_random_var_se_m2"] / (2 * x["measured_random_m"] ** 2) for x in (a, b)))
    assert abs(ratio - expect) < 4 * se, (ratio, expect, se)
    ag = res.details["agreement"]
    assert ag["systematic"]["p"] >= 0.01 and ag["random"]["p"] >= 0.01, ag
    figs = {x.name: x for x in res.figures}
    assert figs["interference_error_m"].value > 0.1 and "interference_noise_factor" in figs


def test_interference_on_the_depthai_emulation_agrees_with_the_twin(tmp_path):
    res = run_bench("interference", "depthai-sim", tmp_path / "o", report=True,
                    options=BenchOptions(frames=4, seed=4, extra={"work_dir": str(tmp_path / "w")}))
    ag = res.details["agreement"]
    assert ag["systematic"]["p"] >= 0.01 and ag["random"]["p"] >= 0.01, ag
    rows = {r["label"]: r for r in res.curves["interference"]}
    # the same frequency at 90 degrees moves the range; another frequency does not
    assert rows["same90"]["measured_interference_error_m"] > 20 * rows["same90"]["measured_interference_error_se_m"]
    assert abs(rows["other"]["measured_interference_error_m"]) < 4 * rows["other"]["measured_interference_error_se_m"]
    assert (tmp_path / "o" / "report.html").exists()
