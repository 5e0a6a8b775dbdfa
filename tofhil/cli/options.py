"""Validated option values for every command: finite numbers within bounds, counts, odd sizes,
input files, new output files and output directories.

Each factory returns a parser for ``typer.Option(..., parser=...)``. A parser raises
``ValueError`` with what was wrong and what was expected; typer turns it into a usage error
naming the option, and :func:`tofhil.cli.main` prints that as one line (exit code 2). The
library checks physical ranges again (with the field name); these checks only make sure
that no NaN, infinity, negative count or misplaced path reaches it from the command line.
"""

from __future__ import annotations

import math
import os
import stat
from pathlib import Path
from typing import Callable

__all__ = ["finite", "count", "odd_size", "memory_size", "existing_file", "new_file", "out_dir", "describe_path_problem",
           "check_output"]


def _interval(lo: float | None, hi: float | None, lo_open: bool, hi_open: bool, unit: str) -> str:
    from tofhil.schema import describe_range

    return describe_range(lo, hi, lo_open=lo_open, hi_open=hi_open, what="a finite number") + (f" {unit}" if unit else "")


def finite(lo: float | None = None, hi: float | None = None, *, lo_open: bool = False, hi_open: bool = False,
           unit: str = "") -> Callable[[object], float]:
    """A finite float within ``[lo, hi]`` (either end optional, ``*_open`` excludes it)."""
    from tofhil.schema import in_range

    expected = _interval(lo, hi, lo_open, hi_open, unit)

    def parse(text: object) -> float:
        if isinstance(text, float):  # a default (typer passes defaults through the parser)
            value = text
        else:
            try:
                value = float(str(text).strip())
            except ValueError:
                raise ValueError(f"{text!s} is not a number (expected {expected})") from None
        if not (math.isfinite(value) and in_range(value, lo, hi, lo_open=lo_open, hi_open=hi_open)):
            raise ValueError(f"{text!s} is out of range (expected {expected})")
        return value

    parse.__name__ = "FLOAT"
    return parse


def count(lo: int = 1, hi: int | None = None, *, what: str = "an integer") -> Callable[[object], int]:
    """An integer within ``[lo, hi]`` (e.g. frames >= 1, a seed >= 0)."""
    expected = f"{what} >= {lo}" if hi is None else f"{what} in [{lo}, {hi}]"

    def parse(text: object) -> int:
        if isinstance(text, int) and not isinstance(text, bool):
            value = text
        else:
            try:
                value = int(str(text).strip(), 10)
            except ValueError:
                raise ValueError(f"{text!s} is not an integer (expected {expected})") from None
        if value < lo or (hi is not None and value > hi):
            raise ValueError(f"{text!s} is out of range (expected {expected})")
        return value

    parse.__name__ = "INTEGER"
    return parse


_MEMORY_UNITS = {"": 1, "k": 1 << 10, "m": 1 << 20, "g": 1 << 30, "t": 1 << 40}


def memory_size(text: object) -> int:
    """A memory size in bytes: ``2G``, ``512M``, ``1.5GiB``, ``4000000`` (binary units), > 0."""
    if isinstance(text, int) and not isinstance(text, bool):
        return text
    s = str(text).strip().lower().removesuffix("ib").removesuffix("b")
    unit = s[-1:] if s[-1:] in _MEMORY_UNITS else ""
    try:
        value = float(s[:len(s) - len(unit)]) * _MEMORY_UNITS[unit]
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and 0 < value < 2 ** 63):
        raise ValueError(f"{text!s} is not a memory size (expected a size > 0 such as 2G, 512M or bytes)")
    return int(value)


memory_size.__name__ = "SIZE"


def odd_size(lo: int = 3, hi: int = 99) -> Callable[[object], int]:
    """An odd window size in pixels within ``[lo, hi]`` (a median filter's)."""
    base = count(lo, hi, what="an odd integer")

    def parse(text: object) -> int:
        value = base(text)
        if value % 2 == 0:
            raise ValueError(f"{text!s} is even (expected an odd integer in [{lo}, {hi}])")
        return value

    parse.__name__ = "ODD"
    return parse


def describe_path_problem(path: Path, *, want: str) -> str | None:
    """What is wrong with ``path`` as ``want`` (``"file"``, ``"new file"``, ``"directory"``),
    or None. Says 'is a directory' where a file was expected, never 'no such file'."""
    try:
        st = path.stat()
    except FileNotFoundError:
        st = None
    except NotADirectoryError:
        return f"{path}: a parent of it is not a directory"
    except OSError as exc:
        return f"{path}: cannot be accessed ({exc.strerror})"
    if want == "file":
        if st is None:
            return f"{path}: no such file"
        if stat.S_ISDIR(st.st_mode):
            return f"{path}: is a directory (expected a file)"
        if not stat.S_ISREG(st.st_mode):
            return f"{path}: is not a regular file"
        if not os.access(path, os.R_OK):
            return f"{path}: is not readable"
        return None
    if want == "directory":
        if st is not None and not stat.S_ISDIR(st.st_mode):
            return f"{path}: is a file (expected a directory)"
        return _parent_problem(path) if st is None else _not_writable(path)
    # a new file: may exist (the command refuses it without --force), but not as anything else
    if st is not None:
        if stat.S_ISDIR(st.st_mode):
            return f"{path}: is a directory (expected a file name)"
        if not stat.S_ISREG(st.st_mode):
            return f"{path}: is not a regular file (a device or a pipe); refusing to write to it"
    return _parent_problem(path)


def _parent_problem(path: Path) -> str | None:
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.exists():
        return f"{parent}: directory does not exist"
    if not parent.is_dir():
        return f"{parent}: is not a directory"
    return _not_writable(parent)


def _not_writable(directory: Path) -> str | None:
    """Try to create a file in ``directory`` (os.access says yes to root on /sys, and knows
    nothing of some read-only mounts); the probe is removed at once."""
    probe = directory / f".tofhil-write-probe-{os.getpid()}"
    try:
        fd = os.open(probe, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600)
    except FileExistsError:
        return None
    except OSError as exc:
        return f"{directory}: directory is not writable ({exc.strerror})"
    os.close(fd)
    os.unlink(probe)
    return None


def _path_parser(want: str) -> Callable[[object], Path]:
    def parse(text: object) -> Path:
        path = text if isinstance(text, Path) else Path(str(text))
        if str(text) == "":
            raise ValueError("an empty path")
        problem = describe_path_problem(path, want=want)
        if problem:
            raise ValueError(problem)
        return path

    parse.__name__ = {"file": "FILE", "new file": "OUT", "directory": "DIR"}[want]
    return parse


#: An input file that must exist (and be a file, not a directory).
existing_file = _path_parser("file")
#: An output file: a new name in a writable directory (or an existing regular file, refused
#: later without --force).
new_file = _path_parser("new file")
#: An output directory: absent (created later) or an existing directory.
out_dir = _path_parser("directory")


def check_output(path: Path, force: bool, suffixes: tuple[str, ...] | None = None,
                 expected: str = "") -> None:
    """A command's output file (after ``new_file`` checked where it goes): the suffix its
    format needs (``--out``; ``expected`` says what), and no overwrite without ``--force``."""
    from tofhil.errors import TofhilError
    from tofhil.outputs import refuse_existing

    if suffixes is not None and path.suffix.lower() not in suffixes:
        raise TofhilError(f"is not a {suffixes[0]} file", file=path, field="--out", expected=expected)
    refuse_existing(path, force)
