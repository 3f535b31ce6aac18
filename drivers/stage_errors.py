"""Typed errors of the stage driver; every message names the port, the command and the reply."""

from __future__ import annotations

from drivers.interfaces import DeviceError


class StageError(DeviceError):
    """Any stage failure."""


class StageRejected(StageError):
    """The device answered RJ; ``reason`` is its reason (BADDATA, BADCOMMAND, PARKED, ...)."""

    def __init__(self, message: str, reason: str) -> None:
        super().__init__(message)
        self.reason = reason


class StageFault(StageError):
    """The device reports an ``F*`` fault; ``warning`` is the flag (FS, FE, ...)."""

    def __init__(self, message: str, warning: str) -> None:
        super().__init__(message)
        self.warning = warning


class StageTimeout(StageError):
    """A move or homing did not finish in time, or made no progress; the axis was stopped."""


class StageLimitError(StageError):
    """Target refused on the host, before sending: outside the travel or not representable."""


class StageNotHomed(StageError):
    """The stage has no reference position (home() it first), or homing did not give one."""


class StageConnectionLost(StageError):
    """The port failed or a reply never came. After a lost reply to a motion command,
    ``position_mm`` and ``busy`` hold the device state queried afterwards (None if unknown)."""

    def __init__(self, message: str, position_mm: float | None = None, busy: bool | None = None):
        super().__init__(message)
        self.position_mm = position_mm
        self.busy = busy


class StageProtocolError(StageError):
    """A reply that is garbled, fails its checksum, does not match the command, or is not Zaber."""
