"""``tofhil compare`` and ``tofhil diagnose`` on bad input and on real-capture trouble:
saturation, masks, cross-sections, colour scales. In-process CLI runs on 80 x 60 sessions."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from tests import straylight_synthetic as syn
from tests.cli_in_process import run_cli
from tofhil.demod import taps_from_signal
from tofhil.frames import RawFrame
from tofhil.session import SessionWriter



def run(capsys, *args) -> tuple[int, str, str]:
    code = run_cli(*args)
    cap = capsys.readouterr()
    return code, cap.out, cap.err


def _write(path: Path, taps: np.ndarray, n: int = 2) -> Path:
    with SessionWriter(path, syn.CAMERA, device={"model": "synthetic"}) as w:
        for i in range(n):
            w.append(RawFrame(taps=taps.astype(np.float32), freq_hz=syn.FREQ, theta_rad=syn.THETA,
                              integration_time_s=1e-3, camera=syn.CAMERA, sequence=i, timestamp_s=0.01 * i))
    return path


@pytest.fixture(scope="module")
def sessions(tmp_path_factory):
    d = tmp_path_factory.mktemp("cmpcli")
    s, _ = syn.scene_signal(0.05)
    taps = taps_from_signal(np.abs(s)[None], np.angle(s)[None], np.full((1, syn.H, syn.W), 5.0), syn.THETA)
    _write(d / "b.h5", taps)
    # the ADC's top: below the largest taps of 70 % of the card's pixels (the wall stays below 6 DN)
    clip = float(np.quantile(taps.max(axis=(0, 1))[syn.CARD], 0.3))
    assert clip > 6.0
    _write(d / "clipped.h5", np.minimum(taps, clip))
    (d / "clip.txt").write_text(repr(clip))
    _write(d / "nan.h5", np.full_like(taps, np.nan))
    return d


def _one_error_line(code: int, err: str) -> str:
    assert code == 2, err
    assert "Traceback" not in err
    text = " ".join(ln.strip() for ln in err.split("error:", 1)[-1].splitlines())
    assert err.count("error:") == 1, err  # one message (rich may wrap it), after any progress lines
    return text


def test_saturated_pixels_are_excluded_and_reported(sessions, tmp_path, capsys):
    d = sessions
    card = f"{syn.CARD[1].start},{syn.CARD[0].start},{syn.CARD[1].stop},{syn.CARD[0].stop}"
    code, out, err = run(capsys, "compare", d / "clipped.h5", d / "b.h5", "--out", tmp_path / "r", "--roi", card)
    assert code == 0, err
    m = json.loads((tmp_path / "r" / "metrics.json").read_text())
    r = m["variants"]["measured"]["regions"][f"roi_{card.replace(',', '_')}"]
    # Independent count: pixels of the card whose unclipped taps exceed the clip level.
    s, _ = syn.scene_signal(0.05)
    taps = taps_from_signal(np.abs(s)[None], np.angle(s)[None], np.full((1, syn.H, syn.W), 5.0), syn.THETA)
    clipped = taps.max(axis=(0, 1)) >= float((d / "clip.txt").read_text())
    want = clipped[syn.CARD].mean()
    assert 0.6 < want < 0.8
    assert r["saturated_fraction_a"] == pytest.approx(want)
    assert r["saturation_dominated"] is True
    assert r["depth_residual_m"]["n"] == (~clipped[syn.CARD]).sum()
    # the clipped pixels are out, so what is left of the card compares exactly
    assert abs(r["depth_residual_m"]["median"]) < 1e-4
    assert m["variants"]["measured"]["regions"]["all"]["saturated_fraction_a"] == pytest.approx(clipped.mean())
    html = (tmp_path / "r" / "report.html").read_text()
    assert "saturated in A" in html and "dominated by saturation" in html
    assert "saturated in A" in out  # the CLI says it too


def test_mask_cross_section_and_half_open_roi(sessions, tmp_path, capsys):
    d = sessions
    mask = np.zeros((syn.H, syn.W), bool)
    mask[syn.SQUARE] = True
    np.save(tmp_path / "square.npy", mask)
    code, _, err = run(capsys, "compare", d / "clipped.h5", d / "b.h5", "--out", tmp_path / "r",
                       "--mask", tmp_path / "square.npy", "--column", "50", "--roi", "4,4,16,12")
    assert code == 0, err
    m = json.loads((tmp_path / "r" / "metrics.json").read_text())
    regions = m["variants"]["measured"]["regions"]
    assert regions["mask_square"]["pixels"] == mask.sum()
    assert regions["roi_4_4_16_12"]["pixels"] == 12 * 8  # X1, Y1 exclusive
    assert m["settings"]["cross_section"] == {"axis": "column", "index": 50}
    assert "pixel column 50" in (tmp_path / "r" / "report.html").read_text()
    code, _, err = run(capsys, "compare", d / "b.h5", d / "b.h5", "--out", tmp_path / "r2", "--row", "60")
    assert "--row" in _one_error_line(code, err) and not (tmp_path / "r2").exists()


def test_bad_input_is_one_line_and_leaves_nothing(sessions, tmp_path, capsys):
    d = sessions
    code, _, err = run(capsys, "compare", d / "b.h5", d / "b.h5", "--out", tmp_path / "r", "--threshold", "-1")
    assert "--threshold" in _one_error_line(code, err)
    assert not (tmp_path / "r").exists()
    # --out an existing file: refused, the file untouched
    f = tmp_path / "afile"
    f.write_text("keep")
    code, _, err = run(capsys, "compare", d / "b.h5", d / "b.h5", "--out", f)
    assert "is a file" in _one_error_line(code, err) and f.read_text() == "keep"
    code, _, err = run(capsys, "diagnose", d / "b.h5", "--scene", "bench_demo", "--out", f)
    assert "is a file" in _one_error_line(code, err) and f.read_text() == "keep"
    # all-NaN capture: refused, naming it; no empty report
    code, _, err = run(capsys, "compare", d / "nan.h5", d / "b.h5", "--out", tmp_path / "r")
    line = _one_error_line(code, err)
    assert "nan.h5" in line and "no valid pixel" in line
    assert not (tmp_path / "r").exists()


def test_failed_diagnose_leaves_no_folder(sessions, tmp_path, capsys):
    one = _write(tmp_path / "one.h5", np.ones((1, 4, syn.H, syn.W)), n=1)
    out = tmp_path / "diag"
    for _ in range(2):  # the second run meets the same error, not an empty folder in its way
        code, _, err = run(capsys, "diagnose", one, "--scene", "bench_demo", "--out", out)
        assert "at least 2 frames" in _one_error_line(code, err)
        assert not out.exists()


def test_residual_scale_is_robust_in_the_report(tmp_path):
    # One pixel 2 m off must not set the residual colour scale: read the colourbar's range
    # back from the figure code (the same function the reports call).
    from tofhil.eval.reports import html as H

    rng = np.random.default_rng(0)
    res = rng.normal(0.0, 0.002, (syn.H, syn.W))
    res[3, 3] = 2.0
    lo, hi = H.symmetric_range([res * 1e3], floor=1e-3)
    assert hi < 6.0  # mm: 2-98 % of a 2 mm Gaussian is about 4 mm
    uri = H.figure_residual_maps([("r", res)])
    assert re.match(r"data:image/png;base64,", uri)


def test_report_shows_the_ghost_psfs_of_a_twin_with_a_lens_prescription(sessions, tmp_path, capsys):
    """B is a twin session of the bundled lens scene: compare's report draws the prescription's
    ghost PSFs and ghost table (eval/reports/optics.py); a plain session gets no lens section."""
    from tofhil.session import open_session
    from tofhil.sim.scene import load_scene, scene_to_yaml

    s, _ = syn.scene_signal(0.05)
    taps = taps_from_signal(np.abs(s)[None], np.angle(s)[None], np.full((1, syn.H, syn.W), 5.0), syn.THETA)
    text = scene_to_yaml(load_scene("dark_square_card_lens"))
    with SessionWriter(tmp_path / "twin.h5", syn.CAMERA, device={"model": "tofhil-sim"}, scene_text=text) as w:
        w.append(RawFrame(taps=taps.astype(np.float32), freq_hz=syn.FREQ, theta_rad=syn.THETA,
                          integration_time_s=1e-3, camera=syn.CAMERA))
    code, _, err = run(capsys, "compare", sessions / "b.h5", tmp_path / "twin.h5", "--out", tmp_path / "r")
    assert code == 0, err
    page = (tmp_path / "r" / "report.html").read_text()
    assert "Ghost PSFs" in page and "filter back-sensor" in page and "side B" in page
    from tofhil.eval.compare import twin_lens_camera

    with open_session(sessions / "b.h5") as a:
        assert twin_lens_camera(a) is None
