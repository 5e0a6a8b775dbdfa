"""Hidden-effect cases for the diagnosis sweep: for each effect of the library, a draw of
plausible hidden parameters from a random generator (the forms tests/eval/test_diagnose.py
hides too; the tests keep their own table with the tolerances they assert, so that no
benchmark loads a test module and no test depends on a benchmark).
"""

from __future__ import annotations

import math
from typing import Any, Callable

import numpy as np


def _sign(rng: np.random.Generator) -> float:
    return float(rng.choice([-1.0, 1.0]))


#: effect -> draw(rng) -> hidden parameters
CASES: dict[str, Callable[[np.random.Generator], dict[str, Any]]] = {
    "stray_light": lambda r: {"weight": r.uniform(0.02, 0.06), "sigma_px": r.uniform(5, 20),
                              "veil": r.uniform(0.002, 0.008)},
    "wiggling": lambda r: {"h3_amplitude": r.uniform(0.02, 0.06), "h3_phase_rad": r.uniform(-math.pi, math.pi)},
    "range_offset": lambda r: {"path_m": _sign(r) * r.uniform(0.02, 0.1)},
    "fixed_pattern": lambda r: {"row_delay_s": _sign(r) * r.uniform(1e-12, 4e-12),
                                "col_delay_s": _sign(r) * r.uniform(1e-12, 4e-12),
                                "random_delay_s": 2e-12, "seed": int(r.integers(100))},
    "amplitude_dependent": lambda r: {"error_m": r.uniform(0.03, 0.08), "amplitude_e": r.uniform(2000, 5000)},
    "lens_distortion": lambda r: {"k1": _sign(r) * r.uniform(0.05, 0.15), "k2": 0.0},
    "ambient": lambda r: {"irradiance_w_m2": r.uniform(0.5, 3.0)},
    "reflectance": lambda r: {"scale": float(r.choice([r.uniform(0.7, 0.9), r.uniform(1.1, 1.3)]))},
    "offset": lambda r: {"dark_e": r.uniform(2000.0, 20000.0)},
    "field_angle": lambda r: {"c2_m": _sign(r) * r.uniform(0.02, 0.06), "c4_m": 0.0},
    # a wall facing the camera and a card: tilt and distance are observable, lateral shifts and
    # roll hardly at all (docs/diagnose.md), so those are not hidden
    "pose": lambda r: {"rx": _sign(r) * r.uniform(0.005, 0.015), "ry": _sign(r) * r.uniform(0.005, 0.015),
                       "rz": 0.0, "tx": 0.0, "ty": 0.0, "tz": _sign(r) * r.uniform(0.005, 0.02)},
}
