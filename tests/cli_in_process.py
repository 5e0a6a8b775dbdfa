"""Run the CLI in the test's own process (no interpreter start-up per call) and get its exit
code; ``tests/conftest.py``'s ``tofhil_cli`` runs it in a subprocess where isolation matters."""

from __future__ import annotations

from pathlib import Path

from tofhil.cli import main


def run_cli(*args: str | Path | float) -> int:
    """``tofhil ARGS...`` through :func:`tofhil.cli.main`; its exit code (0 when it returns)."""
    try:
        main([str(a) for a in args])
    except SystemExit as exc:
        return int(exc.code or 0)
    return 0
