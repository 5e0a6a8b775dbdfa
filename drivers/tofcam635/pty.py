"""Serve an emulated TOFcam635 on a pseudo-terminal, so any serial client can use it.

``PtyServer(emulator).start()`` opens a pty pair, keeps the slave end open itself (so the
pty survives clients opening and closing it), puts it in raw mode (no echo, no CR/LF
translation, no signal characters: the protocol is binary), and pumps bytes between the
master end and :class:`~tofhil.drivers.tofcam635.emulator.Epc635Emulator` on a background thread.
Clients open :attr:`port` (``/dev/pts/N``) with pyserial or the vendor's client.

A disconnect fault on a pty cannot unplug anything; the emulator simply stays silent and
ignores commands while it is "away", which a client sees as timeouts.
"""

from __future__ import annotations

import os
import select
import threading
import tty

from tofhil.drivers.tofcam635.emulator import Epc635Emulator


class PtyServer:
    """Pump bytes between a pseudo-terminal and an emulator on a daemon thread."""

    def __init__(self, emulator: Epc635Emulator) -> None:
        self.emulator = emulator
        self._master = -1
        self._slave = -1
        self.port = ""
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.error: BaseException | None = None

    def start(self) -> "PtyServer":
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        self.port = os.ttyname(self._slave)
        os.set_blocking(self._master, False)
        self._thread = threading.Thread(target=self._run, name="tofhil-pty", daemon=True)
        self._thread.start()
        return self

    def _run(self) -> None:
        out = bytearray()
        try:
            while not self._stop.is_set():
                want_write = [self._master] if out else []
                readable, writable, _ = select.select([self._master], want_write, [], 0.05)
                if readable:
                    try:
                        data = os.read(self._master, 65536)
                    except BlockingIOError:
                        data = b""
                    if data:
                        self.emulator.receive(data)
                        out += self.emulator.transmit()
                if writable and out:
                    try:
                        n = os.write(self._master, out[:65536])
                        del out[:n]
                    except BlockingIOError:
                        pass
                if not out and self.emulator.pending:
                    out += self.emulator.transmit()
        except OSError as exc:  # the pty went away under us
            if not self._stop.is_set():
                self.error = exc

    def serve_forever(self) -> None:
        """Block until :meth:`stop` is called (or the process is signalled)."""
        assert self._thread is not None
        while self._thread.is_alive():
            self._thread.join(0.5)

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
        for fd in (self._master, self._slave):
            if fd >= 0:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self._master = self._slave = -1

    def __enter__(self) -> "PtyServer":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
