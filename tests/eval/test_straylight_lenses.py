"""Stray-light calibration on lenses of other forms than its model (issue 17).

The stray light is made by ``tests/straylight_lenses.py``: convolutions of the complex signal
with kernels written there (no tofhil optics), energy conserved. The baseline (the Gaussian
dictionary with the ghost through the principal point) and the free-form calibration are
measured as % of the dark-square error removed; ``benchmarks/straylight_lenses.py`` prints
the whole table.
"""

from __future__ import annotations

import numpy as np
import pytest

from tests import straylight_lenses as L
from tofhil.eval.corrections import psf_calibration as pc
from tofhil.eval.corrections import straylight as sl


def test_test_kernels_have_unit_sum_and_the_lenses_conserve_energy():
    for k in (L.gaussian(1.7), L.gaussian(8.0, 5.5), L.power_law()):
        assert k.sum() == pytest.approx(1.0, rel=1e-12)
    # A point at the principal point through a lens of narrow parts: everything stays on the
    # sensor, so the total is conserved; a wide lens loses only what leaves the sensor.
    pt = np.zeros((L.H, L.W), complex)
    pt[int(L.CY), int(L.CX)] = 1.0
    narrow = L.Lens("narrow", [(0.05, L.gaussian(2.0))], ghosts=[(0.01, 1.0, (L.CX + 3, L.CY + 2))])
    assert narrow(pt).sum().real == pytest.approx(1.0, abs=1e-9)
    for lens in L.lenses().values():
        out = lens(pt)
        assert 1.0 - lens.total <= out.sum().real <= 1.0 + 1e-9
        assert np.all(out.real >= -1e-12)


def _centre_error(psf) -> float:
    true = np.array(L.lenses()["ghost_7px"].ghosts[0][2])
    return float(np.hypot(*(np.array(psf.info["ghost_center_px"]) - true)))


def test_ghost_centre_off_the_principal_point_is_fitted():
    lens = L.lenses()["ghost_7px"]
    psf = pc.calibrate_psf_target(L.calibration_capture(lens), L.CX, L.CY, rounds=2, ghost_center_px="fit",
                                  sigmas=pc.default_sigmas(L.H, L.W)[::2])
    assert _centre_error(psf) < 0.3
    # Sharp and blurred ghosts through the one fitted centre: their light is the lens's ghost.
    assert sum(g.weight for g in psf.ghosts if g.sigma_px <= 8) >= 0.5 * 0.005
    assert {g.center_px for g in psf.ghosts} == {tuple(psf.info["ghost_center_px"])}


def test_fit_quality_report_warns_when_the_data_cannot_constrain_the_model():
    lens = L.lenses()["gauss_other"]
    # One capture cannot tell a shift-variant lobe from the others: the report says so.
    psf = pc.calibrate_psf_target(L.calibration_capture(lens)[0], L.CX, L.CY, rounds=1, field=True,
                                  sigmas=pc.default_sigmas(L.H, L.W)[::2], refine=False)
    assert any("field" in w and "one capture" in w for w in psf.info["warnings"])
    assert 0 <= psf.info["relative_residual"] < 1 and psf.info["condition"] > 1
    # A target on black WITHOUT stray light: a warning that there is none to fit.
    s, _ = L.scene_signal(square_rho=None, card=True, wall=False)
    psf0 = pc.calibrate_psf_target(s[None], L.CX, L.CY, rounds=1, sigmas=pc.default_sigmas(L.H, L.W)[::2],
                                   refine=False)
    assert any("almost no stray light" in w for w in psf0.info["warnings"])


def test_ghost_magnification_and_blur_are_fitted():
    # The test lens's ghost is upright and magnified 1.3x about the principal point (as
    # sim/optics.py traces them), blurred 3 px, moved pixel area by pixel area in the test:
    # one card, the centre the principal point, magnification and blur fitted.
    lens = L.lenses()["ghost_mag_up"]
    w, sigma, _, m = lens.ghosts[0]
    psf = pc.calibrate_psf_target(L.calibration_capture(lens), L.CX, L.CY, rounds=2, ghost_magnification="fit")
    assert psf.info["ghost_magnification"] == pytest.approx(m, abs=0.02)
    main = max(psf.ghosts, key=lambda g: g.weight)
    assert main.magnification == pytest.approx(m, abs=0.02) and main.sigma_px == pytest.approx(sigma, abs=0.3)
    # The calibration sees S' = (1 - W) S: the ghost's fraction of that is w / (1 - W).
    assert main.weight == pytest.approx(w / (1 - lens.total), rel=0.05)


def test_fit_quality_report_warns_when_no_capture_can_see_the_ghost():
    lens = L.lenses()["gauss_other"]
    quick = dict(rounds=1, sigmas=pc.default_sigmas(L.H, L.W)[::2], refine=False)
    # A patch centred on the principal point: its mirror ghost lands on the patch itself, so
    # no background pixel sees it and its weight is whatever the fit makes of nothing.
    centred = L.patch_captures(lens)[4]
    psf = pc.calibrate_psf_target(centred, L.CX, L.CY, **quick)
    assert psf.info["ghost_visibility"] < 0.01
    assert any("cannot see a ghost" in w for w in psf.info["warnings"])
    # The card in a corner sees it: no such warning.
    psf = pc.calibrate_psf_target(L.calibration_capture(lens), L.CX, L.CY, **quick)
    assert psf.info["ghost_visibility"] > 0.5
    assert not any("ghost" in w for w in psf.info["warnings"])


