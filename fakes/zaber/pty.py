"""Serve a FakeZaberDevice on a real pseudo-terminal, so a driver opens a real tty."""

from __future__ import annotations

import os
import select
import threading
import tty

from fakes.zaber.device import FakeZaberDevice

POLL_S = 0.002  # how often the server looks for due output (s)
MAX_UNSENT_BYTES = 64 << 10  # output the host has not read from the pty; more is dropped


class FakeZaberPty:
    """A pty whose far end is ``device``. Open ``.port`` with pyserial like a real port.

    The server never blocks: output the host does not read waits in a buffer of
    ``MAX_UNSENT_BYTES``, beyond which it is dropped (``dropped_bytes``), as a controller drops
    replies it cannot send.

    The device stays silent until the host sends a command. Setting ``device.faults.vanish``
    closes the pty: the host then sees ``SerialException`` and the port cannot be re-opened.
    """

    def __init__(self, device: FakeZaberDevice | None = None) -> None:
        self.device = device if device is not None else FakeZaberDevice()
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        self.port: str = os.ttyname(self._slave)
        self.vanished = False  # set once the ``vanish`` fault closed the pty
        self.dropped_bytes = 0  # output dropped because the host did not read it
        self._unsent = bytearray()
        os.set_blocking(self._master, False)  # a host that never reads cannot block the server
        self._stop = threading.Event()
        self._thread = threading.Thread(
            target=self._serve, name=f"fake-zaber {self.port}", daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        while not self._stop.is_set():
            if self.device.faults.vanish:
                self.device.faults.vanish = False
                self._close_fds()
                self.vanished = True
                return
            readable, _, _ = select.select([self._master], [], [], POLL_S)
            if readable:  # the server holds the slave side open, so this never sees EIO
                try:
                    self.device.feed(os.read(self._master, 4096))
                except BlockingIOError:
                    pass
            self._unsent += self.device.read_output()
            if len(self._unsent) > MAX_UNSENT_BYTES:  # like a controller's full output buffer
                self.dropped_bytes += len(self._unsent) - MAX_UNSENT_BYTES
                del self._unsent[MAX_UNSENT_BYTES:]
            if self._unsent:
                try:
                    del self._unsent[:os.write(self._master, self._unsent)]
                except BlockingIOError:
                    pass

    def _close_fds(self) -> None:
        for fd in (self._master, self._slave):
            if fd >= 0:
                os.close(fd)
        self._master = self._slave = -1

    def close(self) -> None:
        """Stop serving and close the pty; idempotent."""
        self._stop.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)
        self._close_fds()

    def __enter__(self) -> FakeZaberPty:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
