"""tofhil: hardware-in-the-loop evaluation of Time-of-Flight cameras with a simulator twin.

The core package holds what every part shares: frame types (`tofhil.frames`), the camera
model (`tofhil.camera`), demodulation and phase unwrapping (`tofhil.demod`,
`tofhil.unwrap`), bench session files (`tofhil.session`) and the CLI (the `tofhil.cli` package).
Drivers, the simulator twin and evaluation live in `tofhil.drivers`, `tofhil.sim` and
`tofhil.eval`.
"""

from importlib.metadata import PackageNotFoundError, version as _dist_version

try:
    __version__ = _dist_version("tofhil")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0+unknown"

#: Speed of light in vacuum, m/s (exact, SI definition).
C_M_PER_S = 299_792_458.0

from tofhil.errors import TofhilError  # noqa: E402

__all__ = ["__version__", "C_M_PER_S", "TofhilError"]
