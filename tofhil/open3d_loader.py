"""Import Open3D on machines without a system libusb-1.0.

Open3D's binary links against ``libusb-1.0.so.0``. The ``libusb-package`` wheel ships that
library; loading it globally first lets the dynamic linker resolve Open3D's dependency by
its soname, so ``import open3d`` works on a fresh machine with no system package.
"""

from __future__ import annotations

import ctypes
import importlib
from types import ModuleType

_open3d: ModuleType | None = None


def _preload_libusb() -> None:
    try:
        ctypes.CDLL("libusb-1.0.so.0", mode=ctypes.RTLD_GLOBAL)
        return
    except OSError:
        pass
    import libusb_package

    path = libusb_package.get_library_path()
    if path is not None:
        ctypes.CDLL(str(path), mode=ctypes.RTLD_GLOBAL)


def open3d() -> ModuleType:
    """Return the imported ``open3d`` module, preloading libusb when needed."""
    global _open3d
    if _open3d is None:
        _preload_libusb()
        _open3d = importlib.import_module("open3d")
    return _open3d
