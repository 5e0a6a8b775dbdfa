"""A large raw-tap session is diagnosed on binned taps (``MAX_RAW_DIAGNOSIS_PIXELS``): the binned
data are the means of the sensor's pixels, the binned twin predicts those means, and a hidden
effect is found at its value (in binned pixels), as at full resolution; nothing is found in a
session without one.

The sessions: the bundled dark_square on a 224 x 168 camera (37 632 pixels, binned 2 x 2 to
112 x 84), with the scene's fixed pattern, noise and ADC.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from tests.eval import hidden_forms as hf


@pytest.fixture(scope="module")
def scene():
    return hf.small_dark_square(224)


def _add_stray_light(scene, weight: float, sigma_px: float, veil: float):
    effects = dict(scene.effects) | {"stray_light": {"weight": weight, "sigma_px": sigma_px, "veil": veil}}
    return dataclasses.replace(scene, effects=effects)


@pytest.fixture(scope="module")
def null_session(tmp_path_factory, scene):
    return hf.write_session(scene, tmp_path_factory.mktemp("binned") / "null.h5", None, frames=6, seed=7)


def _blocks_mean(x: np.ndarray, b: int) -> np.ndarray:
    """The mean of b x b blocks, written out with loops (independent of tofhil.binning)."""
    h, w = x.shape[-2] // b, x.shape[-1] // b
    out = np.zeros(x.shape[:-2] + (h, w), dtype=x.dtype)
    for i in range(b):
        for j in range(b):
            out += x[..., i:h * b:b, j:w * b:b]
    return out / (b * b)


def test_binned_taps_are_the_means_of_the_sensor_pixels_and_their_noise_falls_as_the_bin(null_session, scene):
    from tofhil.eval.diagnose.depth_heldout import split_for_diagnosis
    from tofhil.eval.diagnose.heldout import split_session
    from tofhil.session import open_session

    with open_session(null_session) as s:
        binned = split_for_diagnosis(s, scene)
        full = split_session(s, max_pixels=10 ** 9)
    assert binned.bin_px == 2 and binned.camera.shape == (84, 112) and full.bin_px == 1
    assert "binned 2 x 2" in binned.channels
    # the signal is linear in the taps: a bin's S is the mean of its pixels' S
    ok = binned.usable
    expected = _blocks_mean(full.s_test, 2)
    assert np.allclose(binned.s_test[:, ok], expected[:, ok], rtol=1e-9, atol=1e-9)
    # the bins across an object's outline are left out
    from tofhil.sim.render import render

    oid = np.pad(np.asarray(render(scene, samples_per_pixel=1, subpixel=False).object_id), 1, mode="edge")
    near = np.zeros((168, 224), bool)    # a pixel within one pixel of another object
    for dy in (0, 1, 2):
        for dx in (0, 1, 2):
            near |= oid[dy:dy + 168, dx:dx + 224] != oid[1:-1, 1:-1]
    across = near.reshape(84, 2, 112, 2).any(axis=(1, 3))
    assert across.sum() > 50 and not (ok & across).any()
    # the noise of a mean of 4 pixels is a quarter of a pixel's (frame scatter, measured)
    ratio = binned.var_test[0][ok] / _blocks_mean(full.var_test[0], 2)[ok]
    assert np.median(ratio) == pytest.approx(0.25, rel=0.1)


def test_the_binned_twin_predicts_the_means_of_the_full_twin(null_session, scene):
    """The binned twin (its fixed pattern the sensor's binned, more samples per bin) predicts
    what the full-resolution twin predicts averaged over each bin, within a small part of the
    bin's noise."""
    from tofhil.eval.diagnose.depth_heldout import split_for_diagnosis
    from tofhil.eval.diagnose.heldout import split_session
    from tofhil.eval.diagnose.twin_model import TwinModel
    from tofhil.session import open_session

    with open_session(null_session) as s:
        binned = split_for_diagnosis(s, scene)
        full = split_session(s, max_pixels=10 ** 9)
    pb = TwinModel(scene, binned).predict({})
    pf = _blocks_mean(TwinModel(scene, full).predict({}), 2)
    ok = binned.test_pixels
    z = (pb - pf)[:, ok] / np.sqrt(binned.var_test[:, ok])
    # (the twin's sampling error: a fraction of the noise, and no bias)
    assert np.sqrt(np.mean(np.abs(z) ** 2)) < 0.5 and np.all(np.abs(z.mean(axis=1)) < 0.05)
    # the twin samples a bin as the scene samples its 4 pixels, and its own sampling variance is
    # measured with as many samples (a second render, independent placement): a small part of
    # the noise
    model = TwinModel(scene, binned)
    assert model.scene.render.samples_per_pixel == 4 * scene.render.samples_per_pixel
    extra = model.sampling_variance()
    assert 0 < np.median((extra / binned.var_test)[:, ok]) < 0.1
    # and the fixed pattern alone: the binned sensor's is the mean of the sensor's pixels'
    from tofhil.sim.sensor import SensorModel

    sensor_b = TwinModel(scene, binned).scene.sensor
    assert sensor_b.fixed_pattern.binned == (2, 168, 224)
    gain_b, off_b = SensorModel(sensor_b, binned.camera).fixed_pattern()
    gain_f, off_f = SensorModel(dataclasses.replace(sensor_b, fixed_pattern=dataclasses.replace(
        sensor_b.fixed_pattern, binned=None)), full.camera).fixed_pattern()
    assert np.allclose(gain_b, _blocks_mean(gain_f, 2)) and np.allclose(off_b, _blocks_mean(off_f, 2))


def test_one_object_leaves_out_the_bins_an_outline_crosses():
    from tofhil.binning import one_object

    oid = np.zeros((12, 12), np.int32)
    oid[:, 7:] = 1                       # an outline between columns 6 and 7
    kept = one_object(oid, 3)            # bins of columns 0-2, 3-5, 6-8, 9-11
    # within one pixel of the outline: columns 6 and 7, in the third bin column only
    assert kept.tolist() == [[True, True, False, True]] * 4
    kept0 = one_object(oid, 3, margin_px=0)
    assert kept0.tolist() == [[True, True, False, True]] * 4
    oid[:, 7:] = 0
    oid[:, 9:] = 1                       # the outline on a bin border: one pixel of margin crosses it
    assert one_object(oid, 3).tolist() == [[True, True, False, False]] * 4
    assert one_object(oid, 3, margin_px=0).tolist() == [[True, True, True, True]] * 4


def test_a_binned_session_names_its_stray_light_and_a_null_one_nothing(tmp_path, scene, null_session):
    """Stray light hidden in a 224 x 168 session is found in the binned one at its weight and
    veil, its width in binned pixels (half the sensor's); the same session without it is
    within noise and names nothing."""
    from tofhil.eval.diagnose.run import diagnose

    lit = hf.write_session(_add_stray_light(scene, 0.04, 8.0, 0.004), tmp_path / "sl.h5", None, frames=6, seed=8)
    res = diagnose(lit, scene, max_effects=2)
    assert res.causes == ["stray_light"], (res.causes, res.verdict.text)
    assert res.verdict.kind == "explained", res.verdict.text
    p = res.params["stray_light"]
    assert p["weight"] == pytest.approx(0.04, rel=0.15) and p["sigma_px"] == pytest.approx(4.0, rel=0.15)
    null = diagnose(null_session, scene, max_effects=2)
    assert null.causes == [] and null.verdict.kind == "within noise", (null.causes, null.verdict.text)


def test_a_psf_from_a_binned_diagnosis_is_in_the_sensor_s_pixels(tmp_path):
    """The PSF file is applied to the sensor's frames: the binned fit's widths times the bin,
    its fractions of light unchanged."""
    from tofhil.eval.corrections.straylight import psf_from_diagnosis
    from tofhil.eval.diagnose.run import at_sensor_pixels

    doc = {"causes": ["stray_light"], "params": {"stray_light": {"weight": 0.04, "sigma_px": 4.0, "veil": 0.004}}}
    sensor = at_sensor_pixels(doc, 3)["params"]["stray_light"]
    assert sensor == {"weight": 0.04, "sigma_px": 12.0, "veil": 0.004}
    assert at_sensor_pixels(doc, 1) is doc
    binned_psf = psf_from_diagnosis(doc, tmp_path / "d.json")
    sensor_psf = psf_from_diagnosis(at_sensor_pixels(doc, 3), tmp_path / "d.json")
    (lobe_b,), (lobe_s,) = binned_psf.gaussians, sensor_psf.gaussians
    assert lobe_s.sigma_x_px == pytest.approx(3 * lobe_b.sigma_x_px) and lobe_s.weight == pytest.approx(lobe_b.weight)
