"""The layers of ARCHITECTURE.md, checked on the code's own imports (inside functions too).

Dependencies flow one way: drivers, sim and eval depend on the core; eval may use sim;
nothing depends on eval; the core depends on none of them; library code never imports the
CLI; the application layer (``tofhil.app``) may use every library package but not the CLI.
Imports are read from the source (``ast``), so an import inside a function, which runs only
when that function does, counts as much as one at the top.
"""

from __future__ import annotations

import ast
import re
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
#: Source folder -> the package it is installed as (pyproject's package-dir).
FOLDERS = {"tofhil": "tofhil", "drivers": "tofhil.drivers", "sim": "tofhil.sim", "eval": "tofhil.eval"}

LIBRARY = ("drivers", "sim", "eval")
#: layer -> the layers it must not import.
FORBIDDEN = {
    "core": {"drivers", "sim", "eval", "app", "cli"},
    "drivers": {"sim", "eval", "app", "cli"},
    "sim": {"drivers", "eval", "app", "cli"},
    "eval": {"drivers", "app", "cli"},
    "app": {"cli"},
    "cli": set(),
}
_MODULE_TEXT = re.compile(r"^tofhil(\.[A-Za-z_]\w*)+$")


def layer(module: str) -> str:
    """The layer of a dotted module name under ``tofhil``."""
    parts = module.split(".")
    if len(parts) > 1 and parts[1] in LIBRARY + ("app", "cli"):
        return parts[1]
    return "core"


def module_name(path: Path) -> str:
    rel = path.relative_to(ROOT)
    name = ".".join([FOLDERS[rel.parts[0]], *rel.parts[1:]])[: -len(".py")]
    return name[: -len(".__init__")] if name.endswith(".__init__") else name


def library_files() -> list[Path]:
    return sorted(p for folder in FOLDERS for p in (ROOT / folder).rglob("*.py"))


def imported_modules(source: str, module: str, is_package: bool = False) -> set[str]:
    """Every ``tofhil`` module a source imports: ``import``/``from`` statements anywhere (also
    relative ones), and module names given to ``importlib.import_module`` as text."""
    found: set[str] = set()
    base = module.split(".") if is_package else module.split(".")[:-1]
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                prefix = ".".join(base[: len(base) - node.level + 1])
                target = f"{prefix}.{node.module}" if node.module else prefix
            else:
                target = node.module or ""
            found.add(target)
            found.update(f"{target}.{a.name}" for a in node.names)  # from pkg import module
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) and _MODULE_TEXT.match(node.value):
            found.add(node.value)  # a module loaded by name (registries, import_module)
    return {m for m in found if m == "tofhil" or m.startswith("tofhil.")}


def violations(source: str, module: str, is_package: bool = False) -> list[str]:
    own = layer(module)
    return sorted(f"{module} ({own}) imports {m} ({layer(m)})" for m in imported_modules(source, module, is_package)
                  if layer(m) in FORBIDDEN[own])


def test_no_import_crosses_a_layer_the_wrong_way() -> None:
    bad = [v for p in library_files()
           for v in violations(p.read_text(encoding="utf-8"), module_name(p), p.name == "__init__.py")]
    assert not bad, "\n".join(bad)


@pytest.mark.parametrize("module, source", [
    ("tofhil.drivers.depthai.driver", "def f():\n    from tofhil.sim.pipeline import simulate\n"),
    ("tofhil.sim.pipeline", "def f():\n    import tofhil.eval.reports.simulate\n"),
    ("tofhil.eval.rgb.colorize", "from tofhil.drivers.importers import k4a\n"),
    ("tofhil.camera", "import importlib\nimportlib.import_module('tofhil.sim.scene')\n"),
    ("tofhil.sim.render", "from tofhil.cli import main\n"),
    ("tofhil.eval.rgb", "from ...drivers import base\n"),
])
def test_a_forbidden_import_is_caught_wherever_it_hides(module: str, source: str) -> None:
    assert violations(source, module, is_package=module == "tofhil.eval.rgb")


def test_allowed_imports_pass() -> None:
    assert not violations("from tofhil.sim.scene import load_scene\n", "tofhil.eval.diagnose.run")
    assert not violations("from tofhil.drivers.base import create_driver\n", "tofhil.app.sweep")
    assert not violations("from tofhil.frame_source import ImageSource\n", "tofhil.sim.sources")


def test_pyproject_installs_every_package() -> None:
    """Every folder with an ``__init__.py`` is listed (an editable install finds unlisted ones,
    a wheel does not)."""
    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    found = {module_name(p) for p in library_files() if p.name == "__init__.py"}
    assert found - listed == set(), f"not installed: {sorted(found - listed)}"


def test_package_faces_name_what_exists() -> None:
    """Every name a package's ``__all__`` promises resolves (the faces are lazy: a stale entry
    would only fail when a user imports it)."""
    import importlib

    faces = [module_name(p) for p in library_files() if p.name == "__init__.py"
             and "lazy_face" in p.read_text(encoding="utf-8")]
    assert len(faces) >= 8
    for name in faces:
        package = importlib.import_module(name)
        for public in package.__all__:
            assert getattr(package, public) is not None, f"{name}.{public}"