@pytest.mark.slow
@pytest.mark.parametrize("name", ["ghost_2px", "ghost_7px", "ghost_10px"])
def test_free_form_beats_the_baseline_on_off_centre_ghosts(name):
    lens = L.lenses()[name]
    cal = L.calibration_capture(lens)
    base = pc.calibrate_psf_target(cal, L.CX, L.CY)
    free = pc.calibrate_psf_target(cal, L.CX, L.CY, **dict(pc.FREE_FORM, field=False))
    r0 = L.removed(lens, lambda s: sl.deconvolve(s, base, center_px=(L.CX, L.CY)))
    r1 = L.removed(lens, lambda s: sl.deconvolve(s, free, center_px=(L.CX, L.CY)))
    assert all(r1[k] > r0[k] for k in L.REFLECTANCES), (r0, r1)


def test_one_card_says_a_magnified_ghost_may_be_a_field_dependent_lobe():
    # the field-dependent lobe has no ghost; from one card the free form fits one magnified
    # about its centre (the two spread the card's light alike) and must say it cannot tell them apart
    lens = L.lenses()["field_lobe"]
    free = pc.calibrate_psf_target(L.calibration_capture(lens), L.CX, L.CY, **dict(pc.FREE_FORM, field=False))
    assert free.ghosts and abs(free.info["ghost_magnification"] + 1.0) > pc.GHOST_MAGNIFICATION_TOL
    assert any("lobe that widens across the field" in w for w in free.info["warnings"])


@pytest.mark.slow
def test_cli_calibrates_one_free_form_psf_from_several_captures(tmp_path, tofhil_cli):
    from tests.straylight_synthetic import write_session
    from tofhil.sim.straylight import StrayLightPSF

    lens = L.lenses()["ghost_7px"]
    cals = [write_session(tmp_path / f"cal{i}.h5", s[0], n_frames=1, offset=50.0)
            for i, s in enumerate(L.patch_captures(lens, 2))]
    psf_path = tmp_path / "lens.json"
    p = tofhil_cli("correct", cals[0], "--method", "psf", "--calibrate", cals[0], "--calibrate", cals[1],
                   "--psf-form", "free", "--save-psf", psf_path, "--out", tmp_path / "c.h5", timeout=600)
    assert p.returncode == 0, p.stderr
    assert "PSF fit: residual" in p.stdout
    psf = StrayLightPSF.load(psf_path)
    assert psf.info["calibration"]["capture"] == [str(c) for c in cals]
    true = np.array(lens.ghosts[0][2])
    assert np.hypot(*(np.array(psf.info["ghost_center_px"]) - true)) < 0.5
    # One --reference per --calibrate, or none.
    bad = tofhil_cli("correct", cals[0], "--method", "psf", "--calibrate", cals[0], "--calibrate", cals[1],
                     "--reference", cals[0], "--out", tmp_path / "d.h5")
    assert bad.returncode == 2 and "error:" in bad.stderr and "--reference" in bad.stderr
    assert not (tmp_path / "d.h5").exists()
    bad = tofhil_cli("correct", cals[0], "--method", "psf", "--calibrate", cals[0], "--psf-form", "wild",
                     "--out", tmp_path / "e.h5")
    assert bad.returncode == 2 and "--psf-form" in bad.stderr


# Every lens form once: the Gaussian lobe off the study lens (gauss_other), the ghost shifted
# (the largest of the study lens's four offsets, 1, 2, 7, 10 px), the ghost magnified (up), the
# lobe that widens across the field, the power-law tail. Each bench calibration costs 30-60
# CPU-s; benchmarks/straylight_lenses.py runs all nine lenses (the 2 px ghost that the
# whole-pixel search cannot reach exactly, and the inverted magnification, among them).
BENCH_LENSES = [n for n in L.lenses() if n not in ("ghost_1px", "ghost_2px", "ghost_7px", "ghost_mag_inv")]


@pytest.mark.slow
@pytest.mark.parametrize("name", BENCH_LENSES)
def test_bench_procedure_removes_95_percent_for_every_lens_form(name):
    """The documented procedure (a card on black and a bright patch at four more field
    positions, free form) removes >= 95 % of the dark-square error at 50, 5, 2 and 1 %."""
    lens = L.lenses()[name]
    psf = pc.calibrate_psf_target(L.patch_captures(lens), L.CX, L.CY, rounds=3, **pc.FREE_FORM)
    # The field order chosen on held-out captures: second order only for the lens whose lobe
    # widens across the field.
    assert psf.info["field_order_selection"]["chosen"] == (2 if name == "field_lobe" else 1)
    assert not any("lobe that widens across the field" in w for w in psf.info["warnings"])  # five positions
    r = L.removed(lens, lambda s: sl.deconvolve(s, psf, center_px=(L.CX, L.CY)))
    assert all(v >= 0.95 for v in r.values()), r
