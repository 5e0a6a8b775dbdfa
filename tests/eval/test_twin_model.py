"""What diagnosis fits comes from one table: the effect library's Param fields."""

from __future__ import annotations

import math

from tofhil.eval.diagnose.twin_model import fit_library, to_effect_values
from tofhil.sim.effects import EFFECTS, ORDER


def test_fit_library_is_read_from_the_params() -> None:
    lib = fit_library()
    assert list(lib) == list(ORDER)
    for name, spec in ((n, s) for n, simple in lib.items() for s in (simple,) + simple.forms):
        fitted = {k: p for k, p in EFFECTS[name].params.items() if p.fitted and spec.form in p.forms}
        if spec.closed_form is not None:  # a map fitted in closed form: no optimiser parameters
            assert not spec.params and not fitted
            continue
        assert fitted and [fp.name.removeprefix("log10_") for fp in spec.params] == list(fitted)
        for fp in spec.params:
            p = fitted[fp.name.removeprefix("log10_")]
            half = (p.fit[1] - p.fit[0]) / 2 if p.periodic else 0.0  # an angle may cross its wrap
            assert (fp.lo, fp.hi, fp.scale) == (p.fit[0] - half, p.fit[1] + half, p.step)
            assert fp.name.startswith("log10_") == p.log
            assert fp.off == (math.log10(p.off) if p.log else p.off)
            assert fp.lo <= fp.off <= fp.hi  # "off" is inside the range searched
        for start in spec.starts:  # every start names fitted parameters, inside their ranges
            for k, v in start.items():
                fp = next(f for f in spec.params if f.name == k)
                assert fp.lo <= v <= fp.hi, (name, k, v)


def test_multi_starts_vary_one_parameter_at_a_time() -> None:
    stray = fit_library()["stray_light"].starts
    assert {"weight": 0.02, "sigma_px": 15.0} in stray
    assert {"weight": 0.02, "sigma_px": 4.0} in stray and {"weight": 0.02, "sigma_px": 50.0} in stray
    amp = fit_library()["amplitude_dependent"].starts
    assert {"error_m": -0.02, "log10_amplitude_e": 3.0} in amp
    assert fit_library(extra_starts={"pose": [{"tz": 0.01}]})["pose"].starts == ({"tz": 0.01},)


def test_current_values_and_log_scale_round_trip() -> None:
    lib = fit_library(lambda effect, param: 2500.0 if param == "amplitude_e" else EFFECTS[effect].params[param].off)
    (fp,) = [f for f in lib["amplitude_dependent"].params if f.name == "log10_amplitude_e"]
    assert math.isclose(fp.off, math.log10(2500.0))
    assert math.isclose(to_effect_values("amplitude_dependent", {"log10_amplitude_e": fp.off})["amplitude_e"], 2500.0)


def test_forms_and_harmonics_the_taps_cannot_see() -> None:
    """Each flexible form is a spec of its own; with 3 taps the 3rd harmonic cancels, so the
    simple wiggling form (the 3rd harmonic) is left out and the flexible one keeps what 3 taps
    see: 2, 4, 5 and 7 (h = +-1 mod 3); with 4 taps the odd ones only."""
    lib = fit_library(n_taps=4)
    assert [s.form for s in lib["wiggling"].forms] == ["harmonics"] and lib["wiggling"].forms[0].k == 6
    assert [s.form for s in lib["amplitude_dependent"].forms] == ["spline"]
    assert lib["range_offset"].forms == ()
    k3 = fit_library(n_taps=3)["wiggling"]
    assert k3.form == "harmonics" and {p.name for p in k3.params} == {f"h{h}_{q}" for h in (2, 4, 5, 7)
                                                                         for q in ("amplitude", "phase_rad")}
    # with a frequency count given (as a diagnosis gives it) the effect is kept too: it was
    # dropped when its simple form had nothing these taps see
    assert fit_library(n_taps=3, n_freq=1)["wiggling"].form == "harmonics"


def test_angles_are_fitted_across_their_wrap_and_reported_inside_it() -> None:
    assert math.isclose(to_effect_values("wiggling", {"h3_phase_rad": math.pi + 0.25})["h3_phase_rad"],
                        -math.pi + 0.25)
    assert math.isclose(to_effect_values("wiggling", {"h7_phase_rad": -math.pi - 0.5})["h7_phase_rad"],
                        math.pi - 0.5)
    assert to_effect_values("wiggling", {"h3_amplitude": 0.7})["h3_amplitude"] == 0.7  # not an angle
