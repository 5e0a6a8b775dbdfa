"""numba's cache kept true to the code a kernel inlines from another module."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path


def _run(pkg: Path) -> str:
    out = subprocess.run([sys.executable, "-c", "import caller; print(caller.f())"], cwd=pkg, check=True,
                         capture_output=True, text=True)
    return out.stdout.strip()


def test_a_kernel_compiles_anew_when_a_module_it_inlines_changes(tmp_path: Path) -> None:
    """A cached kernel that inlines a function of another module gives that function's new
    result once its source changes (numba alone keeps the old machine code: its cache key is
    the kernel's own file)."""
    (tmp_path / "inlined.py").write_text(textwrap.dedent("""
        from numba import njit

        @njit(cache=True, inline="always")
        def g():
            return 1
    """))
    (tmp_path / "caller.py").write_text(textwrap.dedent("""
        import inlined
        from numba import njit
        from tofhil.numba_cache import drop_stale_cache

        @njit(cache=True)
        def f():
            return inlined.g()

        drop_stale_cache(f, [inlined.__file__])
    """))
    assert _run(tmp_path) == "1"
    assert list((tmp_path / "__pycache__").glob("caller.*.nbi")), "numba wrote no cache"
    assert _run(tmp_path) == "1"                       # from the cache
    (tmp_path / "inlined.py").write_text((tmp_path / "inlined.py").read_text().replace("return 1", "return 22"))
    assert _run(tmp_path) == "22"

