"""Multipath shares by bounce and by source object (sim/multipath.py, the renderer's share rows)."""

from __future__ import annotations

import numpy as np
import pytest

from tofhil.camera import CameraModel
from tofhil.sim.multipath import multipath_shares, shares_from_render
from tofhil.sim.render import render
from tofhil.sim.scene import load_scene, scene_from_dict

CAM = CameraModel(width=16, height=12, fx=11.6667, fy=11.6667, cx=7.5, cy=5.5, pixel_pitch_m=240e-6)


@pytest.fixture(scope="module")
def corner() -> tuple:
    scene = load_scene("corner")
    kw = dict(camera=CAM, bounces=2, samples_per_pixel=16, subpixel=False, freq_hz=[44e6], separate_direct=True)
    with_shares = render(scene, multipath_shares=True, **kw)
    plain = render(scene, **kw)
    return scene, with_shares, plain


def test_shares_sum_to_one_and_leave_the_render_unchanged(corner: tuple) -> None:
    scene, res, plain = corner
    s = shares_from_render(res, [o.name for o in scene.objects])
    lit = np.isfinite(s.by_bounce[0])
    assert lit.all()
    assert np.allclose(s.by_bounce.sum(axis=0), 1.0, atol=1e-12)
    assert np.allclose(s.by_object.sum(axis=0), 1.0, atol=1e-12)
    # the rows are sums of the same paths: total power and phasors as without shares
    assert np.allclose(res.share_power_w.sum(axis=(0, 1)), plain.power_w, rtol=1e-12)
    assert np.allclose(res.phasor, plain.phasor, rtol=1e-12, atol=1e-30)
    assert np.allclose(res.phasor_direct, plain.phasor_direct, rtol=1e-12, atol=1e-30)
    # each bounce row is that bounce's light: row 0 is the direct phasor's power at 0 Hz
    assert np.allclose(s.by_bounce[0] * s.power_w, np.abs(render(scene, camera=CAM, bounces=0, samples_per_pixel=16,
                                                                  subpixel=False, freq_hz=[0.0]).phasor[0, 0]),
                       rtol=1e-9)


def test_light_from_the_seen_wall_is_the_direct_light(corner: tuple) -> None:
    """A plane cannot light itself: the light whose last vertex before the seen point is on the
    seen wall is exactly the direct light (every sample sees the pixel centre's wall)."""
    scene, res, _ = corner
    s = shares_from_render(res, [o.name for o in scene.objects])
    own = np.take_along_axis(s.by_object, res.object_id[None].astype(np.int64), axis=0)[0]
    assert np.allclose(own, s.by_bounce[0], atol=1e-12)
    assert np.all(s.by_bounce[1] > 0) and np.all(s.by_bounce[2] > 0)


def test_indirect_share_grows_toward_the_concave_edges(corner: tuple) -> None:
    """The seen point's distance to the nearest edge of the corner (where two walls meet):
    the nearer the edge, the larger the indirect share (rank correlation clearly negative)."""
    from scipy.stats import spearmanr

    scene, res, _ = corner
    s = shares_from_render(res, [o.name for o in scene.objects])
    R, t = scene.camera_pose[:3, :3], scene.camera_pose[:3, 3]
    p = (CAM.rays.reshape(-1, 3) * res.radial_m.reshape(-1, 1)) @ R.T + t
    coords = np.sort(np.abs(p), axis=1)              # [~0 (on the wall), nearer edge, farther edge]
    assert np.all(coords[:, 0] < 1e-6)
    rho = spearmanr(coords[:, 1], s.indirect.ravel()).statistic
    assert rho < -0.5
    near, far = coords[:, 1] < 0.15, coords[:, 1] > 0.4
    assert s.indirect.ravel()[near].mean() > 1.3 * s.indirect.ravel()[far].mean()


def test_a_single_plane_gets_only_direct_light() -> None:
    scene = scene_from_dict({
        "camera": {"width": 8, "height": 6, "fx": 8.0, "fy": 8.0, "cx": 3.5, "cy": 2.5, "f_number": 1.2},
        "emitter": {"power_w": 0.3},
        "materials": {"white": {"reflectance": 0.9}},
        "objects": [{"name": "wall", "type": "plane", "size": [3.0, 3.0], "material": "white",
                     "pose": {"position": [0, 0, 1.0]}}],
        "sensor": {"freq_hz": [20e6], "taps": 4},
        "render": {"bounces": 3, "samples_per_pixel": 4},
    })
    s = multipath_shares(scene)
    assert s.by_bounce.shape == (4, 6, 8) and s.object_names == ("wall",)
    assert np.allclose(s.by_bounce[0], 1.0, rtol=0, atol=1e-15)
    assert np.all(s.by_bounce[1:] == 0.0)            # no path reaches the emitter after a bounce
    assert np.allclose(s.by_object[0], 1.0, rtol=0, atol=1e-15)


def test_the_wavefront_loop_gives_the_same_shares(monkeypatch: pytest.MonkeyPatch, corner: tuple) -> None:
    """The per-bounce numpy loop (textures, tabulated beams) and the fused kernel agree."""
    scene, res, _ = corner
    monkeypatch.setenv("TOFHIL_RENDER_WAVEFRONT", "1")
    wf = render(scene, camera=CAM, bounces=2, samples_per_pixel=16, subpixel=False, freq_hz=[44e6],
                multipath_shares=True)
    assert np.allclose(wf.share_power_w, res.share_power_w, rtol=1e-6, atol=1e-9 * res.share_power_w.max())


def test_simulate_report_of_a_correlation_scene_and_its_refusal(tmp_path) -> None:
    """`tofhil simulate --report` on a (correlation) scene: the shares' means in report.json
    (the corner: 0 < indirect < 1); an existing report is not overwritten and no session is
    written then."""
    import json

    import yaml

    from tests.cli_in_process import run_cli
    from tofhil.sim.scene import scene_to_yaml

    scene = load_scene("corner", overrides={"camera": {"width": 16, "height": 12, "fx": 11.6667, "fy": 11.6667,
                                                       "cx": 7.5, "cy": 5.5, "pixel_pitch_m": 240e-6},
                                            "render": {"samples_per_pixel": 4, "bounces": 1}})
    path = tmp_path / "c.yaml"
    path.write_text(scene_to_yaml(scene))
    assert yaml.safe_load(path.read_text())["render"]["bounces"] == 1
    assert run_cli("simulate", path, "--out", tmp_path / "c.h5", "--report", tmp_path / "rep") == 0
    rep = json.loads((tmp_path / "rep" / "report.json").read_text())["multipath_shares"]
    assert len(rep["mean_share_by_bounce"]) == 2 and 0.1 < rep["mean_share_by_bounce"][1] < 0.6
    assert sum(rep["mean_share_by_object"].values()) == pytest.approx(1.0, abs=1e-9)
    assert run_cli("simulate", path, "--out", tmp_path / "d.h5", "--report", tmp_path / "rep") == 2
    assert not (tmp_path / "d.h5").exists()
