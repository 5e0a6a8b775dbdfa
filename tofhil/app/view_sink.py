"""A non-blocking hand-off from a producer (the capture loop) to a slow consumer (the viewer).

The capture loop must never wait on the viewer: a camera frame that is not read in time is
lost at the device, a view frame is not. :class:`DroppingSink` holds a bounded queue (2 by
default) that one consumer thread drains; :meth:`DroppingSink.offer` puts a frame in without
waiting and drops it when the queue is full. A consumer that raises is stopped (its error is
kept) and every later frame is dropped, so a viewer that closed or failed costs the capture
nothing but a failed ``put``. The counts say what the viewer saw: ``offered``, ``consumed``,
``dropped`` (full queue, stopped consumer, or left unconsumed at close).
"""

from __future__ import annotations

import queue
import threading
from dataclasses import dataclass
from typing import Callable, Generic, TypeVar

T = TypeVar("T")

_STOP = object()  # the sentinel that ends the consumer thread


@dataclass(frozen=True)
class SinkStats:
    """What a :class:`DroppingSink` did with the frames it was offered."""

    offered: int
    consumed: int
    dropped: int
    #: The consumer's error (``"ExcType: message"``) if it stopped on one, else None.
    error: str | None = None
    #: True when :meth:`DroppingSink.close` gave up waiting for the consumer.
    timed_out: bool = False


class DroppingSink(Generic[T]):
    """Hand items to ``consume`` on a thread of its own; never block the producer."""

    def __init__(self, consume: Callable[[T], None], *, maxsize: int = 2, name: str = "tofhil-view") -> None:
        if maxsize < 1:
            raise ValueError("maxsize must be >= 1")
        self._consume = consume
        self._queue: queue.Queue = queue.Queue(maxsize=maxsize)
        self._lock = threading.Lock()
        self._offered = 0
        self._consumed = 0
        self._error: str | None = None
        self._closed = False
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)  # never keeps the process alive
        self._thread.start()

    # ------------------------------------------------------------------ producer side
    def offer(self, item: T) -> bool:
        """Queue ``item`` for the consumer if there is room; False if it was dropped. Never
        blocks and never raises (safe to call from the capture loop)."""
        with self._lock:
            self._offered += 1
            if self._closed or self._error is not None:
                return False
        try:
            self._queue.put_nowait(item)
        except queue.Full:
            return False
        return True

    def close(self, timeout_s: float = 30.0) -> SinkStats:
        """Let the consumer finish what is queued (at most ``timeout_s``), stop it and count."""
        with self._lock:
            self._closed = True
        timed_out = False
        try:
            self._queue.put(_STOP, timeout=timeout_s)
            self._thread.join(timeout_s)
            timed_out = self._thread.is_alive()
        except queue.Full:
            timed_out = True
        return self.stats(timed_out=timed_out)

    def stats(self, *, timed_out: bool = False) -> SinkStats:
        with self._lock:
            return SinkStats(self._offered, self._consumed, self._offered - self._consumed, self._error, timed_out)

    @property
    def error(self) -> str | None:
        return self._error

    # ------------------------------------------------------------------ consumer side
    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if item is _STOP:
                return
            if self._error is not None:
                continue  # stopped: drain and drop until told to end
            try:
                self._consume(item)
            except Exception as exc:  # a failed viewer stops the view, never the capture
                with self._lock:
                    self._error = f"{type(exc).__name__}: {exc}"
                continue
            with self._lock:
                self._consumed += 1
