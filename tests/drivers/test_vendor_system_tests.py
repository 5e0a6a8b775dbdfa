"""The vendor client's own system tests for the TOFcam635 against ``tofhil emulate --pty``.

epc-tofcam-toolkit 0.13.0 ships its tests only in the sdist: ``tests/tofCam635`` and
``tests/tofCam_lib/test_tofcams.py``, marked ``systemTest`` (they need a camera). They are
run here, unchanged, in a subprocess with ``-m systemTest -k cam635`` against the emulator's
pty, and every one must pass. The sdist comes from ``TOFHIL_VENDOR_SDIST`` (a .tar.gz or
its unpacked directory) or is fetched once with ``pip download`` (PyPI) into
``$XDG_CACHE_HOME/tofhil``. Without the client or the network this skips locally and fails
when ``CI=true``.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tarfile
import tempfile
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from tests.drivers.pty_emulator import emulator_pty

VENDOR = "epc-tofcam-toolkit"
VERSION = "0.13.0"
SDIST_DIR = f"epc_tofcam_toolkit-{VERSION}"
VENDOR_TESTS = ("tests/tofCam635", "tests/tofCam_lib/test_tofcams.py")
#: Every TOFcam635 system test in 0.13.0 (2 in tofCam635, 14 parametrised for cam635).
EXPECTED_TESTS = 16


def _unavailable(reason: str) -> None:
    if os.environ.get("CI", "").lower() == "true":
        pytest.fail(f"vendor system tests cannot run in CI: {reason}")
    pytest.skip(reason)


def _cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "tofhil" / "vendor"


def _unpack(archive: Path, dest_parent: Path) -> Path:
    """Unpack the sdist next to where it is wanted, then rename (no half-unpacked tree left)."""
    dest = dest_parent / SDIST_DIR
    if (dest / "tests").is_dir():
        return dest
    dest_parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=dest_parent) as tmp:
        with tarfile.open(archive) as tar:
            tar.extractall(tmp, filter="data")
        try:
            os.replace(Path(tmp) / SDIST_DIR, dest)
        except OSError:  # another run unpacked it meanwhile
            if not (dest / "tests").is_dir():
                raise
    return dest


def vendor_sdist() -> Path:
    """The unpacked sdist of the vendor client (its ``tests/`` included)."""
    given = os.environ.get("TOFHIL_VENDOR_SDIST")
    if given:
        path = Path(given)
        if path.is_dir():
            return path
        if path.is_file():
            return _unpack(path, _cache_dir())
        _unavailable(f"TOFHIL_VENDOR_SDIST={given} does not exist")
    cache = _cache_dir()
    archive = cache / f"{SDIST_DIR}.tar.gz"
    if not archive.is_file():
        cache.mkdir(parents=True, exist_ok=True)
        proc = subprocess.run([sys.executable, "-m", "pip", "download", "--quiet", "--no-deps", "--no-binary", ":all:",
                               f"{VENDOR}=={VERSION}", "-d", str(cache)],
                              capture_output=True, text=True, timeout=300)
        if proc.returncode != 0 or not archive.is_file():
            _unavailable(f"pip download {VENDOR}=={VERSION} failed: {proc.stderr.strip()[-300:]}")
    return _unpack(archive, cache)


def _outcomes(junit: Path) -> dict[str, str]:
    outcomes: dict[str, str] = {}
    for case in ET.parse(junit).getroot().iter("testcase"):
        name = f"{case.get('classname')}::{case.get('name')}"
        kinds = [child.tag for child in case if child.tag in ("failure", "error", "skipped")]
        outcomes[name] = kinds[0] if kinds else "passed"
    return outcomes


@pytest.mark.slow
def test_the_vendor_system_tests_pass_on_the_emulator(tmp_path: Path) -> None:
    try:
        import epc.tofCam635  # noqa: F401
    except ImportError:
        _unavailable(f"{VENDOR} not installed (pip install --no-deps {VENDOR}=={VERSION}; see docs/drivers.md)")
    root = vendor_sdist()
    junit = tmp_path / "vendor.xml"
    with emulator_pty() as port:  # the default source: the bundled scene through the hidden truth
        env = os.environ | {"TOFHIL_PTY": port, "PYTHONPATH": str(Path(__file__).parent)}
        proc = subprocess.run([sys.executable, "-m", "pytest", "-p", "vendor_dut", "-p", "no:cacheprovider",
                               "-m", "systemTest", "-k", "cam635", f"--junitxml={junit}", "-q", *VENDOR_TESTS],
                              cwd=root, env=env, capture_output=True, text=True, timeout=600)
    assert junit.is_file(), f"the vendor tests did not run:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
    outcomes = _outcomes(junit)
    listing = "\n".join(f"  {v:8s} {k}" for k, v in sorted(outcomes.items()))
    not_passed = {k: v for k, v in outcomes.items() if v != "passed"}
    assert not not_passed and len(outcomes) == EXPECTED_TESTS, (
        f"vendor system tests: {len(outcomes)} run, {len(not_passed)} not passed\n{listing}\n{proc.stdout[-4000:]}")


def test_the_vendor_sdist_is_unpacked_atomically(tmp_path: Path) -> None:
    """The cache never holds a half-unpacked tree: unpacking twice is a no-op, the tree is whole."""
    src = tmp_path / "src" / SDIST_DIR / "tests"
    src.mkdir(parents=True)
    (src / "config.py").write_text("DUT_CONFIG = {}\n")
    archive = tmp_path / f"{SDIST_DIR}.tar.gz"
    with tarfile.open(archive, "w:gz") as tar:
        tar.add(tmp_path / "src" / SDIST_DIR, arcname=SDIST_DIR)
    out = _unpack(archive, tmp_path / "cache")
    assert (out / "tests" / "config.py").read_text() == "DUT_CONFIG = {}\n"
    assert _unpack(archive, tmp_path / "cache") == out
    assert sorted(p.name for p in (tmp_path / "cache").iterdir()) == [SDIST_DIR]
    shutil.rmtree(tmp_path / "cache")
