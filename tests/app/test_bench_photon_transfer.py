"""bench photon-transfer recovers the emulated TOFcam635's sensor (pyusb backend, differential
DCS) within its stated uncertainties, tested as statistics: over 5 seeds (capture noise and
fixed pattern) the standardised errors are N(0, 1)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import chi2

from tofhil.app.bench import BenchOptions, run_bench
from tofhil.eval.calibration.photon_transfer import PtcCapture, photon_transfer
from tofhil.sim.sensor import SensorConfig
from tofhil.yamlio import load_yaml_file

RECOVERED = ("conversion_gain_dn_per_e", "read_noise_e", "full_well_e", "dark_current_e_per_s", "dsnu_e", "prnu")


def _bench_file(tmp_path, seed: int):
    from tofhil.app.bench.rigs import flat_field_bench

    text = flat_field_bench()[2].replace("seed: 7", f"seed: {100 + seed}")  # a new pixel pattern per seed
    p = tmp_path / f"ff{seed}.yaml"
    p.write_text(text)
    return p


def test_photon_transfer_recovers_the_emulated_sensor_within_its_stated_uncertainty(tmp_path):
    z = []
    for seed in range(5):
        bench = _bench_file(tmp_path, seed)
        res = run_bench("photon-transfer", f"emulator:{bench}", tmp_path / f"o{seed}",
                        options=BenchOptions(frames=5, seed=seed, extra={"freqs_hz": [20e6]}), report=seed == 0)
        figs = {f.name: f for f in res.figures}
        for name in RECOVERED:
            f = figs[name]
            assert f.sigma > 0 and math.isfinite(f.value)
            z.append((f.value - f.predicted) / f.sigma)   # predicted = the emulator's true sensor block
    z = np.asarray(z)
    # 30 standardised errors: no outlier, and their spread is what the stated sigmas claim (a sigma
    # twice too small or too large fails the chi-square at 0.1 % either way)
    assert np.abs(z).max() < 4.0, z
    assert chi2.ppf(0.001, z.size) < np.sum(z ** 2) < chi2.ppf(0.999, z.size), z
    assert abs(z.mean()) < 3.5 / math.sqrt(z.size), z   # no common bias
    # the measured block is a scene's sensor: block again
    block = load_yaml_file(tmp_path / "o0" / "sensor.yaml")["sensor"]
    cfg = SensorConfig.from_dict(block)
    assert cfg.conversion_gain_dn_per_e == pytest.approx(0.15, rel=0.02)
    assert cfg.fixed_pattern.dsnu_e == pytest.approx(30, rel=0.03)
    assert (tmp_path / "o0" / "report.html").read_text().count("<img") >= 1
    # and the tap calibration: per-pixel dark offsets (the gates' DSNU, antisymmetric on differential
    # taps) and per-tap gains (equal here: the emulated taps share one gain)
    from tofhil.eval.calibration.taps import TapCalibration

    cal = TapCalibration.load(tmp_path / "o0" / "tap_calibration_20MHz.npz")
    assert cal.offset_dn.shape == (1, 4, 60, 160)
    assert np.allclose(cal.offset_dn[0, 2], -cal.offset_dn[0, 0], atol=0.05)
    assert np.allclose(cal.gain, 1.0, atol=0.02)
    dsnu_from_offsets = cal.offset_dn[0, :2].std() * math.sqrt(2) / 0.15
    assert dsnu_from_offsets == pytest.approx(30.0, rel=0.05)


def _synthetic(single_ended: bool, k=0.2, rn=8.0, dark=5000.0, fw=15000.0, seed=3) -> list[PtcCapture]:
    """An independent generator of single-ended or differential taps (numpy only, closed form)."""
    rng = np.random.default_rng(seed)
    h, w, n = 40, 50, 6
    g = 1 + 0.02 * rng.standard_normal((h, w))
    off = 15.0 * rng.standard_normal((4, h, w))
    caps = []
    for flat, times in ((False, (1e-4, 5e-4, 1e-3, 2e-3)), (True, (5e-5, 1e-4, 2e-4, 4e-4, 6e-4, 8e-4, 2e-3))):
        for t in times:
            a_e = (5e6 * t if flat else 0.0) * g                  # modulated electrons per gate
            mu = np.stack([a_e / 0.8 + a_e * c + dark * t for c in (1, 0, -1, 0)])  # phase 0, contrast 0.8
            e = rng.poisson(np.broadcast_to(mu, (n, *mu.shape))).astype(float)
            e = np.minimum(e, fw) + off + rn * rng.standard_normal(e.shape)
            y = np.rint(k * e) if single_ended else np.rint(k * (e - np.roll(e, 2, axis=1)) / 2)
            caps.append(PtcCapture(t, flat, y, f"{'flat' if flat else 'dark'}-{t}"))
    return caps


@pytest.mark.parametrize("single_ended", [False, True])
def test_photon_transfer_on_an_independent_generator(single_ended):
    res = photon_transfer(_synthetic(single_ended), modulation_contrast=0.8)
    assert res.readout == ("single-ended" if single_ended else "differential")
    q = res.quantities()
    for name, truth in (("conversion_gain_dn_per_e", 0.2), ("read_noise_e", 8.0), ("prnu", 0.02)):
        assert abs(q[name].value - truth) < 4 * q[name].sigma + 0.01 * truth, (name, q[name], truth)
    assert q["dsnu_e"].value == pytest.approx(15.0, rel=0.08)
    assert q["dark_current_e_per_s"].value == pytest.approx(5000.0, rel=0.25)


def test_a_tap_with_another_gain_is_found():
    caps = _synthetic(False)
    for c in caps:   # tap 1 (and its negative, tap 3) reads 8 % more charge per electron
        c.frames = c.frames.astype(float)
        c.frames[:, 1] = np.rint(c.frames[:, 1] * 1.08)
        c.frames[:, 3] = -c.frames[:, 1]
    res = photon_transfer(caps, modulation_contrast=0.8)
    per_tap = res.fit["per_tap"]
    assert per_tap[1]["conversion_gain_dn_per_e"] > per_tap[0]["conversion_gain_dn_per_e"] * 1.05
    assert any("tap calibration" in n for n in res.notes)
    clean = photon_transfer(_synthetic(False), modulation_contrast=0.8)
    assert not any("tap calibration" in n for n in clean.notes)
