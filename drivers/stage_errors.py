"""Typed errors of the stage driver; every message names the port, the command and the reply."""

from __future__ import annotations

from drivers.errors import DeviceError


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


class StageBusy(StageError):
    """A move or homing was refused at once because another thread's move or homing on the same
    stage is in progress; nothing was sent and that motion goes on. ``in_progress`` names it."""

    def __init__(self, message: str, in_progress: str) -> None:
        super().__init__(message)
        self.in_progress = in_progress


class StageStopped(StageError):
    """A move or homing was ended by ``stop()`` (called from another thread). ``target_mm`` is
    the move's target (None for homing), ``position_mm`` the last polled position (None if the
    motion was stopped before it was sent). The axis was told to stop; the driver's rest
    position is unknown until the next completed move or homing."""

    def __init__(self, message: str, target_mm: float | None, position_mm: float | None) -> None:
        super().__init__(message)
        self.target_mm = target_mm
        self.position_mm = position_mm


class StagePositionUnknown(StageError):
    """The driver does not know where the axis rests: no move or homing has completed since a
    motion command was sent (an error or a stop ended it). Query ``position_mm``, or complete a
    ``move_to``/``home()``, which always start from a fresh position query."""
