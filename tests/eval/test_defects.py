"""Defective pixels are found before any fit, excluded, and said: never a scene mismatch."""

from __future__ import annotations

import numpy as np
import pytest

from tests.eval import hidden_forms as hf
from tofhil.eval.diagnose.defects import STUCK_FALSE_ALARM, depth_defects, raw_defects, repeat_probability


def _taps(rng: np.random.Generator, n: int = 6, h: int = 60, w: int = 80, gains=(1.0, 1.0, 1.0, 1.0)) -> np.ndarray:
    """Four-tap frames of a wall with a dark square, read + shot noise, quantised."""
    theta = np.arange(4) * np.pi / 2
    a = np.full((h, w), 300.0)
    a[20:40, 30:50] = 30.0
    phi = np.linspace(0.5, 1.5, w)[None, :] * np.ones((h, 1))
    c = (500.0 + a)[None] + a[None] * np.cos(phi[None] - theta[:, None, None])
    c = c[None] * np.asarray(gains)[None, :, None, None]
    return np.round(np.stack([c + rng.normal(0.0, np.sqrt(4.0 + 0.15 * c)) for _ in range(n)]))


THETA = np.arange(4) * np.pi / 2


def test_a_clean_capture_has_no_defects_even_with_a_tap_gain_imbalance():
    rng = np.random.default_rng(0)
    for gains in ((1.0, 1.0, 1.0, 1.0), (1.0, 1.04, 1.0, 1.05)):
        d = raw_defects(_taps(rng, gains=gains), THETA)
        assert d.count == 0, (gains, {k: int(m.sum()) for k, m in d.kinds.items()})


def test_repeat_probability_is_the_rate_at_which_quantised_taps_repeat():
    """The chance that a working pixel's rounded taps repeat over N frames, against counting."""
    rng = np.random.default_rng(11)
    for sigma, n in ((0.25, 4), (0.5, 3), (1.0, 4)):
        level = rng.uniform(60.0, 61.0, 100_000)
        x = np.round(level[None] + sigma * rng.standard_normal((n, level.size)))
        counted = float((x.std(axis=0) == 0).mean())
        var = np.full((1, 1, level.size), sigma ** 2 + 1.0 / 12.0)
        predicted = float(repeat_probability(level[None, None], var, n, quantised=True).mean())
        se = np.sqrt(predicted * (1 - predicted) / level.size)
        assert abs(counted - predicted) < 5 * se + 1e-4, (sigma, n, counted, predicted)


def test_a_quiet_quantised_sensor_above_a_black_level_has_no_stuck_pixels_and_finds_real_ones():
    """A dim 4-frame session (black level 64 DN, read noise 0.3 DN, shot noise from the black
    level up): many pixels repeat their rounded taps by chance. Over 10 seeds the
    stuck test's false alarms stay at its stated rate (STUCK_FALSE_ALARM per pixel), and stuck
    pixels planted at levels where a working pixel's taps move are all found."""
    theta = np.arange(4) * np.pi / 2
    h, w, n = 120, 160, 4
    false_alarms, tested = 0, 0
    for seed in range(10):
        rng = np.random.default_rng(100 + seed)
        a = np.exp(rng.uniform(np.log(0.5), np.log(150.0), (h, w)))  # dark corners to a bright card
        phi = rng.uniform(0, 2 * np.pi, (h, w))
        c = 64.0 + a[None] * (1 + np.cos(phi[None] - theta[:, None, None]))  # [4, H, W]
        var = 0.09 + 0.02 * (c - 64.0)
        taps = np.round(c[None, None] + np.sqrt(var)[None, None] * rng.standard_normal((n, 1, 4, h, w)))
        repeats = int((taps.std(axis=0) == 0).all(axis=(0, 1)).sum())
        assert repeats > 20  # the class under test: chance repeats are common
        planted = rng.choice(h * w, 10, replace=False)
        v, u = np.unravel_index(planted, (h, w))
        taps[:, :, :, v, u] = np.round(rng.uniform(200.0, 400.0, (1, 1, 4, 10)))  # held at a level where noise moves taps
        d = raw_defects(taps, theta)
        assert d.kinds["stuck"][v, u].all(), seed
        false_alarms += int(d.kinds["stuck"].sum()) - 10
        tested += h * w
    # the rate it states, with room for Poisson scatter (expected < 0.01 here)
    assert false_alarms <= 2, (false_alarms, STUCK_FALSE_ALARM * tested)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_stuck_and_hot_pixels_are_found_by_kind(seed):
    rng = np.random.default_rng(seed)
    taps = _taps(rng)
    h, w = taps.shape[-2:]
    idx = rng.choice(h * w, 40, replace=False)
    v, u = np.unravel_index(idx, (h, w))
    stuck, hot = (v[:20], u[:20]), (v[20:], u[20:])
    taps[:, :, :, stuck[0], stuck[1]] = rng.uniform(0, 1500, (1, 4, 20))
    taps[:, :, :, hot[0], hot[1]] += 300.0 + rng.normal(0.0, 80.0, (taps.shape[0], 1, 4, 20))
    d = raw_defects(taps, THETA)
    assert d.kinds["stuck"][stuck].all()
    assert d.mask[hot].all()
    assert d.count <= 40 + 2, d.to_json()
    assert "stuck or dead" in d.text() and "excluded" in d.text()


def test_clipped_pixels_are_saturation_not_stuck():
    rng = np.random.default_rng(4)
    taps = _taps(rng)
    taps[:, :, :, 10:14, 10:30] = 4095.0  # an ADC pinned at full scale over a patch
    clipped = np.zeros(taps.shape[-2:], bool)
    clipped[10:14, 10:30] = True
    d = raw_defects(taps, THETA, clipped=clipped)
    assert d.count == 0


