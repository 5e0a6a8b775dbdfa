"""numba's on-disk cache, kept true to the code it inlines from other modules.

numba keys a compiled function's cache on its own source file only: a function it inlines
from another module, once changed, leaves the old machine code in use until the caller's own
file changes (numba issue 1833; its documentation's "Cache Notes"). The renderer's kernels
inline the lens models (``sim/kernels.py`` -> ``tofhil/camera_kernels.py`` ->
``tofhil/lens_models.py``), so an edited lens model would render with the old one. A module
whose kernels inline others calls :func:`drop_stale_cache` once its kernels are defined (they
compile on their first call): where the sources it inlines are not the ones its cache was
compiled against, its cache files are removed, and numba compiles anew.
"""

from __future__ import annotations

import contextlib
import hashlib
from pathlib import Path
from typing import Any, Sequence


def drop_stale_cache(kernel: Any, inlined: Sequence[str | Path]) -> bool:
    """Remove the cache files of ``kernel``'s module (``kernel``: one of its ``njit``
    dispatchers) when the source files ``inlined`` differ from those of the last call; True
    when files were removed. The digest is kept beside the cache (``<module>.inlined``); a cache
    directory that cannot be written is left as it is (numba then compiles in memory)."""
    source = Path(kernel.py_func.__code__.co_filename)
    digest = hashlib.sha256()
    for path in inlined:
        digest.update(Path(path).read_bytes())
    token = digest.hexdigest()
    cache_dir = _cache_dir(kernel, source)
    stamp = cache_dir / f"{source.stem}.inlined"
    with contextlib.suppress(OSError):
        if stamp.read_text() == token:
            return False
    removed = False
    for f in cache_dir.glob(f"{source.stem}.*.nb[ic]"):
        with contextlib.suppress(OSError):
            f.unlink()
            removed = True
    with contextlib.suppress(OSError):
        stamp.write_text(token)
    return removed


def _cache_dir(kernel: Any, source: Path) -> Path:
    """Where numba caches ``kernel`` (its own choice of locator: the source's ``__pycache__``, a
    user-wide directory when that is read-only, or ``NUMBA_CACHE_DIR``)."""
    try:
        from numba.core.caching import _CacheImpl

        return Path(_CacheImpl(kernel.py_func)._locator.get_cache_path())  # noqa: SLF001
    except Exception:  # noqa: BLE001 (a numba without this internal: the in-tree default)
        return source.parent / "__pycache__"
