"""Zaber ASCII stage driver for one axis on a serial port (errors in ``drivers.stage_errors``;
the line exchange with the device in ``drivers.zaber_link``).

Millimetres in the API; microsteps exist only inside this module (``microstep_um`` from config).
Every error message names the port, the command sent and the reply received (or
"no reply within X s").

Threads: one command is on the wire at a time (one lock around each write-plus-read; the lock is
per command, not per move, so queries and ``stop()`` from other threads interleave with a move's
polls). One motion (``move_to`` or ``home``) at a time: a second one from another thread is
refused at once with ``StageBusy`` (nothing sent; the first goes on undisturbed), because a lab
script must never silently redirect a moving camera. ``stop()`` from another thread ends the
running motion with ``StageStopped`` in the mover's thread. After any motion that did not
complete, ``position_known`` is False until the next completed ``move_to`` or ``home``.
"""

from __future__ import annotations

import contextlib
import logging
import math
import threading
import time
from collections.abc import Iterator
from typing import Any

from drivers.errors import DeviceSettingError
from drivers.interfaces import Stage
from drivers.serial_lines import LineReader, SerialLike
from drivers.stage_errors import (
    StageBusy,
    StageConnectionLost,
    StageError,
    StageFault,
    StageLimitError,
    StageNotHomed,
    StagePositionUnknown,
    StageProtocolError,
    StageRejected,
    StageStopped,
    StageTimeout,
)
from drivers.zaber_link import READ_SLICE_S, ZaberLink, _Exchange, _ReplyLost
from drivers.zaber_protocol import ACCEL_UNIT, SPEED_UNIT

__all__ = [
    "Stage",
    "StageBusy",
    "StageConnectionLost",
    "StageError",
    "StageFault",
    "StageLimitError",
    "StageNotHomed",
    "StagePositionUnknown",
    "StageProtocolError",
    "StageRejected",
    "StageStopped",
    "StageTimeout",
    "ZaberStage",
]

log = logging.getLogger(__name__)

NOT_HOMED = ("WR", "WH")
FAULT_NAMES = {"FS": "stalled", "FE": "limit error", "FD": "driver disabled",
               "FQ": "encoder error", "FF": "critical fault"}


