"""YAML reading with numbers as people write them.

PyYAML follows YAML 1.1, where ``1e6`` or ``44.0e6`` (no sign in the exponent) is a *string*.
Bench configs are full of such figures, so this loader resolves them as floats, as YAML 1.2
does. Use :func:`load_yaml` for every config file.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import yaml

from tofhil.errors import InputFileError


class _Loader(yaml.SafeLoader):
    pass


_FLOAT = re.compile(r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
                     |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
                     |\.[0-9_]+(?:[eE][-+]?[0-9]+)?
                     |[-+]?\.(?:inf|Inf|INF)
                     |\.(?:nan|NaN|NAN))$""", re.X)

# Replace the float resolver (first characters it may start with, as PyYAML keys them).
for ch in list("-+0123456789."):
    resolvers = _Loader.yaml_implicit_resolvers.get(ch, [])
    _Loader.yaml_implicit_resolvers = dict(_Loader.yaml_implicit_resolvers)
    _Loader.yaml_implicit_resolvers[ch] = [(t, r) for t, r in resolvers if t != "tag:yaml.org,2002:float"]
_Loader.add_implicit_resolver("tag:yaml.org,2002:float", _FLOAT, list("-+0123456789."))


def load_yaml(text: str, source: str | Path = "<yaml>") -> Any:
    """Parse YAML text; a syntax error names the file and the line."""
    try:
        return yaml.load(text, Loader=_Loader)  # noqa: S506 (a SafeLoader subclass)
    except yaml.YAMLError as exc:
        where = ""
        mark = getattr(exc, "problem_mark", None)
        if mark is not None:
            where = f" at line {mark.line + 1}, column {mark.column + 1}"
        raise InputFileError(f"not valid YAML{where}: {getattr(exc, 'problem', exc)}", file=source) from None


def load_yaml_file(path: str | Path) -> Any:
    p = Path(path)
    if not p.is_file():
        raise InputFileError("no such file", file=p)
    return load_yaml(p.read_text(), source=p)
