"""tofhil.schema: field-path validation of numbers, integers, vectors, mappings, enums, and
the one to-plain-Python converter."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from tofhil.errors import InputFileError
from tofhil.schema import Schema, describe_range, to_plain

S = Schema("f.yaml")


def _err(fn, *a, **kw) -> InputFileError:
    with pytest.raises(InputFileError) as e:
        fn(*a, **kw)
    assert e.value.file == "f.yaml"
    return e.value


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf, "1.0", None, True, [1.0], 10 ** 400])
def test_number_refuses_non_finite_and_non_numbers(bad) -> None:
    e = _err(S.number, bad, "a.b")
    assert e.field == "a.b" and e.expected == "a number"


def test_number_allows_nan_or_inf_only_when_asked() -> None:
    assert math.isnan(S.number(math.nan, "x", allow_nan=True))
    assert S.number(math.inf, "x", allow_inf=True) == math.inf
    _err(S.number, math.inf, "x", allow_inf=True, hi=5.0)       # an allowed infinity still obeys the range
    assert S.number(np.float32(0.5), "x") == 0.5 and S.number(np.int64(3), "x") == 3.0


@pytest.mark.parametrize("x, kw, ok", [
    (0.0, {"lo": 0.0}, True), (0.0, {"lo": 0.0, "lo_open": True}, False),
    (1.0, {"hi": 1.0}, True), (1.0, {"hi": 1.0, "hi_open": True}, False),
    (-1e-300, {"lo": 0.0}, False), (0.5, {"lo": 0.0, "hi": 1.0}, True), (1.0000001, {"lo": 0.0, "hi": 1.0}, False),
])
def test_number_ranges_open_and_closed(x, kw, ok) -> None:
    if ok:
        assert S.number(x, "r", **kw) == x
    else:
        assert _err(S.number, x, "r", **kw).expected == describe_range(kw.get("lo"), kw.get("hi"),
                                                                       lo_open=kw.get("lo_open", False),
                                                                       hi_open=kw.get("hi_open", False))


def test_describe_range() -> None:
    assert describe_range(0, 1, lo_open=True) == "a number in (0, 1]"
    assert describe_range(0, None, lo_open=True) == "a number > 0"
    assert describe_range(None, 5, hi_open=True) == "a number < 5"
    assert describe_range(what="an integer") == "an integer"


def test_integer_and_boolean_and_enum() -> None:
    assert S.integer(3, "n", lo=1) == 3 and S.integer(np.int32(7), "n") == 7
    for bad in (3.0, True, "3", 0, 10 ** 20):
        _err(S.integer, bad, "n", lo=1, hi=10 ** 6)
    assert S.boolean(False, "b") is False
    _err(S.boolean, 1, "b")
    assert S.enum("sobol", "s", ("sobol", "random")) == "sobol"
    e = _err(S.enum, "halton", "s", ("sobol", "random"))
    assert "'sobol'" in e.expected
    _err(S.enum, True, "s", (1, 2))          # True == 1, but it is not the integer 1


def test_numbers_and_vectors_name_the_element() -> None:
    assert S.numbers([1, 2.5], "v", n=2) == [1.0, 2.5]
    assert S.numbers(5, "v", scalar_ok=True) == [5.0]
    assert _err(S.numbers, [1, math.nan, 3], "pose.position", n=3).field == "pose.position[1]"
    assert _err(S.numbers, [1, 2], "v", n=3).field == "v"
    assert _err(S.numbers, [-1], "f", lo=0.0, lo_open=True).expected == "a list of at least 1 numbers, each > 0"
    np.testing.assert_array_equal(S.vector([0, 0, 1], "axis"), [0.0, 0.0, 1.0])
    _err(S.vector, "abc", "axis")


def test_mappings_refuse_unknown_and_non_string_keys() -> None:
    assert S.mapping(None, "m") == {}
    src = {"a": [1]}
    got = S.mapping(src, "m", allowed=("a", "b"))
    got["a"].append(2)
    assert src == {"a": [1]}                  # a deep copy
    e = _err(S.mapping, {"a": 1, "c": 2}, "sensor", allowed=("a", "b"))
    assert e.field == "sensor.c" and e.expected == "one of a, b"
    assert _err(S.mapping, {1: 2}, "top").field == "top.1"
    assert _err(S.mapping, [1], "m").expected == "a mapping"
    assert _err(S.require, {}, "power_w", "emitter", "watts").field == "emitter.power_w"


def test_to_plain_dumps_through_yaml_and_json() -> None:
    class Cfg:
        def to_dict(self):
            return {"x": np.float32(1.5)}

    d = {"a": np.arange(3), "b": (np.float64(2.0), np.int16(4)), 3: {"p": Path("/tmp/x"), "c": Cfg()},
         "m": np.bool_(True)}
    plain = to_plain(d)
    assert plain == {"a": [0, 1, 2], "b": [2.0, 4], "3": {"p": "/tmp/x", "c": {"x": 1.5}}, "m": True}
    assert yaml.safe_load(yaml.safe_dump(plain)) == plain
    assert json.loads(json.dumps(plain)) == plain
    assert type(plain["b"][1]) is int and type(plain["m"]) is bool
