"""A session writer killed with SIGKILL mid-frame (the crash guarantee's test, for each storage layout)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import numpy as np


def write_until_killed(code: str, attempt: int) -> int:
    """Run ``code`` (a writer that prints each frame's index once it is complete) and SIGKILL
    it at a random instant inside the frame after the ``5 + 7 attempt``-th; the index of the
    last frame it said was complete."""
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    completed = -1
    target = 5 + 7 * attempt
    deadline = time.monotonic() + 60
    assert proc.stdout is not None
    while completed < target and time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            break
        completed = int(line)
    # kill at a random instant inside the next frame's write
    time.sleep(np.random.default_rng(attempt).uniform(0, 0.004))
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(timeout=10)
    assert completed >= target, "writer did not produce frames"
    return completed
