"""A pyserial URL handler: ``serial.serial_for_url("fakezaber://NAME")`` talks to a fake device
in-process. Nothing is registered at import; call ``register_url_handler()`` once.

Devices are looked up by ``NAME`` in a registry (``url_device(NAME)`` creates or returns one),
so a test can reach the device behind a port it opened by URL. Setting ``faults.vanish`` breaks
the open connection (its next read or write raises ``SerialException``); re-opening the URL
connects again, like a cable pulled and plugged back.
"""

from __future__ import annotations

import sys
import time
from typing import Any
from urllib.parse import urlsplit

import serial
from serial.serialutil import PortNotOpenError, SerialBase, SerialException

from fakes.zaber.device import FakeZaberDevice

SCHEME = "fakezaber"
_POLL_S = 0.001
_devices: dict[str, FakeZaberDevice] = {}


def register_url_handler() -> None:
    """Make ``fakezaber://`` URLs known to ``serial.serial_for_url``; idempotent.

    pyserial imports ``<package>.protocol_<scheme>`` for each package in
    ``serial.protocol_handler_packages``; this module is made importable under that name.
    """
    package = __name__.rpartition(".")[0]
    sys.modules.setdefault(f"{package}.protocol_{SCHEME}", sys.modules[__name__])
    if package not in serial.protocol_handler_packages:
        serial.protocol_handler_packages.append(package)


def url_device(name: str = "default", **device_kwargs: Any) -> FakeZaberDevice:
    """The device served at ``fakezaber://name``; created with ``device_kwargs`` if new."""
    if name not in _devices:
        _devices[name] = FakeZaberDevice(**device_kwargs)
    elif device_kwargs:
        raise ValueError(f"fake device {name!r} exists already; remove_url_device() it first")
    return _devices[name]


def remove_url_device(name: str = "default") -> None:
    """Forget the device served at ``fakezaber://name`` (no error if unknown)."""
    _devices.pop(name, None)


class FakeZaberSerial(SerialBase):
    """pyserial port object connected to a registered FakeZaberDevice."""

    is_open: bool  # set by SerialBase

    def open(self) -> None:
        if self.is_open:
            raise SerialException("port is already open")
        if self._port is None:
            raise SerialException("port must be configured before it can be used")
        parts = urlsplit(self._port)
        if parts.scheme != SCHEME:
            raise SerialException(f"expected {SCHEME}://NAME, got {self._port!r}")
        self.device = url_device(parts.netloc or "default")
        self._buffer = bytearray()
        self._broken = False
        self.is_open = True

    def close(self) -> None:
        self.is_open = False

    def _reconfigure_port(self) -> None:
        """Line settings mean nothing in-process."""

    def _update_dtr_state(self) -> None:
        """No modem lines in-process."""

    def _update_rts_state(self) -> None:
        """No modem lines in-process."""

    def _check_link(self) -> None:
        if not self.is_open:
            raise PortNotOpenError()
        if self.device.faults.vanish:
            self.device.faults.vanish = False
            self._broken = True
        if self._broken:
            raise SerialException(f"{self._port}: device vanished")

    def _pull(self) -> None:
        self._check_link()
        self._buffer += self.device.read_output()

    @property
    def in_waiting(self) -> int:
        self._pull()
        return len(self._buffer)

    def read(self, size: int = 1) -> bytes:
        """Up to ``size`` bytes, waiting at most ``timeout`` seconds (forever when None)."""
        deadline = None if self._timeout is None else time.monotonic() + self._timeout
        self._pull()
        while len(self._buffer) < size and (deadline is None or time.monotonic() < deadline):
            time.sleep(_POLL_S)
            self._pull()
        data = bytes(self._buffer[:size])
        del self._buffer[:size]
        return data

    def write(self, data: bytes) -> int:
        self._check_link()
        self.device.feed(bytes(data))
        return len(data)

    def reset_input_buffer(self) -> None:
        self._pull()
        self._buffer.clear()

    def reset_output_buffer(self) -> None:
        """Writes reach the device at once; nothing to drop."""

    def flush(self) -> None:
        """Writes reach the device at once; nothing to wait for."""


Serial = FakeZaberSerial  # the name pyserial looks up in a protocol module
