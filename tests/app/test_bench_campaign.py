"""The campaign runner on the emulated TOFcam635 (pyusb backend) in front of a flat field:
impossible plans refused naming the step before any capture, resume without retaking."""

from __future__ import annotations

import json

import pytest

from tofhil.app.bench.rigs import EmulatedTofCamRig, flat_field_bench, flat_field_source
from tofhil.app.campaign import MANIFEST, CampaignInterrupted, parse_plan, run_campaign
from tofhil.errors import TofhilError


def _rig(seed: int = 0) -> EmulatedTofCamRig:
    sensor, light, text = flat_field_bench()
    return EmulatedTofCamRig(lambda p: flat_field_source(sensor, p), light, seed=seed, scene_text=text)


def _plan(steps):
    return parse_plan({"name": "t", "steps": steps}, "plan.yaml")


CAPTURES = [{"settings": {"mode": "dcs", "integration_time_us": 100}},
            {"capture": {"label": "a", "frames": 2}},
            {"bench": {"light_amplitude_dn": 0.0}},
            {"wait": 0.5},
            {"capture": {"label": "b", "frames": 2}},
            {"settings": {"integration_time_us": 400}},
            {"capture": {"label": "c", "frames": 2}}]


@pytest.mark.parametrize("bad, field, words", [
    ({"settings": {"mod_freq_hz": 30e6}}, "steps[1].settings.mod_freq_hz", "30000000.0 Hz is not offered"),
    ({"settings": {"integration_time_us": 70000}}, "steps[1].settings.integration_time_us", "out of range"),
    ({"settings": {"mode": "grayscale"}}, "steps[1].settings.mode", "not available"),
    ({"bench": {"target_distance_m": 1.0}}, "steps[1].bench.target_distance_m", "no parameter"),
    ({"bench": {"light_amplitude_dn": 1.0}, "by": "stage"}, "steps[1].by", "by stage is not possible"),
])
def test_a_plan_the_device_cannot_perform_is_refused_naming_the_step(tmp_path, bad, field, words):
    rig = _rig()
    plan = _plan([CAPTURES[1], bad, CAPTURES[4]])
    with pytest.raises(TofhilError) as exc:
        run_campaign(plan, rig, tmp_path / "c")
    msg = str(exc.value)
    assert "step 1 (" in msg and field in msg and words in msg and "plan.yaml" in msg
    assert not (tmp_path / "c").exists()                 # nothing written ...
    assert rig.emulator.stats.images == 0                 # ... and nothing captured


def test_malformed_plans_name_the_field():
    with pytest.raises(TofhilError, match=r"steps\[0\].*exactly one of"):
        _plan([{"settings": {}, "wait": 1}])
    with pytest.raises(TofhilError, match=r"steps\[1\].capture.label"):
        _plan([{"capture": {"label": "x"}}, {"capture": {"label": "x"}}])
    with pytest.raises(TofhilError, match=r"steps\[0\].wait"):
        _plan([{"wait": -1}, {"capture": {}}])


def test_an_interrupted_campaign_resumes_without_retaking_finished_captures(tmp_path):
    out = tmp_path / "c"
    plan = _plan(CAPTURES)
    slept = []

    def stop_at_c(items, total, description):
        for s in items:
            if s.kind == "capture" and s.label == "c":
                raise KeyboardInterrupt  # Ctrl-C before the third capture
            yield s

    rig = _rig()
    with pytest.raises(CampaignInterrupted, match="2 of 3 captures"):
        run_campaign(plan, rig, out, progress=stop_at_c, sleep=slept.append)
    assert rig.emulator.stats.images == 4 and slept == [0.5]
    done = json.loads((out / MANIFEST).read_text())["captures"]
    assert list(done) == ["a", "b"] and done["b"]["bench"] == {"light_amplitude_dn": 0.0}
    # a half-written session of the capture in flight (a crash) is replaced, not trusted
    (out / "sessions" / "003-c.h5").write_bytes(b"half a session")
    with pytest.raises(TofhilError, match="--resume"):
        run_campaign(plan, _rig(), out)                  # not without being asked
    rig2 = _rig()
    applied = []
    orig = rig2.apply_bench
    rig2.apply_bench = lambda p, by, m: (applied.append(dict(p)), orig(p, by, m))
    slept.clear()
    res = run_campaign(plan, rig2, out, resume=True, sleep=slept.append)
    assert (res.taken, res.skipped) == (1, 2)
    assert rig2.emulator.stats.images == 2               # only capture c's two frames
    assert slept == []                                   # the wait before b is not waited again
    assert applied == [{"light_amplitude_dn": 0.0}]       # the bench brought to c's state (light off)
    from tofhil.session import open_session

    with open_session(res.session("c")) as s:
        assert s.n_frames == 2 and s.integration_time_s == pytest.approx(400e-6)
    with pytest.raises(TofhilError, match="another plan"):
        run_campaign(_plan(CAPTURES[:2]), _rig(), out, resume=True)
