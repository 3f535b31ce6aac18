"""The line exchange of a Zaber ASCII device on a serial port: open and re-open the port,
write a command, read until its reply (matching message id, device and axis), one command on
the wire at a time. Every line sent and received is logged at DEBUG on this module's logger.
:class:`drivers.stage.ZaberStage` builds its motion logic on it.
"""

from __future__ import annotations

import logging
import re
import threading
import time
from dataclasses import dataclass

import serial

from drivers.serial_lines import LineReader, SerialLike
from drivers.stage_errors import StageConnectionLost, StageProtocolError
from drivers.zaber_protocol import (
    Reply,
    ZaberChecksumError,
    ZaberFormatError,
    format_command,
    parse_reply,
)

log = logging.getLogger(__name__)

READ_SLICE_S = 0.01  # port read timeout; the line reader loops until its own deadline
INTEGER = re.compile(r"-?[0-9]+")  # a reply's integer data: no '+', '_', spaces or other digits


class _ReplyLost(Exception):
    """Internal: no reply came (``reason`` says why); ``port_ok`` when the port can be used."""

    def __init__(self, reason: str, port_ok: bool) -> None:
        super().__init__(reason)
        self.reason = reason
        self.port_ok = port_ok


@dataclass(frozen=True)
class _Exchange:
    """One command line sent and the reply line that answered it."""

    sent: str
    text: str
    reply: Reply


class ZaberLink:
    """Command/reply exchange with one Zaber device (base of :class:`~drivers.stage.ZaberStage`).

    The subclass sets, before using it: ``port_name``, ``address``, ``axis``, ``baudrate``,
    ``timeout_s`` (reply deadline, s), ``checksum``, ``_url`` (None for a port object passed
    in, which is never re-opened), ``_port``, ``_reader``, ``_lock`` (an ``RLock``),
    ``_msg_id`` and ``_closed``; and implements :meth:`_reply_lost_after_motion`.
    """

    port_name: str
    address: int
    axis: int
    baudrate: int
    timeout_s: float
    checksum: bool
    _url: str | None
    _port: SerialLike
    _reader: LineReader
    _lock: threading.RLock
    _msg_id: int
    _closed: bool

    # ----- opening -------------------------------------------------------------------------
    def _open(self) -> SerialLike:
        try:
            port = serial.serial_for_url(self._url, baudrate=self.baudrate, timeout=READ_SLICE_S)
            port.reset_input_buffer()
        except (serial.SerialException, OSError, ValueError) as exc:
            raise StageConnectionLost(f"{self.port_name}: cannot open the port: {exc}") from exc
        return port

    def _reopen(self) -> None:
        """Re-open a port given by name; raise StageConnectionLost when that is impossible."""
        if self._url is None:
            raise StageConnectionLost(
                f"{self.port_name}: a port object passed in cannot be re-opened")
        try:
            self._port.close()
        except (serial.SerialException, OSError):
            pass  # the old port is dead either way; opening a new one is what matters
        self._port = self._open()
        self._reader = LineReader(self._port)

    def _send(self, line: str) -> None:
        """Write ``line``; if the write fails, re-open and write it once more."""
        data = (line + "\n").encode("ascii")
        try:
            self._port.write(data)
            log.debug("%s: sent %r", self.port_name, line)
            return
        except (serial.SerialException, OSError) as exc:
            first = exc
            log.debug("%s: sending %r failed (%s); re-opening the port", self.port_name, line, exc)
        try:
            self._reopen()
        except StageConnectionLost as exc:
            raise StageConnectionLost(
                f"{self.port_name}: sent {line!r}: write failed ({first}); re-open failed: {exc}"
            ) from first
        try:
            self._port.write(data)
            log.debug("%s: sent %r (after re-opening the port)", self.port_name, line)
        except (serial.SerialException, OSError) as exc:
            raise StageConnectionLost(
                f"{self.port_name}: sent {line!r}: write failed ({first}), and again after "
                f"re-opening ({exc})"
            ) from exc

    def _receive(self, line: str, msg_id: int, axis: int) -> _Exchange:
        """Read lines until the reply to ``line`` (matching message id) or the deadline."""
        deadline = time.monotonic() + self.timeout_s
        while True:
            try:
                raw = self._reader.read_line(deadline)
            except (serial.SerialException, OSError) as exc:
                try:
                    self._reopen()
                except StageConnectionLost as reopen_error:
                    raise _ReplyLost(f"port failed while waiting for the reply ({exc}); "
                                     f"re-open failed: {reopen_error}", port_ok=False) from exc
                raise _ReplyLost(f"port failed while waiting for the reply ({exc}); re-opened",
                                 port_ok=True) from exc
            if raw is None:
                log.debug("%s: no reply to %r within %g s", self.port_name, line, self.timeout_s)
                raise _ReplyLost(f"no reply within {self.timeout_s:g} s", port_ok=True)
            try:
                text = raw.decode("ascii").strip()
            except UnicodeDecodeError:
                log.debug("%s: got %r (not ASCII)", self.port_name, raw)
                raise self._protocol_error(line, raw, "garbled reply (not ASCII)") from None
            log.debug("%s: got %r", self.port_name, text)
            if not text or text[0] in "#!":
                continue  # blank, info or alert line: not a reply
            try:
                reply = parse_reply(text)
            except ZaberChecksumError:
                raise self._protocol_error(line, text, "reply fails its checksum") from None
            except ZaberFormatError:
                what = ("garbled reply" if text[0] == "@"
                        else "not a Zaber ASCII reply (wrong port or baud rate?)")
                raise self._protocol_error(line, text, what) from None
            if reply.msg_id is None:
                raise self._protocol_error(line, text, "reply carries no message id")
            if reply.msg_id != msg_id:
                continue  # a late reply to an earlier command
            if (reply.address, reply.axis) != (self.address, axis):
                raise self._protocol_error(
                    line, text, f"reply from device {reply.address} axis {reply.axis}, "
                    f"expected device {self.address} axis {axis}")
            return _Exchange(line, text, reply)

    def _protocol_error(self, line: str, got: str | bytes, what: str) -> StageProtocolError:
        return StageProtocolError(f"{self.port_name}: sent {line!r}, got {got!r}: {what}")

    def _transact(self, text: str, axis: int | None = None, motion: bool = False) -> _Exchange:
        """Send one command and return its reply, under the lock (write plus read)."""
        axis = self.axis if axis is None else axis
        with self._lock:
            self._msg_id = (self._msg_id + 1) % 100
            line = format_command(text, address=self.address, axis=axis, msg_id=self._msg_id,
                                  checksum=self.checksum)
            if self._closed:
                raise StageConnectionLost(f"{self.port_name}: stage is closed; not sent: {line!r}")
            self._send(line)
            try:
                return self._receive(line, self._msg_id, axis)
            except _ReplyLost as lost:
                if not motion:
                    raise StageConnectionLost(
                        f"{self.port_name}: sent {line!r}: {lost.reason}") from None
                raise self._reply_lost_after_motion(line, lost) from None

    def _int_data(self, ex: _Exchange) -> int:
        if not INTEGER.fullmatch(ex.reply.data):
            raise self._protocol_error(ex.sent, ex.text, "expected an integer")
        return int(ex.reply.data)

    def _reply_lost_after_motion(self, line: str, lost: _ReplyLost) -> StageConnectionLost:
        """The error for a motion command whose reply was lost (the subclass queries the
        device state)."""
        raise NotImplementedError
