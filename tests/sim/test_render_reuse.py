"""Frame arrays reused between renders (render._FRAMES): never while a result refers to them,
and a reused frame renders exactly what a new one does."""

from __future__ import annotations

import dataclasses
import gc

import numpy as np

from tofhil.sim import render as render_mod
from tofhil.sim.render import render
from tofhil.sim.scene import load_scene

FIELDS = ("phasor", "power_w", "ambient_power_w", "radial_m", "object_id", "ambient_power_per_irradiance")


def _copy(res: render_mod.RenderResult) -> dict[str, np.ndarray]:
    return {k: getattr(res, k).copy() for k in FIELDS}


def _same(res: render_mod.RenderResult, ref: dict[str, np.ndarray]) -> None:
    for k in FIELDS:
        np.testing.assert_array_equal(getattr(res, k), ref[k], err_msg=k)


def test_a_held_result_is_never_reused() -> None:
    scene = load_scene("wall")
    a = render(scene, samples_per_pixel=1, bounces=0, subpixel=False)
    b = render(scene, samples_per_pixel=1, bounces=0, subpixel=False)
    c = render(scene, samples_per_pixel=1, bounces=0, subpixel=False)
    for x, y in ((a, b), (a, c), (b, c)):
        for k in FIELDS:
            assert not np.shares_memory(getattr(x, k), getattr(y, k)), k
    power = a.power_w                 # a view alone keeps its frame out of reuse
    del a
    gc.collect()
    d = render(scene, samples_per_pixel=1, bounces=0, subpixel=False)
    assert not np.shares_memory(d.power_w, power)


def test_a_reused_frame_renders_what_a_new_one_does() -> None:
    wall, corner = load_scene("wall"), load_scene("corner")
    cam = corner.camera
    render_mod._FRAMES._sets.clear()
    # new arrays: references to every result are kept, so nothing can be reused
    held = [render(s, camera=cam, **kw) for s, kw in
            ((corner, dict(samples_per_pixel=4, bounces=1)), (wall, dict(samples_per_pixel=1, subpixel=False)),
             (corner, dict(samples_per_pixel=4, bounces=1, pixels=np.eye(cam.height, cam.width, dtype=bool))))]
    refs = [_copy(r) for r in held]
    del held
    gc.collect()
    # the same renders on reused frames, each after a different scene filled them
    for _ in range(2):
        r = render(wall, camera=cam, samples_per_pixel=1, subpixel=False)
        _same(r, refs[1])
        del r
        r = render(corner, camera=cam, samples_per_pixel=4, bounces=1)
        _same(r, refs[0])
        del r
        r = render(corner, camera=cam, samples_per_pixel=4, bounces=1, pixels=np.eye(cam.height, cam.width, dtype=bool))
        _same(r, refs[2])
        del r
    assert render_mod._FRAMES._sets, "nothing was kept for reuse"


def test_camera_rays_kept_for_one_camera_render_every_pose_as_new_ones() -> None:
    """The sub-pixel camera rays of a camera are kept across renders (a fit renders one camera
    at many poses): a render with them kept equals one that made them, bit for bit, for a
    distorted lens, a turned pose and some pixels only."""
    from tofhil.sim import render as R
    from tofhil.sim.effects import EFFECTS

    sc = load_scene("bench_demo")
    cam = dataclasses.replace(sc.camera.scaled(0.4), dist=(0.08, -0.02, 0.001, 0.0, 0.0))
    sc = dataclasses.replace(sc, camera=cam, render=dataclasses.replace(sc.render, samples_per_pixel=4))
    turned = EFFECTS["pose"].apply_scene(sc, EFFECTS["pose"].validate({"rx": 0.012, "tz": 0.01}))
    mask = np.random.default_rng(5).random(cam.shape) < 0.2
    R._CAMERA_FRAME_RAYS.clear()
    R.render(sc, harmonics=(1, 3))                      # the camera's rays made (base pose)
    R.render(sc, harmonics=(1, 3), pixels=mask)
    warm = [R.render(turned, harmonics=(1, 3)), R.render(turned, harmonics=(1, 3), pixels=mask)]
    assert len(R._CAMERA_FRAME_RAYS) > 0
    R._CAMERA_FRAME_RAYS.clear()
    cold = [R.render(turned, harmonics=(1, 3)), R.render(turned, harmonics=(1, 3), pixels=mask)]
    for w, c in zip(warm, cold):
        assert np.array_equal(w.phasor, c.phasor) and np.array_equal(w.power_w, c.power_w)
    assert not np.array_equal(warm[0].phasor, R.render(sc, harmonics=(1, 3)).phasor)  # the pose moved the light