@pytest.mark.parametrize("seed", [5, 6, 7])
def test_saturation_the_clip_levels_do_not_declare_is_its_own_class_not_stuck(seed):
    """A card saturated at the full well holds its taps still at the session's top level, over a
    region: saturation, stated apart, never "stuck" (no clip level told: the test must see it)."""
    rng = np.random.default_rng(seed)
    taps = _taps(rng)
    taps[:, :, :, 5:25, 50:75] = 3000.0  # charge pinned at the full well, below the ADC's top
    d = raw_defects(taps, THETA)
    assert d.count == 0, d.to_json()
    assert d.saturated[5:25, 50:75].all() and "saturated" in d.text()


@pytest.mark.parametrize("seed", [8, 9, 10])
def test_a_moving_target_is_not_hot_pixels_and_isolated_defects_are_still_found(seed):
    """A target moving between frames changes a whole region: not hot pixels; a hot and a stuck
    pixel inside the same capture still are."""
    rng = np.random.default_rng(seed)
    taps = _taps(rng)
    n = taps.shape[0]
    for i in range(n):  # a bright target sliding 3 columns a frame through rows 40-55
        taps[i, :, :, 42:56, 10 + 3 * i:30 + 3 * i] *= 1.8
    taps[:, :, :, 5, 5] = rng.uniform(0, 1500, (1, 4))                        # stuck
    taps[:, :, :, 50, 70] += 300.0 + rng.normal(0.0, 80.0, (n, 1, 4))        # hot
    d = raw_defects(taps, THETA)
    assert d.kinds["stuck"][5, 5] and d.mask[50, 70]
    assert d.mask[42:56, 10:50].sum() <= 3, d.to_json()


def test_depth_defects_zero_depths_outliers_and_flying_pixels():
    from tofhil.camera import CameraModel

    cam = CameraModel.from_fov(80, 60, 60.0)
    rng = np.random.default_rng(5)
    r = np.full((60, 80), 1.5) + rng.normal(0, 0.002, (60, 80))
    r[:, 40:] = 3.0 + rng.normal(0, 0.002, (60, 40))        # a depth step
    r[:, 40] = 2.2                                           # mixed returns along the step
    r[30, 10] = 0.0                                          # no depth, marked valid
    r[12, 20] += 0.3                                         # one pixel off a flat wall
    d = depth_defects(r, np.ones((60, 80), bool), cam)
    assert d.kinds["no_depth"][30, 10] and d.kinds["outlier"][12, 20]
    assert d.kinds["flying"][:, 40].mean() > 0.9
    assert d.kinds["flying"][:, :38].sum() == 0 and d.kinds["flying"][:, 43:].sum() == 0


@pytest.fixture(scope="module")
def scene():
    return hf.small_dark_square(80)


@pytest.mark.parametrize("kind", ["stuck", "hot"])
def test_defects_in_a_twin_session_are_a_finding_not_a_mismatch(tmp_path, scene, kind):
    """0.3 % of the pixels stuck (or hot) in an otherwise perfect twin session: the diagnosis
    says so, leaves them out, and finds the rest within noise (it said "the scene does not
    match" with a misfit of 141 per value)."""
    from tofhil.eval.diagnose.run import diagnose

    make = hf.stuck_pixels if kind == "stuck" else hf.hot_pixels
    path = hf.write_session(scene, tmp_path / f"{kind}.h5", None, frames=6, seed=11,
                            tap_change=make(np.random.default_rng(7)))
    res = diagnose(path, scene, max_effects=2)
    n = round(0.003 * scene.camera.width * scene.camera.height)
    assert n <= res.defects["pixels"] <= n + 3, res.defects
    assert res.verdict.kind == "within noise", (res.verdict.kind, res.causes, res.verdict.text)
    assert res.causes == []
    assert any("defective" in line for line in res.evidence)
    assert "defects" in res.maps and int(res.maps["defects"].sum()) == res.defects["pixels"]


def test_a_clean_twin_session_has_no_defects(tmp_path, scene):
    from tofhil.eval.diagnose.run import diagnose

    path = hf.write_session(scene, tmp_path / "clean.h5", None, frames=6, seed=12)
    res = diagnose(path, scene, max_effects=1)
    assert res.defects["pixels"] == 0, res.defects
    assert res.verdict.kind == "within noise"


def test_two_frequency_unwrapping_errors_are_counted_not_in_the_rmse(tmp_path, scene):
    """A 44 + 60 MHz sensor, nothing hidden: noise in the dark square's phases unwraps some
    pixels to the wrong interval (metres off). They are counted and mapped; the depth RMSE is
    that of the pixels that carry a measurement (it read 1.5 m before)."""
    import dataclasses

    from tofhil.eval.diagnose.run import diagnose

    two = dataclasses.replace(scene, sensor=dataclasses.replace(scene.sensor, freq_hz=(44e6, 60e6)))
    path = hf.write_session(two, tmp_path / "two.h5", None, frames=6, seed=13)
    res = diagnose(path, two, max_effects=1)
    assert res.verdict.kind == "within noise", res.verdict.text
    g = res.gain
    assert g["depth_rmse_m"]["before"] < 0.05, g["depth_rmse_m"]
    n_wrong = g["unwrap_error_pixels"]["before"]
    assert int(res.maps["unwrap_error_before"].sum()) == n_wrong
    if n_wrong:
        assert any("unwrapped to the wrong interval" in n for n in res.verdict.notes)
    table = res.channel_table["before"]
    names = [r["name"] for r in table["readings"]]
    assert "44 MHz phase" in names and "60 MHz phase" in names and "phase inconsistency" in names
    assert "frequency" not in table["significant"], table
