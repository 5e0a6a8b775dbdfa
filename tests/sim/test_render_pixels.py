"""Rendering only some pixels (a fit's): each traced pixel equals the full render's, bit for
bit (same chunks, random streams and sample order); effects that move light between pixels
make the twin render the whole frame."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from tofhil.sim.render import render
from tofhil.sim.scene import load_scene
from tofhil.sim.twin import Twin


@pytest.fixture(scope="module")
def small_scene():
    sc = load_scene("bench_demo")
    cam = sc.camera.scaled(0.5)
    return dataclasses.replace(sc, camera=cam)


@pytest.mark.parametrize("kw", [dict(), dict(samples_per_pixel=1, subpixel=False),
                                dict(bounces=1, separate_direct=True, samples_per_pixel=2)])
def test_pixels_equal_full_render(small_scene, kw):
    h, w = small_scene.camera.shape
    mask = np.random.default_rng(3).random((h, w)) < 0.15
    full = render(small_scene, harmonics=(1, 3), **kw)
    part = render(small_scene, harmonics=(1, 3), pixels=mask, **kw)
    assert np.array_equal(full.phasor[..., mask], part.phasor[..., mask])
    assert np.array_equal(full.power_w[mask], part.power_w[mask])
    assert np.array_equal(full.radial_m[mask], part.radial_m[mask])
    assert np.array_equal(full.object_id[mask], part.object_id[mask])
    # the rest is untraced: no light, no hit, and fewer rays
    assert not np.any(part.phasor[..., ~mask]) and np.all(part.object_id[~mask] == -1)
    assert part.rays_traced < 0.5 * full.rays_traced
    if kw.get("separate_direct"):
        assert np.array_equal(full.phasor_indirect[..., mask], part.phasor_indirect[..., mask])


def test_pixels_of_a_distorted_camera(small_scene):
    # a lens-distortion fit makes a new camera every evaluation: its rays and pixel areas are
    # then computed on the pixels asked for only, each as on the whole grid
    cam = dataclasses.replace(small_scene.camera, dist=(0.08, -0.02, 0.001, 0.0, 0.0))
    mask = np.random.default_rng(4).random(cam.shape) < 0.1
    part = render(small_scene, camera=cam, pixels=mask)
    full = render(small_scene, camera=cam)
    assert np.array_equal(full.phasor[..., mask], part.phasor[..., mask])


def test_bad_pixel_mask_is_refused(small_scene):
    from tofhil.errors import TofhilError

    with pytest.raises(TofhilError, match="pixels"):
        render(small_scene, pixels=np.ones((3, 3), bool))


def test_twin_renders_pixels_only_when_exact(small_scene):
    h, w = small_scene.camera.shape
    mask = np.zeros((h, w), bool)
    mask[::7, ::5] = True
    twin = Twin(small_scene)
    local = twin.effects({"pose": {"rx": 0.002}, "wiggling": {"h3_amplitude": 0.05}})
    full = twin.expected_taps(local)
    part = twin.expected_taps(local, pixels=mask)
    assert np.array_equal(full[..., mask], part[..., mask])
    assert twin.pixel_local(local)
    # stray light moves light between pixels: the prediction on the mask needs the whole frame
    stray = twin.effects({"pose": {"rx": 0.002}, "stray_light": {"weight": 0.05, "sigma_px": 6.0}})
    assert not twin.pixel_local(stray)
    assert np.array_equal(twin.expected_taps(stray)[..., mask], twin.expected_taps(stray, pixels=mask)[..., mask])
