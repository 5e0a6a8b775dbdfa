"""Field-path-aware validation shared by every file format (scenes, sensor blocks, effects,
session attributes), and the one converter to plain Python for YAML/JSON dumps.

Every check raises :class:`tofhil.errors.InputFileError` naming the file, the field (a dotted
path such as ``objects[2].pose.position``) and what was expected. Numbers must be finite
unless a check explicitly allows NaN or infinity; booleans are never numbers; ranges have
open or closed ends.

>>> s = Schema("scene.yaml")
>>> s.number(0.5, "materials.wall.reflectance", lo=0.0, hi=1.0)
0.5
"""

from __future__ import annotations

import copy
import math
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

from tofhil.errors import InputFileError

_NUMBER_TYPES = (int, float, np.integer, np.floating)


def describe_range(lo: float | None = None, hi: float | None = None, *, lo_open: bool = False,
                   hi_open: bool = False, what: str = "a number") -> str:
    """``"a number in (0, 1]"``, ``"a number > 0"``, ``"a number <= 5"``, ``"a number"``."""
    if lo is not None and hi is not None:
        return f"{what} in {'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"
    if lo is not None:
        return f"{what} {'>' if lo_open else '>='} {lo:g}"
    if hi is not None:
        return f"{what} {'<' if hi_open else '<='} {hi:g}"
    return what


def in_range(x: float, lo: float | None = None, hi: float | None = None, *, lo_open: bool = False,
             hi_open: bool = False) -> bool:
    """Whether ``x`` lies in the range (``None``: no bound on that side; ends open or closed):
    the one rule every range check of a file, a command option or a method parameter uses."""
    if lo is not None and (x < lo or (lo_open and x == lo)):
        return False
    return not (hi is not None and (x > hi or (hi_open and x == hi)))


def _show(value: Any) -> str:
    """A short representation of a bad value for a message (never a megabyte of text)."""
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


