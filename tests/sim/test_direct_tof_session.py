"""Direct-ToF sessions: `tofhil simulate` on a direct_tof scene writes histograms/ and the
depth of their peaks; readers that need taps refuse in one line; the report shows the shares."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from tofhil.errors import InputFileError
from tofhil.session import open_session
from tofhil.sim.scene import load_scene, scene_to_yaml
from tests.cli_in_process import run_cli

SMALL = {"camera": {"width": 16, "height": 12, "fx": 11.6667, "fy": 11.6667, "cx": 7.5, "cy": 5.5,
                    "pixel_pitch_m": 240e-6},
         "render": {"samples_per_pixel": 4, "bounces": 1}}


@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory) -> tuple:
    tmp = tmp_path_factory.mktemp("dtof")
    scene = load_scene("corner_direct", overrides=SMALL)
    path = tmp / "corner_direct_small.yaml"
    path.write_text(scene_to_yaml(scene))
    code = run_cli("simulate", path, "--out", tmp / "d.h5", "--frames", "2", "--report", tmp / "rep")
    assert code == 0
    return scene, tmp


def test_session_holds_histograms_and_the_peak_depth(session: tuple) -> None:
    scene, tmp = session
    cfg = scene.direct_tof
    with open_session(tmp / "d.h5") as s:
        assert s.n_frames == 2 and s.has_histograms and not s.has_raw and s.device["kind"] == "direct_tof"
        assert s.bin_width_s == cfg.bin_width_s and s.t0_s == cfg.t0_s
        assert np.allclose(s.histogram_edges_s(), cfg.edges_s)
        h0, h1 = s.histogram_frame(0), s.histogram_frame(1)
        assert h0["counts"].shape == (cfg.bins, 12, 16)
        assert not np.array_equal(h0["counts"], h1["counts"])      # independent counts per frame
        # one count per cycle and dead time at most: a frame's counts per pixel <= cycles
        assert h0["counts"].sum(axis=0).max() <= cfg.cycles_per_frame
        d = s.depth_frame(0)
        assert d.valid.all()
        assert np.array_equal(d.radial_m, h0["peak_distance_m"][0].astype(np.float32))
        # the strongest peak is the direct return: the seen wall's radial distance within 1 cm
        from tofhil.sim.render import render

        truth = render(scene, freq_hz=[0.0], samples_per_pixel=1, bounces=0, subpixel=False).radial_m
        assert np.median(np.abs(d.radial_m - truth)) < 0.01


def test_readers_that_need_taps_refuse_in_one_line(session: tuple, capsys: pytest.CaptureFixture) -> None:
    _, tmp = session
    with open_session(tmp / "d.h5") as s:
        with pytest.raises(InputFileError) as e:
            s.raw_frame(0)
    assert e.value.field == "raw/taps" and "direct-ToF" in str(e.value)
    capsys.readouterr()
    assert run_cli("depth", tmp / "d.h5", "--out", tmp / "depth.h5") == 2
    err = capsys.readouterr().err
    assert "raw/taps" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not (tmp / "depth.h5").exists()
    # diagnosis fits the correlation twin: a histogram session is refused, nothing left behind
    assert run_cli("diagnose", tmp / "d.h5", "--scene", "corner", "--out", tmp / "diag") == 2
    err = capsys.readouterr().err
    assert "histograms" in err and "Traceback" not in err
    assert not (tmp / "diag").exists()


def test_a_histogram_session_without_its_bin_width_is_refused(session: tuple, tmp_path) -> None:
    _, tmp = session
    bad = tmp_path / "bad.h5"
    bad.write_bytes((tmp / "d.h5").read_bytes())
    with h5py.File(bad, "a") as f:
        del f["histograms"].attrs["bin_width_s"]
    with pytest.raises(InputFileError) as e:
        open_session(bad)
    assert e.value.field == "histograms.bin_width_s"


def test_report_shows_where_the_light_comes_from(session: tuple) -> None:
    import json

    _, tmp = session
    page = (tmp / "rep" / "report.html").read_text()
    assert "Where the light comes from" in page and "Direct ToF: histograms" in page
    rep = json.loads((tmp / "rep" / "report.json").read_text())
    shares = rep["multipath_shares"]
    assert sum(shares["mean_share_by_bounce"]) == pytest.approx(1.0, abs=1e-9)
    assert sum(shares["mean_share_by_object"].values()) == pytest.approx(1.0, abs=1e-9)
    assert 0.1 < shares["mean_share_by_bounce"][1] < 0.5          # the corner's one-bounce light
    assert rep["direct_tof"]["pixels_with_peak"] == 16 * 12
