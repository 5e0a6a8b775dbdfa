"""Shared fixtures. Tests mirror the packages: tests/core (tofhil), tests/drivers, tests/sim,
tests/eval, tests/cli; shared test data helpers are ``tests.real_data`` and
``tests.straylight_synthetic``."""

from __future__ import annotations

import os

import tofhil  # noqa: F401  (first: it keeps BLAS on one thread before numpy is imported)
import subprocess
import sys
from pathlib import Path
from typing import Callable

import pytest
from hypothesis import settings

# CI runs the property tests with a fixed seed (a red CI must be reproducible); locally each run
# draws new examples, which is where new hostile inputs are found.
settings.register_profile("ci", derandomize=True, deadline=None)
settings.register_profile("dev", deadline=None)
settings.load_profile("ci" if os.environ.get("CI", "").lower() == "true" else "dev")

# Tests open emulated devices from specs (``emulator:SCENE``, ``depthai-sim:1.0``) as the CLI
# does: give the emulators the twin's frame sources, as the CLI does at start.
from tofhil.app.emulators import connect_emulators  # noqa: E402

connect_emulators()


def run_tofhil(*args: str | Path, cwd: str | Path | None = None, timeout: float = 300,
               input_text: str | None = None) -> subprocess.CompletedProcess:
    """Run the ``tofhil`` CLI in a fresh process, as a user would (``python -m tofhil.cli``)."""
    return subprocess.run([sys.executable, "-m", "tofhil.cli", *map(str, args)], cwd=cwd, capture_output=True,
                          text=True, timeout=timeout, input=input_text)


@pytest.fixture
def tofhil_cli() -> Callable[..., subprocess.CompletedProcess]:
    """``tofhil_cli("info", path)`` runs the CLI in a subprocess and returns the completed process."""
    return run_tofhil
