"""A fit's predictions on its pixels only (TwinModel.predict(pixels=)): equal, bit for bit,
to the full frame's prediction there, for pixel-local effects (rendered only there) and for
stray light (the whole frame rendered and scattered); and the fit asks for exactly those."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from tofhil.eval.diagnose.heldout import HeldOutData, predict_fit
from tofhil.eval.diagnose.twin_model import TwinModel
from tofhil.sim.scene import load_scene


@pytest.fixture(scope="module")
def model() -> TwinModel:
    sc = load_scene("bench_demo")
    sc = dataclasses.replace(sc, camera=sc.camera.scaled(0.5))
    h, w = sc.camera.shape
    z = np.zeros((2, h, w), complex)
    one = np.ones((2, h, w))
    train = (np.indices((h, w)).sum(axis=0) // 4) % 2 == 0
    data = HeldOutData(camera=sc.camera, freq_hz=np.array(sc.freq_hz), theta_rad=np.arange(4) * np.pi / 2,
                       integration_time_s=1e-3, s_train=z, s_test=z, var_train=one, var_test=one,
                       usable=np.ones((h, w), bool), train_pixels=train, test_pixels=~train,
                       n_train_frames=2, n_test_frames=2, offset_channel=True)
    return TwinModel(sc, data)


@pytest.mark.parametrize("active", [{}, {"pose": {"rx": 0.004, "tz": 0.01}}, {"wiggling": {"h3_amplitude": 0.04}},
                                    {"stray_light": {"weight": 0.03, "sigma_px": 6.0}},
                                    {"lens_distortion": {"k1": 0.05}, "range_offset": {"path_m": 0.02}}])
def test_prediction_on_pixels_equals_full_frame(model: TwinModel, active):
    mask = np.zeros(model.data.camera.shape, bool)
    mask[1::3, ::4] = True
    full = model.predict(active)
    part = model.predict(active, pixels=mask)
    assert part.shape == full.shape
    assert np.array_equal(part[:, mask], full[:, mask])
    assert not np.any(part[:, ~mask])


def test_fit_predicts_on_the_fit_pixels(model: TwinModel):
    asked = []

    class Spy:
        predicts_pixels = True

        def predict(self, active, pixels=None):
            asked.append(pixels)
            return model.predict(active, pixels=pixels)

    predict_fit(Spy(), model.data, {})
    assert asked[0] is model.data.fit_pixels
