"""One fake Zaber device (one axis) speaking the ASCII protocol: bytes in, bytes out.

Positions are integer microsteps, speeds use the device's own units (µsteps/s is the
``maxspeed`` value / SPEED_UNIT; µsteps/s² is the ``accel`` value / ACCEL_UNIT; both units come
from ``drivers.zaber_protocol``), times come from an injectable clock.

Simplifications, stated so tests do not rely on more: one axis; a new move starts from rest
even when it interrupts another; homing drives to microstep 0 and then counts as homed; a
command with a wrong checksum is logged and ignored (no reply); a new motion clears ``FS``
and ``NI``.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

from drivers.zaber_protocol import (
    ACCEL_UNIT,
    NO_WARNING,
    SPEED_UNIT,
    Command,
    Reply,
    ZaberFormatError,
    format_reply,
    parse_command,
)
from fakes.zaber.faults import Faults
from fakes.zaber.motion import Profile

WARNING_ORDER = ("FF", "FS", "FE", "FD", "FQ", "WL", "WR", "WH", "WV", "WT", "WM", "NI", "NC", "NU")


# The device's settings a test may choose: keyword -> (Zaber setting name, default); units are
# the device's (microsteps, microsteps per 1.6384 s, ...).
SETTINGS: dict[str, tuple[str, int | str]] = {
    "device_id": ("deviceid", 50081),
    "version": ("version", "7.38"),
    "limit_min": ("limit.min", 0),
    "limit_max": ("limit.max", 1_066_666),
    "maxspeed": ("maxspeed", 153_600),
    "accel": ("accel", 2000),
}


MAX_LINE_BYTES = 256  # a command line longer than this is dropped, as a controller's buffer
MAX_PENDING_REPLIES = 1024  # replies the host has not read; more are dropped
RECEIVED_LOG_BYTES = 1 << 20  # ``received_bytes`` keeps the last this many bytes


class FakeZaberDevice:
    """A single-axis Zaber controller model. Feed it host bytes, read back its reply bytes.

    Thread-safe: a transport thread may feed and read while a test flips ``faults`` or reads
    ``position``. ``received`` logs every complete line the host sent, ``received_bytes`` the
    last ``RECEIVED_LOG_BYTES`` bytes (``received_count`` counts them all), so tests can
    assert that nothing reached the device.

    Bounded like a real controller: a line longer than ``MAX_LINE_BYTES`` is dropped up to its
    newline (``dropped_lines`` counts them), and replies beyond ``MAX_PENDING_REPLIES`` unread
    ones are dropped (``dropped_replies``), so a host that writes without reading cannot
    make it grow without limit.
    """

    def __init__(
        self,
        *,
        address: int = 1,
        position: int = 0,
        reply_checksums: bool = False,
        clock: Callable[[], float] = time.monotonic,
        faults: Faults | None = None,
        **settings: int | str,
    ) -> None:
        unknown = set(settings) - set(SETTINGS)
        if unknown:
            raise TypeError(f"FakeZaberDevice: unknown setting(s) {sorted(unknown)}; "
                            f"known: {sorted(SETTINGS)}")
        self.address = address
        self.reply_checksums = reply_checksums
        self.clock = clock
        self.faults = faults if faults is not None else Faults()
        self.settings: dict[str, int | str] = {"system.axiscount": 1}
        for name, (zaber_name, default) in SETTINGS.items():
            self.settings[zaber_name] = settings.get(name, default)
        self.received: list[str] = []
        self.received_bytes = bytearray()
        self.received_count = 0
        self.dropped_lines = 0
        self.dropped_replies = 0
        self._lock = threading.RLock()
        self._inbuf = bytearray()
        self._discarding = False  # dropping the rest of an overlong line
        self._out: list[tuple[float, int, bytes]] = []  # (release time, sequence, bytes)
        self._seq = 0
        self._pos = float(position)
        self._profile: Profile | None = None
        self._stall_pos: float | None = None
        self._homing = False
        self._homed = False
        self._flags: set[str] = set()  # latched warnings: FS, NI

    # ----- state ---------------------------------------------------------------------------
    @property
    def position(self) -> int:
        """Current position (integer microsteps)."""
        with self._lock:
            self._update()
            return round(self._pos)

    @property
    def busy(self) -> bool:
        with self._lock:
            self._update()
            return self._profile is not None

    @property
    def homed(self) -> bool:
        with self._lock:
            self._update()
            return self._homed

    @property
    def warnings(self) -> list[str]:
        """Active warnings, most serious first."""
        with self._lock:
            self._update()
            active = set(self._flags)
            if not self._homed:
                active.add("WR")
            return [w for w in WARNING_ORDER if w in active]

    # ----- byte interface ------------------------------------------------------------------
    def feed(self, data: bytes) -> None:
        """Receive bytes from the host; complete lines are executed at once."""
        with self._lock:
            self.received_count += len(data)
            self.received_bytes += data[-RECEIVED_LOG_BYTES:]
            del self.received_bytes[:-RECEIVED_LOG_BYTES]
            start = 0
            while start < len(data):
                end = data.find(b"\n", start)
                piece = data[start:] if end < 0 else data[start:end]
                start = len(data) if end < 0 else end + 1
                if not self._discarding:
                    self._inbuf += piece[:MAX_LINE_BYTES + 1 - len(self._inbuf)]
                    if len(self._inbuf) > MAX_LINE_BYTES:
                        self._inbuf.clear()
                        self._discarding = True
                        self.dropped_lines += 1
                if end < 0:
                    break
                if self._discarding:
                    self._discarding = False
                    continue
                line = self._inbuf.decode("ascii", errors="replace").strip()
                self._inbuf.clear()
                self.received.append(line)
                if line:
                    self._handle_line(line)

    def read_output(self) -> bytes:
        """Bytes the device has sent by now (unsolicited alerts included)."""
        with self._lock:
            now = self.clock()
            self._update()
            while self.faults.take("alert_lines"):
                self._emit(f"!{self.address:02d} 1 {self._status()} {self._top_warning()}", now)
            due = sorted(item for item in self._out if item[0] <= now)
            self._out = [item for item in self._out if item[0] > now]
            return b"".join(item[2] for item in due)

    # ----- commands ------------------------------------------------------------------------
    def _handle_line(self, line: str) -> None:
        try:
            cmd = parse_command(line)
        except ZaberFormatError:
            return  # not for us, or a corrupted command: a device stays silent
        if cmd.address not in (0, self.address):
            return
        self._update()
        if self.faults.vanish_on is not None and self.faults.vanish_on in cmd.text:
            self.faults.vanish_on = None
            self.faults.vanish = True
            self._execute(cmd)
            return
        flag, data = self._execute(cmd)
        if self.faults.drop_on is not None and self.faults.drop_on in cmd.text:
            self.faults.drop_on = None
            return
        self._reply(cmd, flag, data)

    def _execute(self, cmd: Command) -> tuple[str, str]:
        """Run ``cmd``; return the reply's (flag, data)."""
        if cmd.axis > int(self.settings["system.axiscount"]):
            return "RJ", "BADAXIS"
        words = cmd.text.split()
        verb, args = (words[0], words[1:]) if words else ("", [])
        if verb == "":
            return "OK", "0"
        if verb == "home":
            self._start(0.0, homing=True)
            return "OK", "0"
        if verb == "get" and len(args) == 1:
            value = self._get(args[0])
            return ("OK", value) if value is not None else ("RJ", "BADCOMMAND")
        if verb == "move" and args[:1] == ["abs"]:
            return self._move_abs(args[1:])
        if verb in ("stop", "estop") and not args:
            self._halt(abrupt=verb == "estop")
            return "OK", "0"
        if verb == "warnings" and args in ([], ["clear"]):
            active = self.warnings
            if args:
                self._flags.clear()
            return "OK", " ".join([f"{len(active):02d}", *active])
        if verb == "tools" and args[:1] == ["echo"]:
            return "OK", " ".join(args[1:]) or "0"
        return "RJ", "BADCOMMAND"

    def _get(self, name: str) -> str | None:
        if name == "pos":
            return str(round(self._pos))
        if name == "limit.home.triggered":
            return "1" if self._homed else "0"
        value = self.settings.get(name)
        return None if value is None else str(value)

    def _move_abs(self, args: list[str]) -> tuple[str, str]:
        if len(args) != 1 or not args[0].lstrip("-").isdigit():
            return "RJ", "BADDATA"
        target = int(args[0])
        if not self._homed:
            return "RJ", "BADDATA"
        if not int(self.settings["limit.min"]) <= target <= int(self.settings["limit.max"]):
            return "RJ", "BADDATA"
        self._start(float(target), homing=False)
        return "OK", "0"

    # ----- motion --------------------------------------------------------------------------
    def _start(self, target: float, *, homing: bool) -> None:
        now = self.clock()
        if self._profile is not None:
            self._pos = self._profile.state(now)[0]
            self._profile = None
        self._flags.discard("FS")
        self._flags.discard("NI")
        direction = 1.0 if target >= self._pos else -1.0
        if self.faults.stop_short:
            target = target - direction * min(self.faults.stop_short, abs(target - self._pos))
            self.faults.stop_short = 0
        self._stall_pos = None
        if self.faults.stall_at is not None:
            self._stall_pos = self._pos + (target - self._pos) * self.faults.stall_at
            self.faults.stall_at = None
        self._homing = homing
        vmax = max(int(self.settings["maxspeed"]) / SPEED_UNIT, 1.0)
        accel = max(int(self.settings["accel"]), 0) / ACCEL_UNIT  # 0: no ramp (full speed at once)
        self._profile = Profile(self._pos, target, now, vmax, accel)
        self._update()

    def _halt(self, *, abrupt: bool) -> None:
        if self._profile is None:
            return
        now = self.clock()
        self._flags.add("NI")
        self._homing = False
        if abrupt:
            self._pos = self._profile.state(now)[0]
            self._profile = None
        else:
            self._profile = self._profile.stopping(now)
        self._update()

    def _update(self) -> None:
        """Advance the motion to the clock's current time."""
        if self._profile is None:
            return
        profile = self._profile
        pos, _ = profile.state(self.clock())
        direction = 1.0 if profile.end >= profile.start else -1.0
        if self._stall_pos is not None and direction * (pos - self._stall_pos) >= 0:
            self._pos, self._profile, self._homing = self._stall_pos, None, False
            self._flags.add("FS")
            return
        self._pos = pos
        if pos == profile.end:
            self._profile = None
            if self._homing and round(pos) == 0:
                self._homed = True
            self._homing = False

    # ----- replies -------------------------------------------------------------------------
    def _status(self) -> str:
        return "BUSY" if self._profile is not None else "IDLE"

    def _top_warning(self) -> str:
        active = self.warnings
        return active[0] if active else NO_WARNING

    def _reply(self, cmd: Command, flag: str, data: str) -> None:
        faults = self.faults
        if faults.silent or faults.take("drop_replies"):
            return
        status = self._status()
        if status == "BUSY" and faults.idle_glitch and cmd.text.split()[:1] in ([], ["get"]):
            faults.idle_glitch = False
            status = "IDLE"
        reply = Reply(self.address, cmd.axis, cmd.msg_id, flag, status, self._top_warning(), data)
        line = format_reply(reply, checksum=self.reply_checksums).encode("ascii")
        if faults.take("bad_checksum_replies"):
            text = format_reply(reply, checksum=True)
            line = (text[:-2] + f"{(int(text[-2:], 16) + 1) & 0xFF:02X}").encode("ascii")
        if faults.take("garble_replies"):
            line = _garble(line)
        due = self.clock() + (faults.delay_s if faults.take("delay_replies") else 0.0)
        self._emit(line.decode("latin-1"), due)
        while faults.take("info_lines"):
            id_part = f" {cmd.msg_id:02d}" if cmd.msg_id is not None else ""
            self._emit(f"#{self.address:02d} {cmd.axis}{id_part} info from the fake", due)

    def _emit(self, line: str, due: float) -> None:
        if len(self._out) >= MAX_PENDING_REPLIES:
            self.dropped_replies += 1
            return
        self._out.append((due, self._seq, line.encode("latin-1") + b"\r\n"))
        self._seq += 1


def _garble(line: bytes) -> bytes:
    """Bit errors: set the top bit of the bytes of the OK/RJ flag."""
    out = bytearray(line)
    start = max(line.find(b" OK "), line.find(b" RJ ")) + 1
    for i in range(start, start + 2):
        out[i] |= 0x80
    return bytes(out)
