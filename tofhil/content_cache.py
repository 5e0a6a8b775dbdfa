"""Content-keyed caches: a digest of what values hold, and a bounded least-recently-used map.

The simulator keeps work it may be asked for again -- renders (``sim/twin.py``), Embree
scenes and per-pixel camera arrays (``sim/render.py``), the transforms and results of the
stray-light lobes (``sim/straylight/lobes.py``), traced lens models (``sim/optics.py``). They
share two things, both here:

- :func:`content_digest`: a SHA-256 hex digest of what values *hold* (numbers, strings,
  arrays, mappings, sequences, dataclasses, meshes), not of which Python objects they are:
  equal content gives equal keys, whatever object identity or dictionary order.
- :class:`LRUCache`: least recently used first out, bounded in entries and, optionally, in
  bytes, with optionally some entries pinned (kept whatever the bounds).

Core module: numpy and the standard library only.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import threading
from collections import OrderedDict
from typing import Any, Callable, Collection, Hashable, Iterator, Mapping

import numpy as np

#: Per dataclass type, the fields :func:`content_digest` leaves out (e.g. the fields of a
#: scene that do not change a render).
SkipFields = Mapping[type, Collection[str]]


def content_digest(*parts: Any, skip_fields: SkipFields | None = None) -> str:
    """A SHA-256 hex digest of what ``parts`` hold, recursively: numbers, strings, arrays
    (dtype, shape and bytes), mappings (in sorted key order), sequences, dataclasses (field by
    field, less ``skip_fields[type]`` for an instance of that type) and meshes (anything with
    ``vertices`` and ``faces``: its triangles); anything else by its type and ``repr``."""
    h = hashlib.sha256()
    for p in parts:
        _feed(h, p, skip_fields or {})
    return h.hexdigest()


def _array_bytes(x: np.ndarray) -> Any:
    """The bytes of an array in C order, without a copy where numpy can export its buffer."""
    c = np.ascontiguousarray(x)
    try:
        return c.data
    except ValueError:  # (a dtype numpy does not export, e.g. datetime64)
        return c.tobytes()


def _feed(h: Any, x: Any, skip_fields: SkipFields) -> None:
    if x is None or isinstance(x, (bool, int, float, complex, str, np.generic)):
        h.update(f"{type(x).__name__}:{x!r};".encode())
    elif isinstance(x, np.ndarray):
        h.update(f"nd:{x.dtype.str}:{x.shape};".encode())
        h.update(_array_bytes(x) if x.dtype != object else repr(x.tolist()).encode())
    elif isinstance(x, Mapping):
        h.update(f"map:{len(x)};".encode())
        for k in sorted(x, key=repr):
            _feed(h, k, skip_fields)
            _feed(h, x[k], skip_fields)
    elif isinstance(x, (list, tuple)):
        h.update(f"seq:{len(x)};".encode())
        for v in x:
            _feed(h, v, skip_fields)
    elif dataclasses.is_dataclass(x) and not isinstance(x, type):
        h.update(f"dc:{type(x).__qualname__};".encode())
        skip: set[str] = set()
        for t, names in skip_fields.items():
            if isinstance(x, t):
                skip.update(names)
        for f in dataclasses.fields(x):
            if f.name not in skip:
                h.update(f"{f.name}=".encode())
                _feed(h, getattr(x, f.name), skip_fields)
    elif hasattr(x, "vertices") and hasattr(x, "faces"):  # a trimesh mesh: its triangles
        h.update(b"mesh;")
        _feed(h, np.asarray(x.vertices), skip_fields)
        _feed(h, np.asarray(x.faces), skip_fields)
    else:
        h.update(f"{type(x).__qualname__}:{x!r};".encode())


class LRUCache:
    """A map ``key -> value``, least recently used first out.

    Bounded in entries (``max_entries``) and, with ``nbytes`` (a value's size), in bytes
    (``max_bytes``); None = no bound. Only the unpinned entries count against the bounds, and
    the newest of them is always kept (a value larger than the whole byte budget stays until
    the next one comes). ``put(..., pin=True)`` pins an entry while fewer than
    ``max_pinned`` are. ``thread_safe``: every operation under a lock (caches shared by the
    renderer's threads).
    """

    def __init__(self, max_entries: int | None = None, max_bytes: int | None = None, *,
                 nbytes: Callable[[Any], int] | None = None, max_pinned: int = 0,
                 thread_safe: bool = False) -> None:
        if max_bytes is not None and nbytes is None:
            raise ValueError("a byte bound needs the size of a value (nbytes)")
        self.max_entries = max_entries
        self.max_bytes = max_bytes
        self.max_pinned = max_pinned
        self._size_of = nbytes
        self.entries: OrderedDict[Hashable, Any] = OrderedDict()
        self.pinned: set[Hashable] = set()
        self._nbytes: dict[Hashable, int] = {}
        self._lock: Any = threading.Lock() if thread_safe else contextlib.nullcontext()

    def get(self, key: Hashable, default: Any = None) -> Any:
        """The value of ``key`` (now the most recently used), or ``default``."""
        with self._lock:
            v = self.entries.get(key)
            if v is None:
                return default
            self.entries.move_to_end(key)
            return v

    def put(self, key: Hashable, value: Any, *, pin: bool = False) -> None:
        """Keep ``value`` under ``key`` as the most recently used; then drop the least recently
        used unpinned entries while the bounds are exceeded (never the newest)."""
        with self._lock:
            self.entries[key] = value
            self.entries.move_to_end(key)
            if self._size_of is not None:
                self._nbytes[key] = self._size_of(value)
            if pin and len(self.pinned) < self.max_pinned:
                self.pinned.add(key)
            unpinned = [k for k in self.entries if k not in self.pinned]
            held = sum(self._nbytes[k] for k in unpinned) if self.max_bytes is not None else 0
            while unpinned[:-1] and ((self.max_entries is not None and len(unpinned) > self.max_entries)
                                     or (self.max_bytes is not None and held > self.max_bytes)):
                oldest = unpinned.pop(0)
                held -= self._nbytes.pop(oldest, 0)
                del self.entries[oldest]

    def make_room(self) -> None:
        """Drop the least recently used unpinned entries until one more fits the entry bound:
        called before building a large value, so that the old ones are gone first (never two
        of them in memory at once)."""
        if self.max_entries is None:
            return
        with self._lock:
            unpinned = [k for k in self.entries if k not in self.pinned]
            while unpinned and len(unpinned) >= self.max_entries:
                oldest = unpinned.pop(0)
                self._nbytes.pop(oldest, None)
                del self.entries[oldest]

    def clear(self) -> None:
        """Drop every entry (the pinned ones too)."""
        with self._lock:
            self.entries.clear()
            self.pinned.clear()
            self._nbytes.clear()

    def __len__(self) -> int:
        return len(self.entries)

    def __iter__(self) -> Iterator[Hashable]:
        """The keys, least recently used first."""
        return iter(list(self.entries))

    def __contains__(self, key: Hashable) -> bool:
        return key in self.entries
