"""The one content digest and the one bounded LRU map the simulator's caches use."""

from __future__ import annotations

import dataclasses

import numpy as np

from tofhil.content_cache import LRUCache, content_digest


def test_digest_is_of_content_not_identity_or_order():
    assert content_digest({"a": 1, "b": [2.0, "x"]}) == content_digest({"b": [2.0, "x"], "a": 1})
    a = np.arange(12.0).reshape(3, 4)
    assert content_digest(a) == content_digest(a.copy()) == content_digest(np.asfortranarray(a))
    assert content_digest(a) != content_digest(a.astype(np.float32))
    assert content_digest(a) != content_digest(a.reshape(4, 3))
    assert content_digest(1) != content_digest(1.0) != content_digest("1")
    assert content_digest(np.zeros(2, "M8[s]")) == content_digest(np.zeros(2, "M8[s]"))  # (no buffer export)


def test_digest_leaves_out_the_fields_it_is_told_to():
    @dataclasses.dataclass
    class Thing:
        value: float
        label: str

    a, b = Thing(1.0, "a"), Thing(1.0, "b")
    assert content_digest(a) != content_digest(b)
    assert content_digest(a, skip_fields={Thing: {"label"}}) == content_digest(b, skip_fields={Thing: {"label"}})


def test_lru_bounds_entries_and_keeps_the_newest():
    c = LRUCache(2)
    for k in "abc":
        c.put(k, k.upper())
    assert list(c) == ["b", "c"]
    assert c.get("b") == "B" and list(c) == ["c", "b"]  # a hit is the most recently used
    c.put("d", "D")
    assert list(c) == ["b", "d"] and c.get("c") is None and c.get("c", 0) == 0


def test_lru_byte_bound_and_pins():
    c = LRUCache(8, 30, nbytes=len, max_pinned=1)
    c.put("base", "x" * 100, pin=True)  # pinned: not counted, never dropped
    c.put("p2", "y", pin=True)          # only one pin: an ordinary entry
    for i in range(4):
        c.put(f"r{i}", "z" * 10)
    assert list(c) == ["base", "r1", "r2", "r3"]
    c.put("big", "w" * 100)             # larger than the budget: kept while it is the newest
    assert list(c) == ["base", "big"]
    c.clear()
    assert len(c) == 0 and not c.pinned


def test_make_room_drops_before_a_new_entry_is_built():
    c = LRUCache(1)
    c.put("a", 1)
    c.make_room()
    assert len(c) == 0
    c.put("b", 2)
    assert "b" in c and len(c) == 1
