"""What the fit leaves, said as a signature (eval/diagnose/leftover.py)."""

from __future__ import annotations

from tofhil.eval.diagnose.leftover import what_is_left


def _reading(channel: str, name: str, significant: bool, text: str = "") -> dict:
    return {"channel": channel, "name": name, "significant": significant, "text": text or name, "z": 0.0}


CLEAN = {"readings": [_reading("frequency", "44 MHz phase", False), _reading("frequency", "44 MHz gain", False),
                      _reading("tap", "tap gain pattern", False), _reading("offset", "offset", False),
                      _reading("frame", "range trend", False), _reading("noise", "scatter / noise model", False)]}


def test_nothing_said_when_explained_or_within_noise() -> None:
    for kind in ("explained", "within noise", "nothing searched"):
        assert what_is_left(CLEAN, [{"channel": "depth", "kind": "smooth", "rms": 0.01, "noise_rms": 0.002}], kind) is None


def test_a_smooth_field_error_in_no_channel_is_light_or_geometry_the_twin_lacks() -> None:
    structure = [{"channel": "depth", "kind": "smooth", "object": "wall", "rms": 0.011, "noise_rms": 0.004},
                 {"channel": "depth", "kind": "edges", "object": "", "rms": 0.003, "noise_rms": 0.004},
                 {"channel": "amplitude", "kind": "smooth", "object": "wall", "rms": 0.008, "noise_rms": 0.016}]
    text = what_is_left(CLEAN, structure, "unexplained")
    assert "a smooth depth error of 11.0 mm rms on wall (2.8 x its noise)" in text
    assert "edges" not in text                       # the largest structure of each map
    assert "a smooth amplitude error of 0.8 % rms" in text
    assert "not in any tap, frequency, offset or frame channel" in text
    assert "a surface it does not have" in text


def test_a_part_in_a_channel_is_said_and_that_channel_is_not_called_clean() -> None:
    table = {"readings": [_reading("frequency", "60 MHz phase", True, "60 MHz: phase +0.0120 rad"),
                          _reading("tap", "tap gain pattern", False), _reading("frame", "range trend", False)]}
    text = what_is_left(table, [], "partly explained")
    assert text.startswith("what is left: 60 MHz: phase +0.0120 rad")
    assert "not in any tap or frame channel" in text and "frequency channel" not in text
    assert "surface" not in text                     # a calibration channel, not light the twin lacks


def test_nothing_readable_is_said_so() -> None:
    assert "no shape" in what_is_left(CLEAN, [], "unexplained")


def test_edges_and_large_amplitude_errors_read_as_words() -> None:
    structure = [{"channel": "depth", "kind": "edges", "object": "", "rms": 0.0048, "noise_rms": 0.001},
                 {"channel": "amplitude", "kind": "spot", "object": "plane0", "rms": 1.514, "noise_rms": 0.17}]
    text = what_is_left(CLEAN, structure, "partly explained")
    assert "a depth error at depth edges of 4.8 mm rms" in text
    assert "a spot amplitude error of a factor 4.5 rms on plane0" in text
