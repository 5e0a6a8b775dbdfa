"""Progress of long work, reported without a user interface.

Library code (rendering, simulation, corrections, capture) takes a :data:`Progress` callable and
wraps its iterations in it; the CLI passes one that draws a bar. Library code never imports the
CLI, so the same functions run silently in tests, notebooks and workers.
"""

from __future__ import annotations

from typing import Iterable, Protocol, TypeVar

T = TypeVar("T")


class Progress(Protocol):
    """Wraps an iterable of ``total`` items; yields the same items while showing progress."""

    def __call__(self, items: Iterable[T], total: int, description: str) -> Iterable[T]: ...


def no_progress(items: Iterable[T], total: int, description: str) -> Iterable[T]:
    """The silent default: the items unchanged."""
    return items
