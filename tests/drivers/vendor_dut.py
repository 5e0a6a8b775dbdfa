"""pytest plugin for the vendor's system tests (epc-tofcam-toolkit's ``tests/config.py``):
its ``DUT_CONFIG`` names the cameras on ESPROS's bench; point the TOFcam635 at the pty in
``TOFHIL_PTY`` and drop the others, whose fixtures then skip."""

from __future__ import annotations

import os

import pytest


def pytest_configure(config: pytest.Config) -> None:
    from epc.tofCam635 import TOFcam635

    import tests.config as dut  # the vendor's tests package (cwd is the sdist's root)

    dut.DUT_CONFIG.clear()
    dut.DUT_CONFIG["dut_TOFcam635"] = (TOFcam635, {"port": os.environ["TOFHIL_PTY"]})
