"""Property-based: scenes with hostile values at every level either load as a valid scene or
fail with a TofhilError naming the file and the field -- never another exception."""

from __future__ import annotations

import copy
import math
from typing import Any

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tofhil.errors import TofhilError
from tofhil.sim.scene import Scene, scene_from_dict, scene_from_yaml

BASE: dict[str, Any] = {
    "name": "hostile",
    "params": {"d": 1.0, "rho": 0.5},
    "camera": {"preset": "holmlund_thesis", "width": 40, "height": 30, "cx": 19.5, "cy": 14.5,
               "pose": {"position": [0, 0, 0], "look_at": [0, 0, 1], "up": [0, -1, 0]}, "f_number": 1.4},
    "emitter": {"power_w": 0.5, "offset_m": [0.01, 0, 0], "axis": [0, 0, 1],
                "profile": {"type": "table", "theta_deg": [0, 30, 60], "relative_intensity": [1, 0.8, 0.1]},
                "waveform": {"harmonics": [[1, 1.0, 0.0], {"order": 3, "amplitude": 0.1, "phase_rad": 0.2}]}},
    "ambient_irradiance_w_m2": 1.0,
    "materials": {"wall": {"reflectance": "${rho}"},
                  "shiny": {"reflectance": 0.3, "glossy": {"reflectance": 0.2, "exponent": 20},
                            "texture": {"type": "checker", "size_m": 0.1, "reflectance": [0.7, 0.1]}}},
    "objects": [
        {"name": "wall", "type": "plane", "size": [3, 2], "material": "wall",
         "pose": {"position": [0, 0, "${d}"], "rotation_deg": [0, 5, 0]}},
        {"name": "box", "type": "box", "size": [0.1, 0.1, 0.1], "material": "shiny",
         "pose": {"matrix": [[1, 0, 0, 0.2], [0, 1, 0, 0], [0, 0, 1, 0.8], [0, 0, 0, 1]]}},
        {"name": "ball", "type": "sphere", "radius": 0.05, "subdivisions": 2, "material": "shiny"},
        {"name": "can", "type": "cylinder", "radius": 0.05, "height": 0.2, "sections": 16,
         "material": {"reflectance": 0.4}},
    ],
    "sensor": {"freq_hz": [20e6, 44e6], "taps": 4, "theta_deg": [0, 90, 180, 270], "integration_time_s": 3e-4,
               "wavelength_m": 850e-9, "quantum_efficiency": 0.3, "adc_bits": 12, "black_level_dn": 64,
               "full_well_e": 2e5, "read_noise_e": 20, "fixed_pattern": {"dsnu_e": 2, "prnu": 0.01, "seed": 1}},
    "effects": {"stray_light": {"weight": 0.02, "sigma_px": 5.0}, "wiggling": {"h3_amplitude": 0.02}},
    "render": {"samples_per_pixel": 2, "bounces": 1, "seed": 3, "subpixel": True, "sampler": "sobol"},
}

HOSTILE = st.one_of(
    st.sampled_from([math.nan, math.inf, -math.inf, -1, 0, -0.0, 1e308, -1e308, 10 ** 30, 2 ** 63, True, False,
                     None, "", "x", "${1/0}", "${9**9**9}", "${nope}", [], [math.nan], [1, 2], {}, {"k": 1},
                     8000, 20000, 100001, 1e-300, 0.5, 3]),
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(min_value=-(10 ** 40), max_value=10 ** 40),
    st.text(max_size=8),
    st.lists(st.floats(allow_nan=True, allow_infinity=True), max_size=5),
)


def _paths(node: Any, prefix: tuple = ()) -> list[tuple]:
    out = [prefix] if prefix else []
    if isinstance(node, dict):
        for k, v in node.items():
            out += _paths(v, prefix + (k,))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            out += _paths(v, prefix + (i,))
    return out


def _mappings(node: Any, prefix: tuple = ()) -> list[tuple]:
    out = [prefix] if isinstance(node, dict) else []
    if isinstance(node, dict):
        for k, v in node.items():
            out += _mappings(v, prefix + (k,))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            out += _mappings(v, prefix + (i,))
    return out


PATHS = _paths(BASE)
MAPPINGS = _mappings(BASE)


def _set(d: Any, path: tuple, value: Any) -> None:
    for k in path[:-1]:
        d = d[k]
    d[path[-1]] = value


def _get(d: Any, path: tuple) -> Any:
    for k in path:
        d = d[k]
    return d


def _check(d: dict) -> None:
    try:
        scene = scene_from_dict(d, source="hostile.yaml")
    except TofhilError as exc:
        assert exc.file == "hostile.yaml", str(exc)
        assert exc.field, f"no field named: {exc}"
        return
    assert isinstance(scene, Scene)
    # A scene that loads is usable: finite numbers everywhere the renderer reads them.
    assert np.all(np.isfinite(scene.camera_pose)) and all(np.all(np.isfinite(o.pose)) for o in scene.objects)
    assert all(math.isfinite(f) and f > 0 for f in scene.sensor.freq_hz)
    assert math.isfinite(scene.emitter.power_w) and scene.emitter.power_w >= 0  # 0: dark frames (issue 34)
    for o in scene.objects:
        for v in np.ravel([x for x in o.params.values() if not isinstance(x, str)]):
            assert math.isfinite(float(v)) and float(v) > 0
    assert all(0 <= m.reflectance <= 1 for m in scene.materials.values())
    assert scene.camera.width <= 100_000 and scene.camera.height <= 100_000


SETTINGS = settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@SETTINGS
@given(path=st.sampled_from(PATHS), value=HOSTILE)
def test_a_hostile_value_anywhere_gives_a_valid_scene_or_a_field_error(path, value) -> None:
    d = copy.deepcopy(BASE)
    _set(d, path, value)
    _check(d)


@SETTINGS
@given(path=st.sampled_from(MAPPINGS), key=st.one_of(st.text(min_size=1, max_size=12), st.integers()),
       value=HOSTILE)
def test_an_unknown_key_at_any_level_gives_a_valid_scene_or_a_field_error(path, key, value) -> None:
    d = copy.deepcopy(BASE)
    target = _get(d, path)
    if key in target:
        return
    target[key] = value
    _check(d)


@SETTINGS
@given(path=st.sampled_from(PATHS))
def test_a_removed_key_gives_a_valid_scene_or_a_field_error(path) -> None:
    d = copy.deepcopy(BASE)
    parent = _get(d, path[:-1])
    if isinstance(parent, dict):
        del parent[path[-1]]
    else:
        parent.pop(path[-1])
    _check(d)


@settings(max_examples=100, deadline=None)
@given(text=st.text(max_size=200))
def test_arbitrary_yaml_text_gives_a_scene_or_an_error(text) -> None:
    try:
        scene_from_yaml(text, source="t.yaml")
    except TofhilError as exc:
        assert exc.file == "t.yaml"
