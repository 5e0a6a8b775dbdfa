"""Renderer options against closed forms: transient, subpixel mixing, thin lens, textures,
glossy lobe, ambient light, beam tables, distortion, meshes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tofhil.camera import CameraModel
from tofhil.demod import phase_to_distance, wrapped_phase
from tofhil.sim.render import pixel_area_normalized, render
from tofhil.sim.scene import load_scene, scene_from_dict

F_HZ = 44.0e6


def scene_dict(objects, materials=None, camera=None, emitter=None, **extra) -> dict:
    d = {"camera": camera or {"width": 24, "height": 18, "fx": 20.0, "fy": 20.0, "cx": 11.5, "cy": 8.5,
                              "pixel_pitch_m": 50e-6},
         "emitter": emitter or {"power_w": 1.0},
         "materials": materials or {"white": {"reflectance": 0.8}},
         "objects": objects, "sensor": {"freq_hz": [F_HZ]}}
    d.update(extra)
    return d


def wall(z=1.0, size=20.0, material="white", name="wall", x=0.0):
    return {"name": name, "type": "plane", "size": [size, size], "material": material,
            "pose": {"position": [x, 0.0, z]}}


def lambert_power(cam: CameraModel, z: float, rho: float, n: float = 1.0, power: float = 1.0,
                  f_number: float = 1.2) -> np.ndarray:
    """Closed-form pixel power of a Lambertian fronto-parallel plane, co-located cos^n emitter."""
    cos_a = cam.ray_z
    irr = power * (n + 1) / (2 * math.pi) * cos_a ** n * cos_a / (z / cos_a) ** 2
    f = cam.fx * cam.pixel_pitch_m
    return rho * irr / math.pi * math.pi * (f / (2 * f_number)) ** 2 * cos_a ** 4 / (cam.fx * cam.fy)


def test_transient_histogram_conserves_power_and_puts_it_at_2r() -> None:
    scene = scene_from_dict(scene_dict([wall(1.5)]))
    edges = np.arange(2.9, 4.5, 0.002)
    res = render(scene, transient_bins=edges)
    np.testing.assert_allclose(res.transient.sum(axis=0), res.power_w, rtol=1e-12)
    expected_bin = np.searchsorted(edges, 2 * res.radial_m, side="right") - 1
    assert np.array_equal(res.transient.argmax(axis=0), expected_bin)
    # With multipath: nothing arrives before the direct return (causality), all power binned.
    corner = load_scene("corner")
    cam = corner.camera.scaled(0.1)
    r2 = render(corner, camera=cam, samples_per_pixel=16, bounces=2, transient_bins=200, subpixel=False)
    np.testing.assert_allclose(r2.transient.sum(axis=0), r2.power_w, rtol=1e-9)
    centres = 0.5 * (r2.transient_edges_m[1:] + r2.transient_edges_m[:-1])
    width = r2.transient_edges_m[1] - r2.transient_edges_m[0]
    early = centres[:, None, None] < (2 * r2.radial_m - width)[None]
    assert r2.transient[early].sum() == 0.0
    assert r2.transient[~early].sum() > 0


def test_direct_part_of_a_multipath_render_equals_a_direct_only_render() -> None:
    corner = load_scene("corner")
    cam = corner.camera.scaled(0.1)
    a = render(corner, camera=cam, samples_per_pixel=4, bounces=2, separate_direct=True, subpixel=False)
    b = render(corner, camera=cam, samples_per_pixel=4, bounces=0, subpixel=False)
    np.testing.assert_allclose(a.phasor_direct, b.phasor, rtol=1e-12)
    assert np.mean(np.abs(a.phasor_indirect) > 0) > 0.9    # 4 samples: a few may all escape


def test_subpixel_sampling_mixes_a_depth_edge_by_area() -> None:
    # A near card whose edge (x = 0) cuts column 11 (cx = 11) exactly in half.
    cam = {"width": 23, "height": 5, "fx": 40.0, "fy": 40.0, "cx": 11.0, "cy": 2.0, "pixel_pitch_m": 50e-6}
    objs = [wall(1.0), {"name": "card", "type": "plane", "size": [2.0, 2.0], "material": "white",
                        "pose": {"position": [1.0, 0.0, 0.5]}}]
    scene = scene_from_dict(scene_dict(objs, camera=cam))
    res = render(scene, samples_per_pixel=1024, seed=2)
    only_wall = render(scene_from_dict(scene_dict([wall(1.0)], camera=cam)), samples_per_pixel=1024, seed=2)
    only_card = render(scene_from_dict(scene_dict([wall(0.5)], camera=cam)), samples_per_pixel=1024, seed=2)
    mixed = res.phasor[0, 0, 2, 11]
    expect = 0.5 * only_wall.phasor[0, 0, 2, 11] + 0.5 * only_card.phasor[0, 0, 2, 11]
    assert abs(mixed / expect - 1) < 0.01
    d = phase_to_distance(wrapped_phase(mixed), F_HZ)
    assert 0.5 < d < 1.0                                         # a flying pixel between the surfaces
    assert res.object_id[2, 10] == 0 and res.object_id[2, 12] == 1


def test_thin_lens_in_focus_equals_pinhole_and_defocus_blurs_by_the_circle_of_confusion() -> None:
    pitch, fx, n_f, z_f, z = 2.8e-6, 1000.0, 1.0, 1.0, 0.2
    cam = {"width": 60, "height": 1, "fx": fx, "fy": fx, "cx": 29.5, "cy": 0.0, "pixel_pitch_m": pitch}
    focused = scene_from_dict(scene_dict([wall(z_f)], camera={**cam, "f_number": n_f, "focus_distance_m": z_f}))
    pinhole = scene_from_dict(scene_dict([wall(z_f)], camera={**cam, "f_number": n_f}))
    a = render(focused, samples_per_pixel=64, subpixel=False)
    b = render(pinhole)
    np.testing.assert_allclose(a.phasor, b.phasor, rtol=1e-9)   # Fermat: equal paths to the focus
    # A half-plane card (edge at x = 0) out of focus at z = 0.2 m, nothing behind it.
    card = [{"name": "card", "type": "plane", "size": [2.0, 2.0], "material": "white",
             "pose": {"position": [1.0, 0.0, z]}}]
    blurred = render(scene_from_dict(scene_dict(card, camera={**cam, "f_number": n_f, "focus_distance_m": z_f})),
                     samples_per_pixel=4096, seed=1)
    full = lambert_power(CameraModel(**{k: v for k, v in cam.items()}), z, 0.8, f_number=n_f)
    radius_px = fx * (fx * pitch / (2 * n_f)) * abs(1 / z - 1 / z_f)   # blur-disk radius: 5.6 px

    def disk_esf(s):  # fraction of a unit disk with x < s
        s = np.clip(s, -1, 1)
        return 1 - (np.arccos(s) - s * np.sqrt(1 - s * s)) / np.pi

    u = np.arange(60)
    sub = (np.arange(64) + 0.5) / 64 - 0.5                      # box filter of the pixel
    expect = disk_esf((u[:, None] + sub[None, :] - 29.5) / radius_px).mean(axis=1)
    got = blurred.power_w[0] / full[0]
    assert np.abs(got - expect).max() < 0.02
    assert got[20] < 0.01 and got[40] > 0.99 and 0.3 < got[29] < 0.5


def test_checker_and_image_textures_scale_the_reflectance(tmp_path) -> None:
    img = np.array([[1.0, 0.25], [0.5, 0.125]])
    np.save(tmp_path / "albedo.npy", img)
    cam = {"width": 40, "height": 40, "fx": 20.0, "fy": 20.0, "cx": 19.5, "cy": 19.5, "pixel_pitch_m": 50e-6}
    mats = {"white": {"reflectance": 1.0},
            "img": {"reflectance": 0.8, "texture": {"type": "image", "file": str(tmp_path / "albedo.npy")}},
            "chk": {"reflectance": 0.5, "texture": {"type": "checker", "size_m": 0.25, "reflectance": [0.9, 0.3]}}}
    # The image spans a 2 m x 2 m plane at 1 m: one image pixel per view quadrant.
    ref = render(scene_from_dict(scene_dict([wall(1.0, 2.0, "white")], mats, cam)))
    res = render(scene_from_dict(scene_dict([wall(1.0, 2.0, "img")], mats, cam)))
    ratio = res.power_w / ref.power_w
    np.testing.assert_allclose(ratio[:20, :20], 0.8 * img[0, 0])
    np.testing.assert_allclose(ratio[:20, 20:], 0.8 * img[0, 1])
    np.testing.assert_allclose(ratio[20:, :20], 0.8 * img[1, 0])
    np.testing.assert_allclose(ratio[20:, 20:], 0.8 * img[1, 1])
    # Checker cells of 0.25 m at 1 m span 5 px; the plane's local z = 0 lies on a cell boundary.
    res = render(scene_from_dict(scene_dict([wall(1.0, 2.0, "chk")], mats, cam)))
    ratio = res.power_w / ref.power_w
    assert set(np.round(np.unique(ratio), 9)) == {0.9, 0.3}
    x = (np.arange(40) - 19.5) / 20.0                            # world x of the column centres
    cells = np.floor(x / 0.25).astype(int)
    np.testing.assert_allclose(ratio[21], np.where((cells + 0) % 2 == 0, 0.9, 0.3))


def test_glossy_lobe_matches_normalised_phong() -> None:
    rho_s, expo = 0.5, 10.0
    mats = {"gloss": {"reflectance": 0.0, "glossy": {"reflectance": rho_s, "exponent": expo}},
            "white": {"reflectance": 1.0}}
    g = render(scene_from_dict(scene_dict([wall(1.0, material="gloss")], mats)))
    w = render(scene_from_dict(scene_dict([wall(1.0, material="white")], mats)))
    # Co-located light and camera: the mirror direction makes 2*theta with the view direction.
    cos_2t = np.cos(2 * np.arccos(scene_from_dict(scene_dict([wall()])).camera.ray_z))
    expect = math.pi * rho_s * (expo + 2) / (2 * math.pi) * np.clip(cos_2t, 0, None) ** expo
    np.testing.assert_allclose(g.power_w / w.power_w, expect, rtol=1e-9)


def test_ambient_power_matches_camera_equation() -> None:
    scene = scene_from_dict(scene_dict([wall(2.0)], ambient_irradiance_w_m2=3.0))
    res = render(scene)
    cam = scene.camera
    f = cam.fx * cam.pixel_pitch_m
    expect = 0.8 * 3.0 / math.pi * math.pi * (f / 2.4) ** 2 * cam.ray_z ** 4 / (cam.fx * cam.fy)
    np.testing.assert_allclose(res.ambient_power_w, expect, rtol=1e-12)


def test_beam_table_matches_equivalent_cos_n() -> None:
    th = np.linspace(0, 90, 901)
    table = {"type": "table", "theta_deg": th.tolist(), "relative_intensity": np.cos(np.radians(th)).tolist()}
    a = render(scene_from_dict(scene_dict([wall()], emitter={"power_w": 1.0, "profile": table})))
    b = render(scene_from_dict(scene_dict([wall()], emitter={"power_w": 1.0, "profile": {"type": "cos_n", "n": 1}})))
    np.testing.assert_allclose(a.power_w, b.power_w, rtol=1e-4)


def test_distorted_camera_gives_exact_ranges_and_pixel_solid_angles() -> None:
    cam_d = {"width": 24, "height": 18, "fx": 20.0, "fy": 20.0, "cx": 11.5, "cy": 8.5, "pixel_pitch_m": 50e-6,
             "dist": [-0.2, 0.05, 0.001, -0.002, 0.0]}
    scene = scene_from_dict(scene_dict([wall(1.0)], camera=cam_d))
    res = render(scene)
    truth = 1.0 / scene.camera.ray_z
    assert np.abs(phase_to_distance(wrapped_phase(res.phasor[0, 0]), F_HZ) - truth).max() < 1e-4
    # Pixel area in normalised coordinates: compare with the shoelace area of the undistorted corners.
    cam = scene.camera
    v, u = 8.0, 20.0
    cu = np.array([u - 0.5, u + 0.5, u + 0.5, u - 0.5])
    cv = np.array([v - 0.5, v - 0.5, v + 0.5, v + 0.5])
    x, y = cam.undistort_normalized(cu, cv)
    shoelace = 0.5 * abs(np.dot(x, np.roll(y, 1)) - np.dot(y, np.roll(x, 1)))
    assert pixel_area_normalized(cam)[8, 20] == pytest.approx(shoelace, rel=1e-3)


def test_mesh_files_render_like_the_primitive(tmp_path) -> None:
    import trimesh

    box = trimesh.creation.box(extents=[0.4, 0.3, 0.2])
    cam = {"width": 20, "height": 16, "fx": 20.0, "fy": 20.0, "cx": 9.5, "cy": 7.5, "pixel_pitch_m": 50e-6}
    prim = render(scene_from_dict(scene_dict(
        [{"name": "b", "type": "box", "size": [0.4, 0.3, 0.2], "material": "white",
          "pose": {"position": [0.05, 0, 0.8], "rotation_deg": [10, 20, 30]}}], camera=cam)))
    for ext in ("obj", "ply", "stl", "glb"):
        path = tmp_path / f"box.{ext}"
        box.export(path)
        res = render(scene_from_dict(scene_dict(
            [{"name": "b", "type": "mesh", "file": str(path), "material": "white",
              "pose": {"position": [0.05, 0, 0.8], "rotation_deg": [10, 20, 30]}}], camera=cam)))
        np.testing.assert_allclose(res.radial_m, prim.radial_m, rtol=1e-6)
        np.testing.assert_allclose(res.power_w, prim.power_w, rtol=1e-5, atol=1e-20)
