"""Line reading with a hard deadline on a serial-like port (pyserial's readline can outlive
its timeout while bytes trickle in)."""

from __future__ import annotations

import time
from typing import Protocol

MAX_LINE = 1024  # bytes without a newline handed on as one (garbled) line


class SerialLike(Protocol):
    """What the driver needs of a port object (pyserial's ``Serial`` has it all)."""

    timeout: float | None

    def write(self, data: bytes) -> int | None: ...
    def read(self, size: int = 1) -> bytes: ...
    def close(self) -> None: ...


class LineReader:
    """Reads ``\\n``-terminated lines with a hard deadline, whatever the port's own timeout."""

    def __init__(self, port: SerialLike) -> None:
        self.port = port
        self._buf = bytearray()

    def read_line(self, deadline: float) -> bytes | None:
        """The next line (terminator included), or None when ``deadline`` (monotonic s) passes.
        A line is never longer than MAX_LINE bytes: MAX_LINE bytes without a newline come back as
        one (garbled) line. Port errors propagate. Returns at the latest one port read (the
        port's ``timeout``) after the deadline."""
        while True:
            end = self._buf.find(b"\n", 0, MAX_LINE)  # a newline further on ends a later line
            if end >= 0 or len(self._buf) >= MAX_LINE:
                size = end + 1 if end >= 0 else MAX_LINE
                line = bytes(self._buf[:size])
                del self._buf[:size]
                return line
            if time.monotonic() >= deadline:
                return None
            waiting = getattr(self.port, "in_waiting", 0)
            self._buf += self.port.read(max(1, min(waiting, MAX_LINE)))
