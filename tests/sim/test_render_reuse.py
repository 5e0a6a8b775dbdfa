"""Frame arrays reused between renders (render._FRAMES): never while a result refers to them,
and a reused frame renders exactly what a new one does."""

from __future__ import annotations

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
