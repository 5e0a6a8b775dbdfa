"""Package faces that name their public API without importing it.

A package's ``__init__`` lists what users import from it (``__all__``) and which module
defines each name; the module is imported on first use (PEP 562). Importing a small module
of a package (``tofhil.eval.diagnose.verdict``) then does not pull in the whole package, and
no package ``__init__`` can close an import cycle.
"""

from __future__ import annotations

import importlib
from typing import Any, Callable, Mapping


def lazy_face(package: str, exports: Mapping[str, str]) -> tuple[list[str], Callable[[str], Any], Callable[[], list[str]]]:
    """``(__all__, __getattr__, __dir__)`` of a package whose public names ``exports`` maps to
    the submodule (relative to ``package``) that defines each."""

    def __getattr__(name: str) -> Any:
        module = exports.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        return getattr(importlib.import_module(f"{package}.{module}"), name)

    def __dir__() -> list[str]:
        return sorted(exports)

    return sorted(exports), __getattr__, __dir__
