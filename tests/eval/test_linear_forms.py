"""Flexible map forms fitted in closed form (eval/diagnose/linear_forms.py): the fixed-pattern range
offset map (per column, row and pixel) and the per-frame drift.

The hidden offsets are made here by rotating every harmonic's phase of the twin's light
directly (tests/eval/hidden_forms.py ``rotate_radial``), not with the effect under test; the
sessions carry the sensor's own noise, quantisation and clipping.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from tests.eval import hidden_forms as hf
from tofhil.errors import TofhilError

MAP = "range_offset_map"


@pytest.fixture(scope="module")
def scene():
    return hf.small_dark_square(40)


def offsets_change(offsets_m: np.ndarray) -> hf.Change:
    def change(signal, sensor):
        return hf.rotate_radial(signal, offsets_m)

    return change


def hidden_column_pixel(seed: int, shape: tuple[int, int], col_sd_m: float = 0.008,
                        pixel_sd_m: float = 0.006) -> tuple[np.ndarray, np.ndarray]:
    r = np.random.default_rng(seed)
    h, w = shape
    col = col_sd_m * r.standard_normal(w)
    return col, col[None, :] + pixel_sd_m * r.standard_normal((h, w))


# ------------------------------------------------------------------------------ the effect
def test_offset_map_effect_reads_like_a_range_offset(tmp_path, scene):
    """A uniform map of d metres is the constant range offset of optical path 2 d (two
    independent forms of the same physics), and a per-pixel map moves each pixel alone."""
    from tofhil.sim.twin import Twin

    twin = Twin(scene)
    h, w = scene.camera.shape
    d = 0.013
    uniform = twin.expected_taps(twin.effects({MAP: {"values": np.full((h, w), d)}}))
    path = twin.expected_taps(twin.effects({"range_offset": {"path_m": 2 * d}}))
    np.testing.assert_allclose(uniform, path, rtol=1e-9, atol=1e-6)
    m = np.zeros((h, w))
    m[5, 7] = 0.05
    np.save(tmp_path / "m.npy", m)
    base = twin.expected_taps(twin.effects({}))
    one = twin.expected_taps(twin.effects({MAP: {"file": str(tmp_path / "m.npy")}}))
    changed = np.any(one != base, axis=(0, 1))
    assert changed[5, 7] and changed.sum() == 1


def test_offset_map_file_is_validated_with_a_clear_error(tmp_path, scene):
    from tofhil.sim.scene import load_scene, scene_to_yaml

    h, w = scene.camera.shape
    text = scene_to_yaml(scene)
    cases = {"missing.npy": None, "nan.npy": np.full((h, w), np.nan), "shape.npy": np.zeros((h + 1, w)),
             "flat.npy": np.zeros(h * w)}
    for name, arr in cases.items():
        if arr is not None:
            np.save(tmp_path / name, arr)
        f = tmp_path / f"{name}.yaml"
        f.write_text(text + f"\neffects:\n  {MAP}:\n    file: {name}\n")
        with pytest.raises(TofhilError) as exc:
            from tofhil.sim.twin import Twin

            Twin(load_scene(f)).expected_taps()
        msg = str(exc.value)
        assert f"effects.{MAP}.file" in msg and str(f) in msg, msg
        if name == "shape.npy":
            assert f"{h} x {w}" in msg


# ------------------------------------------------------------------------------ diagnosis
@pytest.fixture(scope="module")
def column_pixel_diagnosis(tmp_path_factory, scene):
    """Hidden per-column (8 mm) + per-pixel (6 mm) offsets, diagnosed with the extended scene
    written to a directory (the map file goes beside it) and diagnosis.json as the CLI writes
    it (the report's figures are left out: slow, and tested elsewhere)."""
    from tofhil.eval.reports import html as H
    from tofhil.eval.diagnose.run import diagnose

    tmp = tmp_path_factory.mktemp("colpix")
    col, hidden = hidden_column_pixel(11, scene.camera.shape)
    path = hf.write_session(scene, tmp / "cols.h5", offsets_change(hidden), frames=FRAMES, seed=12)
    out = tmp / "d"
    out.mkdir()
    # the offset map against the library forms nearest to it: a constant offset and the
    # row/column clock delays (the whole library is slow here; benchmarks/diagnose_sweep.py
    # runs it)
    res = diagnose(path, scene, max_effects=1, candidates=[MAP, "range_offset", "fixed_pattern", "drift"],
                   extended_scene_path=out / "extended_scene.yaml")
    H.write_json(out / "diagnosis.json", res.to_json())
    return res, out, col, hidden


#: Frames of the column/pixel session: a per-pixel offset of 6 mm is estimated from the
#: training frames of that pixel alone, so it needs enough of them to stand above the noise.
FRAMES = 32


def test_column_and_pixel_offsets_are_named_as_the_offset_map(column_pixel_diagnosis):
    res, out, col, hidden = column_pixel_diagnosis
    assert res.causes == [MAP], (res.causes, res.evidence)
    assert res.verdict.excess_removed is not None and res.verdict.excess_removed >= 0.9, res.verdict
    assert not any(c["worse"] for c in res.channels.values()), res.channels
    g = res.gain
    assert g["depth_rmse_m"]["after"] < 0.7 * g["depth_rmse_m"]["before"]
    assert g["amplitude_rmse"]["after"] <= 1.02 * g["amplitude_rmse"]["before"]
    p = res.params[MAP]
    assert "column" in p["form"] and "pixel" in p["form"] and p["file"] == "range_offset_map.npy"
    assert 0 < p["dof"] < res.data.usable.sum() + sum(res.data.usable.shape)


def test_offset_map_file_holds_the_hidden_map(column_pixel_diagnosis):
    res, out, col, hidden = column_pixel_diagnosis
    fitted = np.load(out / "range_offset_map.npy")
    ok = res.data.usable
    # the map is known up to the twin's own noise: the column part to about a millimetre
    fitted_col = np.array([np.median(fitted[ok[:, u], u]) for u in range(fitted.shape[1])])
    assert np.corrcoef(fitted_col, col)[0, 1] > 0.95
    assert np.corrcoef(fitted[ok], hidden[ok])[0, 1] > 0.8
    d = json.loads((out / "diagnosis.json").read_text())
    assert d["causes"] == [MAP] and d["params"][MAP]["file"] == "range_offset_map.npy"
    assert "range_offset_map.npy" in (out / "extended_scene.yaml").read_text()


def test_extended_scene_loads_the_map_and_reproduces_the_gain(column_pixel_diagnosis):
    """The extended scene (base scene + the map file) is what the 'after' figures come from:
    loaded on its own, it predicts the held-out data with the reported misfit."""
    from tofhil.eval.diagnose.twin_model import TwinModel
    from tofhil.sim.scene import load_scene

    res, out, _, _ = column_pixel_diagnosis
    ext = load_scene(out / "extended_scene.yaml")
    pred = TwinModel(ext, res.data).predict({})
    n = res.data.n_values("test")
    assert res.data.chi2(pred, "test") / n == pytest.approx(res.chi2_per_value["after_extended_scene"], rel=1e-9)


def test_null_sessions_name_no_map(tmp_path, scene):
    """Five sessions with nothing hidden: neither the regularised map nor the drift is named
    (they do not fit noise), and nothing else on the candidate list either."""
    from tofhil.eval.diagnose.run import diagnose

    named = []
    for seed in range(5):
        path = hf.write_session(scene, tmp_path / f"null{seed}.h5", None, frames=8, seed=100 + seed)
        res = diagnose(path, scene, max_effects=1, candidates=[MAP, "range_offset", "drift"])
        named.append(res.causes + (["drift"] if res.drift["named"] else []))
        first = next(c for c in res.ranked if c["effect"] == MAP)
        assert first["params"]["dof_pixel"] == 0.0  # the per-pixel part is noise: not kept
    assert named == [[]] * 5, named


def test_one_frame_depth_session_says_why_no_pixel_map(tmp_path, scene):
    """With one frame the training and held-out frames are the same: the per-pixel part
    cannot be scored, and the diagnosis says so."""
    from tofhil.eval.diagnose.run import diagnose
    from tofhil.session import SessionWriter
    from tofhil.sim.scene import scene_to_yaml

    _, hidden = hidden_column_pixel(3, scene.camera.shape)
    raw_path = hf.write_session(scene, tmp_path / "raw.h5", offsets_change(hidden), frames=1, seed=4)
    from tofhil.session import open_session

    with open_session(raw_path) as s:
        depth = s.depth_frame(0)
    path = tmp_path / "depth.h5"
    with SessionWriter(path, scene.camera, device={"model": "tofhil-sim"}, scene_text=scene_to_yaml(scene),
                       force=True) as w:
        w.append(None, depth)
    res = diagnose(path, scene, max_effects=1, candidates=[MAP])
    assert any("one frame" in line and "per-pixel" in line for line in res.evidence), res.evidence


def test_linear_drift_over_frames_is_named(tmp_path, scene):
    """A range drift linear over the frames (12 mm first to last, zero on average): named as
    the per-frame drift, its offsets follow the hidden line, and no map is named for it."""
    from tofhil.eval.diagnose.run import diagnose

    frames, span = 8, 0.012
    path = hf.write_session(scene, tmp_path / "drift.h5", None, frames=frames, seed=21,
                            frame_change=hf.linear_drift(np.random.default_rng(0), span))
    res = diagnose(path, scene, max_effects=1, candidates=[MAP, "range_offset", "drift"])
    d = res.drift
    assert d is not None and d["named"], d
    hidden = span * (np.arange(frames) / (frames - 1) - 0.5)
    fitted = np.array(d["offsets_mm"]) * 1e-3
    slope = np.polyfit(np.arange(frames), fitted, 1)[0]
    assert slope == pytest.approx(span / (frames - 1), rel=0.25)
    assert np.sqrt(np.mean((fitted - hidden) ** 2)) < 0.25 * span
    assert MAP not in res.causes
    assert d["text"] in res.evidence
    # the frames' mean hides the drift; the verdict is the drift's, not "within noise"
    assert res.verdict.kind in ("explained", "partly explained") and "drift" in res.verdict.text


def test_emitter_power_drift_over_frames_is_named_as_a_scale(tmp_path, scene):
    """The emitter's power falling by 6 % over 8 frames (warm-up), the range unchanged: the
    per-frame drift is named, its amplitude scale follows the hidden line and its range offsets
    stay within noise."""
    from tofhil.eval.diagnose.run import diagnose

    frames, span = 8, -0.06
    path = hf.write_session(scene, tmp_path / "power.h5", None, frames=frames, seed=23,
                            frame_change=hf.emitter_power_drift(span))
    res = diagnose(path, scene, max_effects=1, candidates=[MAP, "range_offset", "drift"])
    d = res.drift
    assert d is not None and d["named"], d
    hidden = 1.0 + span * (np.arange(frames) / (frames - 1) - 0.5)
    fitted = np.array(d["amplitude_scale"])
    assert np.polyfit(np.arange(frames), fitted, 1)[0] == pytest.approx(span / (frames - 1), rel=0.25)
    assert np.sqrt(np.mean((fitted - hidden) ** 2)) < 0.25 * abs(span)
    assert np.ptp(d["offsets_mm"]) < 2.0  # no range drift made up for it
    assert "modulated light" in d["text"]
