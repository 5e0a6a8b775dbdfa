"""``tofhil emulate --pty`` as a subprocess, for the tests that talk to it over the pty."""

from __future__ import annotations

import contextlib
import selectors
import subprocess
import sys
from typing import Iterator


def _read_port_line(proc: subprocess.Popen, timeout_s: float) -> str:
    sel = selectors.DefaultSelector()
    assert proc.stdout is not None
    sel.register(proc.stdout, selectors.EVENT_READ)
    if not sel.select(timeout_s):
        raise TimeoutError(f"no PORT= line within {timeout_s} s")
    line = proc.stdout.readline().strip()
    assert line.startswith("PORT="), line
    return line.removeprefix("PORT=")


@contextlib.contextmanager
def emulator_pty(*args: str, startup_s: float = 120.0) -> Iterator[str]:
    """Start ``tofhil emulate --pty ARGS``; yield its port; terminate it on exit."""
    proc = subprocess.Popen([sys.executable, "-m", "tofhil.cli", "emulate", "--pty", *args],
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        yield _read_port_line(proc, startup_s)
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=10)
