"""tofhil: hardware-in-the-loop evaluation of Time-of-Flight cameras with a simulator twin.

The core package holds what every part shares: frame types (`tofhil.frames`), the camera
model (`tofhil.camera`), demodulation and phase unwrapping (`tofhil.demod`,
`tofhil.unwrap`), bench session files (`tofhil.session`) and the CLI (the `tofhil.cli` package).
Drivers, the simulator twin and evaluation live in `tofhil.drivers`, `tofhil.sim` and
`tofhil.eval`.
"""

import os as _os

# tofhil's parallel work runs on numba's and Embree's threads; OpenBLAS's own threads on top
# of those spin and wait for a core, and the small solves of diagnosis then take 100x longer
# (a 220 x 220 ridge solve: 0.1 s instead of 1 ms with the two cores busy). BLAS runs on one
# thread unless the user chose otherwise; this must happen before numpy is first imported.
for _var in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    _os.environ.setdefault(_var, "1")


def __getattr__(name: str) -> str:
    """``tofhil.__version__``, looked up when first asked for: importlib.metadata costs
    ~0.03 CPU-s, paid by every command otherwise (``tofhil ndt`` is timed against PCL)."""
    if name != "__version__":
        raise AttributeError(f"module 'tofhil' has no attribute {name!r}")
    from importlib.metadata import PackageNotFoundError, version

    try:
        value = version("tofhil")
    except PackageNotFoundError:  # running from a source tree that is not installed
        value = "0.0.0+unknown"
    globals()["__version__"] = value
    return value


#: Speed of light in vacuum, m/s (exact, SI definition).
C_M_PER_S = 299_792_458.0

from tofhil.errors import TofhilError  # noqa: E402

__all__ = ["__version__", "C_M_PER_S", "TofhilError"]
