"""YAML reading with numbers as people write them.

PyYAML follows YAML 1.1, where ``1e6`` or ``44.0e6`` (no sign in the exponent) is a *string*.
Bench configs are full of such figures, so this loader resolves them as floats, as YAML 1.2
does. Use :func:`load_yaml` for every config file.

Config files come from others too (a scene shared by mail, a sweep spec on a cluster), so
reading is bounded before anything walks the result: the text is at most
:data:`MAX_YAML_BYTES` and the document at most :data:`MAX_YAML_VALUES` values once every
alias is expanded (a 400-byte file of nested aliases, "billion laughs", would otherwise expand
to 10^9 values in the first code that copies it: a scene's expression substitution).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import yaml

from tofhil.errors import InputFileError

#: Largest YAML text read (bytes): a config is a page of YAML, not a data file; meshes,
#: textures and tables live in their own files. libyaml composes 16 MiB in about a second.
MAX_YAML_BYTES = 16 << 20
#: Most values a document may expand to with its aliases followed (each alias counts the whole
#: tree it names), checked on the composed nodes before any Python object is built. A bench
#: scene of 10^4 objects is about 2 x 10^5 values; one million bounds what building the tree
#: and copying it (expression substitution, a deep merge) take to seconds and a few hundred MB.
MAX_YAML_VALUES = 1_000_000


# libyaml's parser when present (it composes 10^6 nodes in 0.4 s where the pure-Python one
# takes 30 s); constructors and resolvers stay Python, so the float rule below applies to both.
class _Loader(getattr(yaml, "CSafeLoader", yaml.SafeLoader)):  # type: ignore[misc]
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


def expanded_size(node: yaml.Node, limit: int) -> int:
    """The number of values under a composed YAML ``node`` with every alias counted as the
    whole tree it names; counting stops once past ``limit`` (a node that contains itself, as
    ``&a [*a]``, counts as past it). Each distinct node is visited once (memoised by
    identity), so nine levels of nine aliases cost their written size, not 9^9 values."""
    sizes: dict[int, int] = {}

    def size(n: yaml.Node) -> int:
        if isinstance(n, yaml.ScalarNode):
            return 1
        key = id(n)
        if key in sizes:
            return sizes[key]
        sizes[key] = limit + 1  # while inside it: a reference to itself is endless
        children = [c for pair in n.value for c in pair] if isinstance(n, yaml.MappingNode) else n.value
        total = 1
        for c in children:
            total += size(c)
            if total > limit:
                break
        sizes[key] = total = min(total, limit + 1)
        return total

    return size(node)


def load_yaml(text: str, source: str | Path = "<yaml>") -> Any:
    """Parse YAML text within the bounds of this module; a syntax error names the file and
    the line, a bound exceeded names the file and the bound."""
    if len(text) > MAX_YAML_BYTES:  # characters: at least as many bytes
        raise InputFileError(f"is {len(text)} characters long", file=source,
                             expected=f"a YAML file of at most {MAX_YAML_BYTES >> 20} MiB")
    loader = _Loader(text)
    try:
        node = loader.get_single_node()
        if node is not None and expanded_size(node, MAX_YAML_VALUES) > MAX_YAML_VALUES:
            raise InputFileError(f"expands to more than {MAX_YAML_VALUES:,} values through its aliases "
                                 "(&anchor / *alias)", file=source,
                                 expected=f"a document of at most {MAX_YAML_VALUES:,} values with aliases expanded")
        return None if node is None else loader.construct_document(node)
    except yaml.YAMLError as exc:
        where = ""
        mark = getattr(exc, "problem_mark", None)
        if mark is not None:
            where = f" at line {mark.line + 1}, column {mark.column + 1}"
        raise InputFileError(f"not valid YAML{where}: {getattr(exc, 'problem', exc)}", file=source) from None
    finally:
        loader.dispose()


def read_yaml_text(path: str | Path) -> str:
    """A YAML file's text, its size checked before it is read (a config file that is really a
    10 GB data file fails at once instead of filling memory)."""
    p = Path(path)
    if not p.is_file():
        raise InputFileError("is a directory" if p.is_dir() else "no such file", file=p)
    if p.stat().st_size > MAX_YAML_BYTES:
        raise InputFileError(f"is {p.stat().st_size} bytes", file=p,
                             expected=f"a YAML file of at most {MAX_YAML_BYTES >> 20} MiB")
    try:
        return p.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise InputFileError(f"is not UTF-8 text (byte {exc.start})", file=p, expected="a UTF-8 YAML file") from None


def load_yaml_file(path: str | Path) -> Any:
    """Read and parse a YAML file within the bounds of this module."""
    return load_yaml(read_yaml_text(path), source=Path(path))
