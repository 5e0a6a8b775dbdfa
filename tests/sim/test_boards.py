"""Calibration boards: the printed pattern matches the board's corner points, specs validate,
and a board in a scene renders its pattern at its physical size."""

from __future__ import annotations

import numpy as np
import pytest

from tofhil.boards import TEXELS_PER_SQUARE, BoardSpec
from tofhil.errors import InputFileError
from tofhil.sim.scene import load_scene, scene_from_dict, scene_from_yaml, scene_to_yaml


def test_checkerboard_pattern_has_corners_where_the_corner_points_say():
    spec = BoardSpec.parse("checkerboard:5x4:0.02")
    img = spec.pattern()
    m = spec.margin_texels
    assert img.shape == (4 * TEXELS_PER_SQUARE + 2 * m, 5 * TEXELS_PER_SQUARE + 2 * m)
    assert spec.size_m == pytest.approx((0.02 * 7, 0.02 * 6))
    # every inner corner: the four texels around it alternate ink / paper
    for x, y, _ in spec.corner_points():
        c, r = m + int(round(x / spec.texel_m)), m + int(round(y / spec.texel_m))
        quad = img[r - 1:r + 1, c - 1:c + 1]
        assert quad[0, 0] == quad[1, 1] != quad[0, 1] == quad[1, 0]
    assert img[m, m] == 0.0                    # top-left square is ink
    assert np.all(img[:m] == 1) and np.all(img[:, :m] == 1)  # white margin


def test_charuco_pattern_is_detected_at_its_corner_points():
    import cv2

    spec = BoardSpec.parse("charuco:5x4:0.04:0.03")
    img8 = (spec.pattern() * 255).astype(np.uint8)
    corners, ids, _, _ = cv2.aruco.CharucoDetector(spec.cv_board()).detectBoard(img8)
    # pixel centres at integers: texel edge k is at k - 0.5
    board_xy = (corners.reshape(-1, 2) + 0.5 - spec.margin_texels) * spec.texel_m
    assert len(ids) == 12
    assert np.abs(board_xy - spec.corner_points()[ids.ravel(), :2]).max() < 0.01 * spec.square_m


@pytest.mark.parametrize("text, field", [
    ("checkerboard:6x6:0.03", "target.grid"),            # symmetric under a half turn
    ("charuco:5x4:0.04:0.05", "target.marker_m"),        # marker larger than the square
    ("charuco:20x20:0.04:0.03", "target.grid"),          # more markers than DICT_4X4_50 has
    ("aruco:3x2:0.04:0.01:DICT_9X9_1", "target.dictionary"),
    ("hexagon:3x2:0.04", "target.type"),
    ("checkerboard:9x6", "target"),
])
def test_bad_specs_name_the_field(text, field):
    with pytest.raises(InputFileError) as e:
        BoardSpec.parse(text)
    assert e.value.field == field


def test_spec_round_trips_through_a_mapping():
    for text in ("checkerboard:9x6:0.03", "charuco:7x5:0.04:0.03:DICT_5X5_100", "aruco:4x3:0.04:0.01"):
        spec = BoardSpec.parse(text)
        assert BoardSpec.from_dict(spec.to_dict()) == spec


SCENE = """
camera: {width: 40, height: 30, hfov_deg: 60}
emitter: {power_w: 0.1}
materials: {paper: {reflectance: 0.5}}
objects:
  - name: board
    type: board
    target: {type: checkerboard, grid: [3, 2], square_m: 0.2, margin_m: 0.0, reflectance: [0.1, 0.9]}
    pose: {position: [0, 0, 1.0]}
sensor: {freq_hz: [20.0e6]}
"""


def test_board_renders_its_pattern_at_its_size():
    from tofhil.sim.render import render

    scene = scene_from_yaml(SCENE)
    assert scene.objects[0].board.size_m == pytest.approx((0.6, 0.4))
    res = render(scene, freq_hz=[20e6])
    cam = scene.camera
    # the board covers x in [-0.3, 0.3], y in [-0.2, 0.2] at z = 1: pixels whose centre ray
    # hits inside it and not within a pixel of an edge see ink (0.1) or paper (0.9)
    x = cam.rays[..., 0] / cam.rays[..., 2]
    y = cam.rays[..., 1] / cam.rays[..., 2]
    inside = (np.abs(x) < 0.3) & (np.abs(y) < 0.2)
    assert np.array_equal(res.object_id >= 0, inside)
    col, row = np.floor((x + 0.3) / 0.2), np.floor((y + 0.2) / 0.2)
    ink = inside & ((col + row) % 2 == 0)
    paper = inside & ((col + row) % 2 == 1)
    # pixels one cell apart see ink and paper at nearly the same geometry: their power ratio
    # is the pattern's reflectance ratio (the 4-neighbours of an ink pixel in the paper cell)
    p = res.power_w
    ratios = [p[r, c] / p[r, c + 1] for r, c in zip(*np.nonzero(ink)) if c + 1 < cam.width and paper[r, c + 1]]
    assert ratios and np.median(ratios) == pytest.approx(0.1 / 0.9, rel=0.05)


def test_board_scene_round_trips_and_defaults_to_a_matte_material():
    scene = scene_from_yaml(SCENE)
    assert scene.materials[scene.objects[0].material].reflectance == 1.0
    again = scene_from_yaml(scene_to_yaml(scene))
    assert again.objects[0].params == scene.objects[0].params


def test_bundled_board_scene_loads():
    scene = load_scene("board")
    assert scene.objects[0].board.kind == "checkerboard"


def test_board_with_a_bad_target_names_the_field():
    d = {"camera": {"width": 4, "height": 3, "hfov_deg": 60}, "emitter": {"power_w": 0.1},
         "materials": {"m": 0.5}, "sensor": {"freq_hz": [20e6]},
         "objects": [{"type": "board", "target": {"type": "checkerboard", "grid": [3, 2]}}]}
    with pytest.raises(InputFileError) as e:
        scene_from_dict(d)
    assert e.value.field == "objects[0].target.square_m"
