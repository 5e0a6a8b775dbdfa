"""The PSF the twin simulates with is the PSF corrections take: a scene simulated with the
``stray_light`` effect, corrected with that effect's parameters (as a PSF file and as the
diagnosis.json diagnose writes), loses its dark-square error against the noise-free render
of the same scene without stray light (the physical truth)."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("tofhil.sim.pipeline")

from tofhil.eval.corrections.straylight import load_psf  # noqa: E402
from tofhil.session import open_session  # noqa: E402
from tofhil.sim.effects import EFFECTS  # noqa: E402
from tofhil.sim.straylight import Ghost, StrayLightPSF  # noqa: E402

STRAY = {"weight": 0.03, "sigma_px": 15.0, "veil": 0.01, "ghost_weight": 0.01, "ghost_sigma_px": 2.0}


def test_effect_parameters_and_psf_convert_both_ways(tmp_path) -> None:
    effect = EFFECTS["stray_light"]
    psf = effect.psf(effect.validate(STRAY))
    assert psf.ghosts == (Ghost(0.01, 2.0, None),)  # no centre: the principal point of the camera
    back = effect.psf(effect.validate(effect.values(psf)))
    assert back == psf
    two = StrayLightPSF(ghosts=(Ghost(0.01, 1.0, (3.0, 4.0)), Ghost(0.02, 0.0)), direct=0.95, conserve=False)
    assert effect.psf(effect.validate(effect.values(two))) == two
    path = two.save(tmp_path / "p.json")
    assert StrayLightPSF.load(path) == two
    # The PSF file is the effect's parameter block: it pastes into a scene's effects.
    assert effect.psf(effect.validate(json.loads(path.read_text())["stray_light"])) == two


@pytest.fixture(scope="module")
def sessions(tmp_path_factory):
    from tofhil.sim.pipeline import simulate_session
    from tofhil.sim.scene import load_scene

    d = tmp_path_factory.mktemp("twin")
    scene = load_scene("dark_square_card", overrides={"params": {"square_reflectance": 0.05},
                                                      "sensor": {"black_level_dn": 64.0}})
    simulate_session(scene, d / "a.h5", frames=1, noise=False, effects={"stray_light": dict(STRAY)})
    simulate_session(scene, d / "truth.h5", frames=1, noise=False, effects={})
    return d


def _square_errors(metrics: dict, variant: str) -> float:
    return metrics["variants"][variant]["regions"]["square"]["depth_residual_m"]["median"]


def test_correct_and_compare_with_the_simulated_psf(sessions, tofhil_cli, tmp_path) -> None:
    d = sessions
    effect = EFFECTS["stray_light"]
    psf = effect.psf(effect.validate(STRAY))
    psf_file = psf.save(tmp_path / "lens.json")
    diag = tmp_path / "diagnosis.json"  # what diagnose writes when stray light is a cause
    diag.write_text(json.dumps({"cause": "stray_light", "causes": ["stray_light"], "params": {"stray_light": STRAY}}))
    assert load_psf(diag) == psf

    p = tofhil_cli("correct", d / "a.h5", "--method", f"psf:psf={diag}", "--out", tmp_path / "c.h5")
    assert p.returncode == 0, p.stderr
    with open_session(tmp_path / "c.h5") as c, open_session(d / "a.h5") as a, open_session(d / "truth.h5") as t:
        dc, da, dt = (s.depth_frame(0).radial_m for s in (c, a, t))
    # Pixels whose depth the stray light moves by more than 1 cm: the dark square and around.
    moved = np.abs(da - dt) > 0.01
    assert moved.sum() > 100
    before = np.nanmean(np.abs(da - dt)[moved])
    after = np.nanmean(np.abs(dc - dt)[moved])
    # Not 100 %: the sensor's per-tap gains turn the scattered unmodulated light into a false
    # signal no correction of S removes (a tap calibration does; see docs/evaluation.md).
    assert before > 0.05 and after < 0.1 * before, (before, after)

    out = tmp_path / "report"
    p = tofhil_cli("compare", d / "a.h5", d / "truth.h5", "--out", out, "--frames", "1",
                   "--correct", f"psf:psf={psf_file}")
    assert p.returncode == 0, p.stderr
    m = json.loads((out / "metrics.json").read_text())
    sq_before = _square_errors(m, "measured")
    sq_after = _square_errors(m, f"psf:psf={psf_file}")
    assert sq_before < -0.05  # the near card's stray light pulls the dark square nearer
    assert abs(sq_after) < 0.1 * abs(sq_before), (sq_before, sq_after)


def test_second_order_field_lobe_moves_rho4_of_the_light_and_round_trips(tmp_path) -> None:
    """``field_weight4``: a source at field radius rho spreads ``field_weight4 rho^4`` more
    (closed form: a narrow lobe keeps it all on a big sensor); the operator's adjoint is its
    transpose; the PSF file keeps it."""
    from tofhil.sim.straylight import GaussianLobe, StrayLightOperator, field_rho2

    h, w = 61, 81
    psf = StrayLightPSF(gaussians=(GaussianLobe(0.0, 1.5, 1.5, 0.0, 0.04),), conserve=True)
    op = StrayLightOperator(psf, (h, w), (40.0, 30.0))
    rho2 = field_rho2((h, w), (40.0, 30.0))
    for y, x in ((30, 40), (30, 60), (10, 20)):
        pt = np.zeros((h, w), complex)
        pt[y, x] = 1.0
        assert op.scatter(pt).sum().real == pytest.approx(0.04 * rho2[y, x] ** 2, rel=1e-6, abs=1e-12)
        # Energy conserved: the direct part loses what the lobe moves.
        assert op.apply(pt).sum().real == pytest.approx(1.0, abs=1e-9)
    rng = np.random.default_rng(0)
    a, b = rng.standard_normal((h, w)), rng.standard_normal((h, w))
    assert np.vdot(op.scatter(a), b) == pytest.approx(np.vdot(a, op.scatter_adjoint(b)), rel=1e-9)
    path = psf.save(tmp_path / "f4.json")
    assert StrayLightPSF.load(path).gaussians == psf.gaussians