class Schema:
    """Validation bound to one file: every error names ``file`` and the field path."""

    def __init__(self, file: str | Path | None) -> None:
        self.file = file

    # ------------------------------------------------------------------ errors
    def error(self, message: str, field: str | None, expected: str | None = None) -> InputFileError:
        return InputFileError(message, file=self.file, field=field, expected=expected)

    def bad(self, value: Any, field: str, expected: str) -> InputFileError:
        return self.error(f"got {_show(value)}", field, expected)

    # ------------------------------------------------------------------ scalars
    def number(self, value: Any, field: str, *, lo: float | None = None, hi: float | None = None,
               lo_open: bool = False, hi_open: bool = False, allow_nan: bool = False,
               allow_inf: bool = False, expected: str | None = None) -> float:
        """A real number (int or float, not bool, not a string) within the range.

        NaN and +-inf are refused unless ``allow_nan`` / ``allow_inf``; an allowed infinity
        must still lie within the range (``hi=None`` admits +inf)."""
        exp = expected or describe_range(lo, hi, lo_open=lo_open, hi_open=hi_open)
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, _NUMBER_TYPES):
            raise self.bad(value, field, exp)
        try:
            x = float(value)
        except OverflowError:  # an integer beyond the float range
            raise self.bad(value, field, exp) from None
        if math.isnan(x):
            if allow_nan:
                return x
            raise self.bad(value, field, exp)
        if math.isinf(x) and not allow_inf:
            raise self.bad(value, field, exp)
        if not in_range(x, lo, hi, lo_open=lo_open, hi_open=hi_open):
            raise self.bad(value, field, exp)
        return x

    def integer(self, value: Any, field: str, *, lo: int | None = None, hi: int | None = None,
                expected: str | None = None) -> int:
        """An integer (not bool; a float is refused even when integral) within ``[lo, hi]``."""
        exp = expected or describe_range(lo, hi, what="an integer")
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
            raise self.bad(value, field, exp)
        i = int(value)
        if (lo is not None and i < lo) or (hi is not None and i > hi):
            raise self.bad(value, field, exp)
        return i

    def boolean(self, value: Any, field: str) -> bool:
        if not isinstance(value, (bool, np.bool_)):
            raise self.bad(value, field, "true or false")
        return bool(value)

    def enum(self, value: Any, field: str, choices: Sequence[Any]) -> Any:
        """One of ``choices`` (compared by equality; unhashable values are refused)."""
        try:
            ok = any(value == c and type(value) is type(c) for c in choices)
        except Exception:  # an exotic type whose == raises
            ok = False
        if not ok:
            raise self.bad(value, field, "one of " + ", ".join(repr(c) for c in choices))
        return value

    def string(self, value: Any, field: str, *, nonempty: bool = False, expected: str | None = None) -> str:
        if not isinstance(value, str) or (nonempty and not value):
            raise self.bad(value, field, expected or ("a non-empty string" if nonempty else "a string"))
        return value

    # ------------------------------------------------------------------ sequences
    def numbers(self, value: Any, field: str, *, n: int | None = None, min_len: int = 1,
                max_len: int | None = None, scalar_ok: bool = False, expected: str | None = None,
                **range_kw: Any) -> list[float]:
        """A list of numbers (each checked like :meth:`number`; errors name ``field[i]``).

        ``n`` fixes the length; ``scalar_ok`` accepts a bare number as a list of one."""
        if scalar_ok and isinstance(value, _NUMBER_TYPES) and not isinstance(value, (bool, np.bool_)):
            value = [value]
        if isinstance(value, np.ndarray):
            value = value.tolist()
        count = f"{n}" if n is not None else f"at least {min_len}" if max_len is None else f"{min_len} to {max_len}"
        rng = describe_range(range_kw.get("lo"), range_kw.get("hi"), lo_open=range_kw.get("lo_open", False),
                             hi_open=range_kw.get("hi_open", False), what="each")
        exp = expected or f"a list of {count} numbers" + ("" if rng == "each" else f", {rng}")
        if not isinstance(value, (list, tuple)):
            raise self.bad(value, field, exp)
        if (n is not None and len(value) != n) or len(value) < min_len or \
                (max_len is not None and len(value) > max_len):
            raise self.bad(value, field, exp)
        return [self.number(v, f"{field}[{i}]", expected=exp, **range_kw) for i, v in enumerate(value)]

    def vector(self, value: Any, field: str, n: int = 3, **range_kw: Any) -> np.ndarray:
        """``n`` finite numbers as a float64 array."""
        return np.asarray(self.numbers(value, field, n=n, **range_kw), dtype=np.float64)

    # ------------------------------------------------------------------ mappings
    def mapping(self, value: Any, field: str, *, allowed: Iterable[str] | None = None,
                none_ok: bool = True, expected: str | None = None) -> dict[str, Any]:
        """A (deep-copied) mapping with string keys; ``allowed`` refuses any other key by name."""
        if value is None and none_ok:
            return {}
        if not isinstance(value, Mapping):
            raise self.bad(value, field, expected or "a mapping")
        for k in value:
            if not isinstance(k, str):
                raise self.error(f"key {_show(k)} is not a name", f"{field}.{k}" if field else str(k),
                                 "names (strings) as keys")
        if allowed is not None:
            self.keys(value, field, allowed)
        return copy.deepcopy(dict(value))

    def keys(self, value: Mapping[str, Any], field: str, allowed: Iterable[str]) -> None:
        """Refuse the first key not in ``allowed``, naming it as ``field.key``."""
        allowed = sorted(set(allowed))
        for k in value:
            if k not in allowed:
                raise self.error(f"unknown key {_show(k)}", f"{field}.{k}" if field else str(k),
                                 "one of " + ", ".join(allowed))

    def require(self, value: Mapping[str, Any], key: str, field: str, expected: str) -> Any:
        """``value[key]``, or an error naming ``field.key`` as missing."""
        if key not in value:
            raise self.error("missing", f"{field}.{key}" if field else key, expected)
        return value[key]


# ---------------------------------------------------------------------------- plain Python
def to_plain(x: Any, *, nonfinite_as_none: bool = False) -> Any:
    """Numpy scalars and arrays, tuples, Paths and nested mappings -> plain Python (dict, list,
    int, float, str, bool, None) that YAML and JSON dump; dataclass-like objects with a
    ``to_dict`` method are converted through it. ``nonfinite_as_none``: NaN and infinities
    become ``None`` (strict JSON, e.g. report figures that are undefined)."""
    def plain(v: Any) -> Any:
        return to_plain(v, nonfinite_as_none=nonfinite_as_none)

    if isinstance(x, Mapping):
        return {str(k): plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [plain(v) for v in x]
    if isinstance(x, np.ndarray):
        return plain(x.tolist())
    if isinstance(x, np.generic):
        x = x.item()
    if nonfinite_as_none and isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, Path):
        return str(x)
    if hasattr(x, "to_dict") and callable(x.to_dict):
        return plain(x.to_dict())
    return x