class ZaberStage(ZaberLink, Stage):
    """One axis of a Zaber device speaking the ASCII protocol.

    ``port`` is a device path or any URL ``serial.serial_for_url`` opens, or an open serial-like
    object (then it is never re-opened). Travel limits are the intersection of ``travel_mm``
    and the device's ``limit.min``/``limit.max``, checked before any byte is sent; targets are
    never clipped. A move is done when two consecutive polls say IDLE, within ``tolerance_um``
    of the target, with no ``F*`` fault; then (and after homing) the driver sleeps ``settle_s``.

    Deadlines: every command waits at most ``timeout_s`` for its reply. A move waits at most
    |distance|/speed + 2*speed/accel + ``margin_s`` (speed and accel read from the device; a
    device reporting ``accel 0``, Zaber's "no ramp", gets no ramp term) or
    the ``timeout`` given to ``move_to``, and at most ``no_progress_s`` without the position
    changing; on either, or on any error once the axis moves, the driver sends ``stop`` and
    raises. So a call returns within its move deadline + 2 * ``timeout_s`` (+ ``settle_s``).

    Lost connection policy: when the port fails, it is re-opened (ports given by name only).
    A command is re-sent only when writing it failed. When the reply to ``home`` or
    ``move abs`` is lost, the command is not re-sent: the driver queries position and status
    and raises StageConnectionLost carrying them (``position_mm``, ``busy``), without stopping
    the axis; the caller decides (wait with move_to to the same target, stop(), or give up).

    Threads: any thread may call any method; each command's write-plus-read holds one lock, so
    bytes of two commands never interleave and ``position_mm`` or ``stop()`` from another thread
    get on the wire between a move's polls (waiting at most one command's ``timeout_s``).
    Policy for motions: one ``move_to``/``home`` at a time per stage. A second one, from any
    thread, raises ``StageBusy`` at once, naming the port and the motion in progress; nothing is
    sent and the first motion completes as if nothing happened. ``stop()`` from another thread
    sends ``stop`` at once and makes the running motion raise ``StageStopped`` (naming the port
    and the target) in its own thread at its next poll, within ``poll_s`` + 2 * ``timeout_s``.

    Rest position: ``position_known`` is True, and ``last_position_mm`` the position where the
    axis rests, only after a completed ``move_to`` or ``home`` with no motion command sent since.
    Sending ``move abs`` or ``home`` makes it unknown until that motion completes; so after any
    error or stop during a motion the position is explicitly unknown (``last_position_mm``
    raises StagePositionUnknown) until the next completed motion. ``move_to`` and ``home`` never
    rely on it: each starts from a fresh ``get pos``. A refused motion (StageBusy, StageLimitError)
    changes nothing.
    """

    def __init__(
        self,
        port: str | SerialLike,
        *,
        baudrate: int = 115200,
        address: int = 1,
        axis: int = 1,
        microstep_um: float,
        travel_mm: tuple[float, float],
        tolerance_um: float = 1.0,
        timeout_s: float = 1.0,
        settle_s: float = 0.0,
        poll_s: float = 0.02,
        margin_s: float = 1.0,
        no_progress_s: float = 1.0,
        checksum: bool = True,
    ) -> None:
        checks = {
            "microstep_um must be > 0": microstep_um > 0,
            "tolerance_um must be > 0": tolerance_um > 0,
            "timeout_s, poll_s and no_progress_s must be > 0":
                min(timeout_s, poll_s, no_progress_s) > 0,
            "settle_s and margin_s must be >= 0": min(settle_s, margin_s) >= 0,
            "travel_mm must be (low, high) with low < high": travel_mm[0] < travel_mm[1],
        }
        for message, ok in checks.items():
            if not ok:
                raise DeviceSettingError(f"ZaberStage: {message}")
        self.address, self.axis, self.baudrate = address, axis, baudrate
        self.microstep_um, self.tolerance_um = microstep_um, tolerance_um
        self.travel_mm = (float(travel_mm[0]), float(travel_mm[1]))
        self.timeout_s, self.settle_s, self.poll_s = timeout_s, settle_s, poll_s
        self.margin_s, self.no_progress_s, self.checksum = margin_s, no_progress_s, checksum
        self._lock = threading.RLock()  # one command (write plus read) at a time
        self._state_lock = threading.Lock()  # guards _motion and _stop_requested
        self._motion: str | None = None  # the move or homing in progress, e.g. "move to 5 mm"
        self._stop_requested = threading.Event()  # set by stop() while a motion is in progress
        self._rest_steps: int | None = None  # where the axis rests, None when unknown
        self._unknown_why = "no move or homing has completed yet"
        self._msg_id = 0
        self._closed = False
        self._url = port if isinstance(port, str) else None
        self.port_name = self._url or str(getattr(port, "port", None) or type(port).__name__)
        self._port: SerialLike = self._open() if isinstance(port, str) else port
        self._port.timeout = READ_SLICE_S
        self._reader = LineReader(self._port)
        ready = False
        try:
            self._identify()
            ready = True
        finally:
            if not ready:
                self.close()

    def _identify(self) -> None:
        """Check the port speaks Zaber; read identity, limits, speed and acceleration."""
        self.device_id = self._get_int("deviceid", axis=0)
        self.firmware_version = self._command("get version", axis=0).reply.data
        self.axis_count = self._get_int("system.axiscount", axis=0)
        low, high = self._get_int("limit.min"), self._get_int("limit.max")
        self.device_limits_mm = (self._mm(low), self._mm(high))
        maxspeed, accel = self._get_int("maxspeed"), self._get_int("accel")
        self.speed_steps_s = maxspeed / SPEED_UNIT
        self.accel_steps_s2 = accel / ACCEL_UNIT  # 0: no ramp, full speed at once (Zaber)
        if maxspeed <= 0 or accel < 0:
            raise StageProtocolError(
                f"{self.port_name}: sent 'get maxspeed' and 'get accel', got {maxspeed} and "
                f"{accel}: the device cannot move, so no move timeout can be computed"
            )
        self._limits = (max(self.travel_mm[0], self.device_limits_mm[0]),
                        min(self.travel_mm[1], self.device_limits_mm[1]))
        if self._limits[0] > self._limits[1]:
            raise StageLimitError(
                f"{self.port_name}: configured travel {self.travel_mm} mm does not overlap the "
                f"device limits {self.device_limits_mm} mm (sent 'get limit.min'/'get limit.max', "
                f"got {low}/{high} microsteps)"
            )

    # ----- transport -----------------------------------------------------------------------
    def _reply_lost_after_motion(self, line: str, lost: _ReplyLost) -> StageConnectionLost:
        position = busy = None
        state = "device state unknown"
        if lost.port_ok:
            try:
                ex = self._transact("get pos")
                position, busy = self._mm(self._int_data(ex)), ex.reply.busy
                state = (f"then sent {ex.sent!r}, got {ex.text!r}: device {ex.reply.status} at "
                         f"{position:.6g} mm, warning {ex.reply.warning}")
            except StageError as exc:
                state = f"the state query failed too ({exc})"
        return StageConnectionLost(
            f"{self.port_name}: sent {line!r}: {lost.reason}; the motion command was not re-sent "
            f"and may or may not be under way; {state}",
            position_mm=position,
            busy=busy,
        )

    # ----- commands ------------------------------------------------------------------------
    def _command(self, text: str, axis: int | None = None, motion: bool = False) -> _Exchange:
        """Send ``text``; raise StageNotHomed/StageRejected on RJ, StageFault on motion + F*."""
        ex = self._transact(text, axis, motion)
        if ex.reply.rejected:
            if motion and ex.reply.warning in NOT_HOMED:
                raise StageNotHomed(f"{self.port_name}: sent {ex.sent!r}, got {ex.text!r}: "
                                    "the stage has no reference position; call home() first")
            raise StageRejected(f"{self.port_name}: sent {ex.sent!r}, got {ex.text!r}: "
                                f"rejected ({ex.reply.data})", ex.reply.data)
        if motion:
            self._raise_if_fault(ex)
        return ex

    def _get_int(self, setting: str, axis: int | None = None) -> int:
        return self._int_data(self._command(f"get {setting}", axis))

    def _raise_if_fault(self, ex: _Exchange) -> None:
        if ex.reply.fault:
            name = FAULT_NAMES.get(ex.reply.warning, "fault")
            stopped = self._stop_quietly()
            raise StageFault(f"{self.port_name}: sent {ex.sent!r}, got {ex.text!r}: "
                             f"{ex.reply.warning} {name}; {stopped}", ex.reply.warning)

    def _stop_quietly(self) -> str:
        """Stop the axis after an error; say how that went (a failed stop never hides the error)."""
        try:
            self._transact("stop")
        except StageError as exc:
            return f"stopping the axis failed too ({exc})"
        return "axis stopped"

    def _mm(self, steps: int | float) -> float:
        return steps * self.microstep_um / 1000.0

    def _target_steps(self, z_mm: float) -> int:
        """Microsteps for ``z_mm``; raise StageLimitError (nothing sent) when not allowed."""
        low, high = self._limits
        if not (math.isfinite(z_mm) and low <= z_mm <= high):
            raise StageLimitError(f"{self.port_name}: target {z_mm} mm is outside the allowed "
                                  f"travel [{low:g}, {high:g}] mm; nothing sent")
        steps = round(z_mm * 1000.0 / self.microstep_um)
        error_um = abs(steps * self.microstep_um - z_mm * 1000.0)
        if error_um > self.tolerance_um:
            raise StageLimitError(
                f"{self.port_name}: target {z_mm} mm is not representable: the nearest microstep "
                f"({steps}) is {error_um:.3g} um away, tolerance {self.tolerance_um:g} um; "
                "nothing sent")
        return steps

    def _motion_time(self, distance_steps: float) -> float:
        """Move deadline (s): |distance|/speed + 2*speed/accel + margin; with accel 0 (no ramp:
        the device starts and stops at full speed) |distance|/speed + margin."""
        ramp = 0.0 if self.accel_steps_s2 == 0 else 2 * self.speed_steps_s / self.accel_steps_s2
        return abs(distance_steps) / self.speed_steps_s + ramp + self.margin_s

    def move_deadline_s(self, distance_mm: float) -> float:
        """Deadline (s) the driver gives a move of ``distance_mm`` (mm) when no ``timeout`` is
        passed to ``move_to``: |distance|/speed + 2*speed/accel (0 with accel 0) + margin_s."""
        return self._motion_time(distance_mm * 1000.0 / self.microstep_um)

    @contextlib.contextmanager
    def _motion_slot(self, what: str) -> Iterator[None]:
        """Hold the one motion slot for ``what``; StageBusy (nothing sent) when it is taken."""
        with self._state_lock:
            if self._motion is not None:
                raise StageBusy(f"{self.port_name}: {what} refused: {self._motion} is in progress "
                                "(started by another thread); nothing sent", self._motion)
            self._motion = what
            self._stop_requested.clear()
        try:
            yield
        except BaseException as exc:
            if self._rest_steps is None:
                self._unknown_why = f"{what} ended with {type(exc).__name__}: {exc}"
            raise
        finally:
            with self._state_lock:
                self._motion = None
                self._stop_requested.clear()

    def _motion_sent(self, what: str, target: int | None) -> None:
        """Called just before a motion command is sent: raise StageStopped if stop() came
        first (nothing sent); else forget the rest position until the motion completes."""
        if self._stop_requested.is_set():
            goal = "home" if target is None else f"{self._mm(target):.6g} mm"
            raise StageStopped(f"{self.port_name}: {what} was stopped by stop() before it was "
                               f"sent (target {goal}); nothing moved", self._target_mm(target),
                               None)
        self._rest_steps = None
        self._unknown_why = f"{what} is under way"

    def _target_mm(self, target: int | None) -> float | None:
        return None if target is None else self._mm(target)

    def _wait(self, target: int | None, duration: float, started_by: str) -> int:
        """Poll until done (see class docstring); return the position in microsteps.
        ``target`` None (homing): done when IDLE without fault on two consecutive polls."""
        start = time.monotonic()
        idle_polls, last_pos, last_change = 0, None, start
        while True:
            try:
                ex = self._command("get pos")
                pos = self._int_data(ex)
            except StageError as exc:
                exc.args = (f"{exc}; {self._stop_quietly()}",)
                raise
            self._raise_if_fault(ex)
            goal = "home" if target is None else f"{self._mm(target):.6g} mm"
            if self._stop_requested.is_set():
                stopped = self._stop_quietly()
                raise StageStopped(
                    f"{self.port_name}: {started_by!r} (target {goal}) was stopped by stop() from "
                    f"another thread: last sent {ex.sent!r}, got {ex.text!r} (device "
                    f"{ex.reply.status} at {self._mm(pos):.6g} mm); {stopped}; position unknown "
                    "until the next completed move or homing", self._target_mm(target),
                    self._mm(pos))
            at_target = target is None or abs(pos - target) * self.microstep_um <= self.tolerance_um
            idle_polls = idle_polls + 1 if (at_target and not ex.reply.busy) else 0
            if idle_polls >= 2:
                return pos
            now = time.monotonic()
            if pos != last_pos:
                last_pos, last_change = pos, now
            problem = None
            if now - last_change > self.no_progress_s:
                problem = f"no progress for {self.no_progress_s:g} s"
            elif now - start > duration:
                problem = (f"not done within {duration:.3g} s "
                           "(raise the timeout, or check maxspeed/accel)")
            if problem:
                stopped = self._stop_quietly()
                raise StageTimeout(
                    f"{self.port_name}: {started_by!r} {problem}: last sent {ex.sent!r}, got "
                    f"{ex.text!r} (device {ex.reply.status} at {self._mm(pos):.6g} mm, "
                    f"target {goal}); {stopped}")
            self._stop_requested.wait(self.poll_s)  # a stop() wakes the poll loop at once

    # ----- Stage interface -----------------------------------------------------------------
    def home(self) -> None:
        """Home the axis and wait; raise StageNotHomed if the device is still not referenced,
        StageBusy (nothing sent) while another thread's motion runs, StageStopped on stop()."""
        with self._motion_slot("home"):
            self._motion_sent("home", None)
            ex = self._command("home", motion=True)
            low, high = self.device_limits_mm
            final = self._wait(None, self._motion_time((high - low) * 1000.0 / self.microstep_um),
                               ex.sent)
            check = self._command("get limit.home.triggered")
            if check.reply.data != "1":
                raise StageNotHomed(f"{self.port_name}: homing ended but sent {check.sent!r}, "
                                    f"got {check.text!r}: no reference position")
            self._rest_steps = final
            log.debug("%s: homed at %.6g mm", self.port_name, self._mm(final))
            time.sleep(self.settle_s)

    def move_to(self, z_mm: float, timeout: float | None = None) -> float:
        """Move to ``z_mm`` (mm), wait until done and settled; return the measured position (mm).
        ``timeout`` (s) replaces the computed move deadline. Raises StageBusy (nothing sent)
        while another thread's motion runs, StageStopped when stop() ends it."""
        target = self._target_steps(z_mm)
        what = f"move to {z_mm:g} mm"
        with self._motion_slot(what):
            before = self._command("get pos")
            pos, r = self._int_data(before), before.reply
            if (pos == target == self._rest_steps and not r.busy and not r.fault
                    and r.warning not in NOT_HOMED):
                return self._mm(pos)  # zero-length move from a known rest position: done at once
            self._motion_sent(what, target)
            ex = self._command(f"move abs {target}", motion=True)
            duration = self._motion_time(target - pos) if timeout is None else timeout
            final = self._wait(target, duration, ex.sent)
            self._rest_steps = final
            log.debug("%s: %s: done at %.6g mm", self.port_name, what, self._mm(final))
            time.sleep(self.settle_s)
            return self._mm(final)

    @property
    def position_mm(self) -> float:
        """Measured position (mm), queried from the device; valid while moving."""
        return self._mm(self._get_int("pos"))

    @property
    def position_known(self) -> bool:
        """True when the axis rests at ``last_position_mm`` (see the class docstring)."""
        return self._rest_steps is not None

    @property
    def last_position_mm(self) -> float:
        """Where the last completed move or homing left the axis (mm), without asking the device;
        raise StagePositionUnknown when a motion was sent since and did not complete."""
        steps = self._rest_steps
        if steps is None:
            raise StagePositionUnknown(f"{self.port_name}: rest position unknown: "
                                       f"{self._unknown_why}; query position_mm, or move_to/home")
        return self._mm(steps)

    @property
    def limits_mm(self) -> tuple[float, float]:
        """Allowed travel (low, high) in mm: configured travel ∩ device limits."""
        return self._limits

    @property
    def is_homed(self) -> bool:
        return self._get_int("limit.home.triggered") == 1

    def stop(self) -> None:
        """Decelerate to a stop now (returns once the device accepted the command). A move or
        homing running in another thread then raises StageStopped there."""
        with self._state_lock:
            if self._motion is not None:
                self._stop_requested.set()
        self._command("stop")

    def close(self) -> None:
        """Close the port; idempotent."""
        with self._lock:
            if not self._closed:
                self._closed = True
                self._port.close()

    def describe(self) -> dict[str, Any]:
        """Identity and settings for run metadata (mm, s, um)."""
        return {
            "type": type(self).__name__,
            "port": self.port_name,
            "address": self.address,
            "axis": self.axis,
            "device_id": self.device_id,
            "firmware_version": self.firmware_version,
            "axis_count": self.axis_count,
            "device_limits_mm": self.device_limits_mm,
            "travel_mm": self.travel_mm,
            "limits_mm": self._limits,
            "microstep_um": self.microstep_um,
            "tolerance_um": self.tolerance_um,
            "maxspeed_mm_s": self._mm(self.speed_steps_s),
            "accel_mm_s2": self._mm(self.accel_steps_s2),
            "timeout_s": self.timeout_s,
            "settle_s": self.settle_s,
            "checksum": self.checksum,
        }
